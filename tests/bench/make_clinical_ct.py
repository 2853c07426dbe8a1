#!/usr/bin/python3
"""Makes clinical-size CT volumes from the shared CT head by trilinear upsampling.

Hospitals' head and body CTs are 512x512 per slice and 200-1,000 slices; the shared CT head is
256x256x113 at 1x1x2 mm. Upsampling by an integer factor f along an axis with the end samples
kept (n -> (n-1)*f+1) gives the sizes the benchmarks of issue 30 use:

    tests/bench/make_clinical_ct.py ../shared/data/ct-head-256x256x113.nii.gz ct-511x511x225.nii.gz --factors 2 2 2
    tests/bench/make_clinical_ct.py ../shared/data/ct-head-256x256x113.nii.gz ct-511x511x897.nii.gz --factors 2 2 8

The result keeps the input's physical extent and placement: spacing is divided by f and the
sform/qform map the new voxel i to the old voxel i/f. It reads and writes NIfTI-1 (.nii or
.nii.gz) with numpy alone and works one output slice at a time, so its memory is the input plus
one slice of the output (the output is streamed to the file).
"""
import argparse
import gzip
import struct
import sys

import numpy as np

DTYPES = {2: np.uint8, 4: np.int16, 8: np.int32, 16: np.float32, 64: np.float64, 256: np.int8,
          512: np.uint16, 768: np.uint32}


def read_nifti(path):
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rb") as f:
        data = f.read()
    if len(data) < 348:
        sys.exit(f"{path}: {len(data)} bytes, shorter than a NIfTI-1 header (348)")
    endian = "<" if struct.unpack("<i", data[0:4])[0] == 348 else ">"
    if struct.unpack(endian + "i", data[0:4])[0] != 348 or data[344:347] not in (b"n+1", b"ni1"):
        sys.exit(f"{path}: not a single-file NIfTI-1 volume (sizeof_hdr 348 and magic n+1 expected)")
    header = bytearray(data[:348])
    dim = struct.unpack(endian + "8h", data[40:56])
    if dim[0] != 3:
        sys.exit(f"{path}: {dim[0]} dimensions; a 3-D volume was expected")
    datatype = struct.unpack(endian + "h", data[70:72])[0]
    if datatype not in DTYPES:
        sys.exit(f"{path}: datatype {datatype} is not one this script reads")
    vox_offset = int(struct.unpack(endian + "f", data[108:112])[0])
    nx, ny, nz = dim[1:4]
    dtype = np.dtype(DTYPES[datatype]).newbyteorder(endian)
    count = nx * ny * nz
    if vox_offset + count * dtype.itemsize > len(data):
        sys.exit(f"{path}: {len(data)} bytes hold fewer than the {nx}x{ny}x{nz} voxels declared")
    voxels = np.frombuffer(data, dtype=dtype, count=count, offset=vox_offset)
    return endian, header, voxels.reshape((nz, ny, nx)), dtype


def axis_weights(n, f):
    """For an axis of n samples upsampled by f: for each output index, the lower input index and
    the weight of the upper one."""
    out = (n - 1) * f + 1
    pos = np.arange(out, dtype=np.float64) / f
    lo = np.minimum(np.floor(pos).astype(np.int64), n - 2 if n > 1 else 0)
    return lo, pos - lo


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("input", help="a NIfTI-1 volume (.nii or .nii.gz)")
    ap.add_argument("output", help="the upsampled volume (.nii or .nii.gz)")
    ap.add_argument("--factors", type=int, nargs=3, default=[2, 2, 2], metavar=("FX", "FY", "FZ"),
                    help="integer upsampling factor per axis (default 2 2 2)")
    args = ap.parse_args()
    fx, fy, fz = args.factors
    if min(args.factors) < 1 or max(args.factors) > 16:
        sys.exit(f"--factors {fx} {fy} {fz}: each factor must be 1..16")
    endian, header, vol, dtype = read_nifti(args.input)
    nz, ny, nx = vol.shape
    if min(nx, ny, nz) < 2:
        sys.exit(f"{args.input}: {nx}x{ny}x{nz}; every axis needs two samples to interpolate")
    lx, wx = axis_weights(nx, fx)
    ly, wy = axis_weights(ny, fy)
    lz, wz = axis_weights(nz, fz)
    ox, oy, oz = len(lx), len(ly), len(lz)

    # Header: new dims, spacing / f, sform columns / f; qform keeps its offset (voxel 0 stays).
    e = endian
    dim = list(struct.unpack(e + "8h", header[40:56]))
    dim[1:4] = [ox, oy, oz]
    header[40:56] = struct.pack(e + "8h", *dim)
    pixdim = list(struct.unpack(e + "8f", header[76:108]))
    pixdim[1] /= fx
    pixdim[2] /= fy
    pixdim[3] /= fz
    header[76:108] = struct.pack(e + "8f", *pixdim)
    header[108:112] = struct.pack(e + "f", 352.0)
    for row in range(3):
        off = 280 + 16 * row
        s = list(struct.unpack(e + "4f", header[off:off + 16]))
        s[0] /= fx
        s[1] /= fy
        s[2] /= fz
        header[off:off + 16] = struct.pack(e + "4f", *s)

    def plane(k):  # input slice k upsampled in-plane, as float64
        src = vol[k].astype(np.float64)
        rows = src[ly] * (1 - wy)[:, None] + src[np.minimum(ly + 1, ny - 1)] * wy[:, None]
        return rows[:, lx] * (1 - wx) + rows[:, np.minimum(lx + 1, nx - 1)] * wx

    opener = gzip.open if args.output.endswith(".gz") else open
    info = np.iinfo(dtype) if np.issubdtype(dtype, np.integer) else None
    with opener(args.output, "wb") as out:
        out.write(bytes(header) + b"\0\0\0\0")
        cache = {}
        for k in range(oz):
            a, b = int(lz[k]), min(int(lz[k]) + 1, nz - 1)
            for key in list(cache):
                if key not in (a, b):
                    del cache[key]
            for key in (a, b):
                if key not in cache:
                    cache[key] = plane(key)
            s = cache[a] * (1 - wz[k]) + cache[b] * wz[k]
            if info is not None:
                s = np.clip(np.rint(s), info.min, info.max)
            out.write(s.astype(dtype).tobytes())
    print(f"{args.output}: {ox}x{oy}x{oz}, spacing {pixdim[1]:g}x{pixdim[2]:g}x{pixdim[3]:g} mm, "
          f"{ox * oy * oz / 1e6:.1f} M voxels")


if __name__ == "__main__":
    main()
