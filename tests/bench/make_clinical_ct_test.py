#!/usr/bin/python3
"""make_clinical_ct.py on a tiny generated NIfTI: sizes (n-1)*f+1, spacing / f, the input's samples
kept at multiples of f, midpoints interpolated, the sform scaled, and bad input refused."""
import gzip
import os
import struct
import subprocess
import sys
import tempfile

import numpy as np

SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "make_clinical_ct.py")


def write_nifti(path, vol, spacing):
    nz, ny, nx = vol.shape
    h = bytearray(348)
    h[0:4] = struct.pack("<i", 348)
    h[40:56] = struct.pack("<8h", 3, nx, ny, nz, 1, 1, 1, 1)
    h[70:72] = struct.pack("<h", 512)  # uint16
    h[72:74] = struct.pack("<h", 16)
    h[76:108] = struct.pack("<8f", 1, *spacing, 1, 1, 1, 1)
    h[108:112] = struct.pack("<f", 352)
    h[254:256] = struct.pack("<h", 1)  # sform_code
    h[280:328] = struct.pack("<12f", spacing[0], 0, 0, 10, 0, spacing[1], 0, 20, 0, 0, spacing[2], 30)
    h[344:348] = b"n+1\0"
    with gzip.open(path, "wb") as f:
        f.write(bytes(h) + b"\0" * 4 + vol.astype("<u2").tobytes())


def read_nifti(path):
    with gzip.open(path, "rb") as f:
        d = f.read()
    dim = struct.unpack("<8h", d[40:56])
    pixdim = struct.unpack("<8f", d[76:108])
    srow = struct.unpack("<12f", d[280:328])
    vol = np.frombuffer(d, "<u2", offset=352, count=dim[1] * dim[2] * dim[3])
    return vol.reshape(dim[3], dim[2], dim[1]), pixdim[1:4], srow


def main():
    failures = []

    def check(ok, what):
        if not ok:
            failures.append(what)

    rng = np.random.default_rng(7)
    vol = rng.integers(0, 4000, size=(5, 4, 3)).astype(np.uint16)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.nii.gz"), os.path.join(tmp, "out.nii.gz")
        write_nifti(src, vol, (1.0, 1.0, 2.0))
        subprocess.run([sys.executable, SCRIPT, src, dst, "--factors", "2", "2", "4"], check=True)
        out, spacing, srow = read_nifti(dst)
        check(out.shape == (17, 7, 5), f"shape {out.shape}, expected (17, 7, 5)")
        check(np.allclose(spacing, (0.5, 0.5, 0.5)), f"spacing {spacing}")
        check(np.array_equal(out[::4, ::2, ::2], vol), "input samples not kept at multiples of f")
        mid = np.rint((vol[:-1].astype(float) + vol[1:]) / 2)
        check(np.array_equal(out[2::4, ::2, ::2], mid), "z midpoints not interpolated")
        check(np.allclose(srow, (0.5, 0, 0, 10, 0, 0.5, 0, 20, 0, 0, 0.5, 30)), f"sform {srow}")

        bad = os.path.join(tmp, "bad.nii.gz")
        with gzip.open(bad, "wb") as f:
            f.write(b"not a nifti")
        r = subprocess.run([sys.executable, SCRIPT, bad, dst], capture_output=True, text=True)
        check(r.returncode != 0 and "bad.nii.gz" in r.stderr, f"bad input: {r.returncode} {r.stderr}")
        r = subprocess.run([sys.executable, SCRIPT, src, dst, "--factors", "0", "2", "2"],
                           capture_output=True, text=True)
        check(r.returncode != 0 and "--factors" in r.stderr, f"bad factors: {r.stderr}")
    for f in failures:
        print("FAIL:", f)
    print(f"make_clinical_ct_test: 5 checks of the upsampled volume and 2 of bad input, "
          f"{len(failures)} failed")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
