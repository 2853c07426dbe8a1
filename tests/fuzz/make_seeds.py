#!/usr/bin/env python3
"""Writes the seed corpora of the volume, DICOM, DICOM receive and series check, Upload,
CreateVolume, checkpoint and level-record fuzz targets
(corpus/<target>/): small valid files (named ok-*) and edge cases (bad-*). Run from anywhere;
the output is deterministic, so a re-run changes nothing. Inputs of several files are joined
with SEP (kFileSeparator in fuzz_entries.h)."""
import gzip
import hashlib
import os
import struct
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))
SEP = b"\n--decima-fuzz-next-file--\n"


def write(target, name, data):
    d = os.path.join(HERE, "corpus", target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def gz(data):
    return gzip.compress(data, mtime=0)


# ---- NIfTI-1 --------------------------------------------------------------------------------
def nifti_header(dims, datatype, bitpix, pixdim=(1, 1, 2), single=True, sform=False,
                 slope=0.0, inter=0.0, dim0=3):
    h = bytearray(348)
    struct.pack_into("<i", h, 0, 348)
    d = [dim0] + list(dims) + [1] * (7 - len(dims))
    struct.pack_into("<8h", h, 40, *d)
    struct.pack_into("<hh", h, 70, datatype, bitpix)
    struct.pack_into("<8f", h, 76, 1.0, *pixdim, 1, 1, 1, 1)
    struct.pack_into("<f", h, 108, 352.0 if single else 0.0)
    struct.pack_into("<ff", h, 112, slope, inter)
    if sform:
        struct.pack_into("<h", h, 254, 1)
        struct.pack_into("<12f", h, 280, pixdim[0], 0, 0, -10, 0, pixdim[1], 0, -20, 0, 0,
                         pixdim[2], 5)
    h[344:348] = b"n+1\0" if single else b"ni1\0"
    return bytes(h)


def nifti_single(dims, datatype, bitpix, data, **kw):
    return nifti_header(dims, datatype, bitpix, **kw) + b"\0" * 4 + data


u8 = bytes(range(48))                       # 4 x 4 x 3 uint8
i16 = struct.pack("<48h", *range(-24, 24))  # 4 x 4 x 3 int16
f32 = struct.pack("<48f", *[i * 0.5 for i in range(48)])

write("nifti", "ok-nii-uint8", b"\0" + nifti_single((4, 4, 3), 2, 8, u8))
write("nifti", "ok-nii-gz-int16-sform",
      b"\0" + gz(nifti_single((4, 4, 3), 4, 16, i16, sform=True)))
write("nifti", "ok-nii-rescaled", b"\0" + nifti_single((4, 4, 3), 4, 16, i16, slope=2.0,
                                                        inter=-1.0))
write("nifti", "ok-pair-float32", b"\1" + nifti_header((4, 4, 3), 16, 32, single=False) + SEP
      + f32)
write("nifti", "bad-truncated", b"\0" + nifti_single((4, 4, 3), 2, 8, u8)[:300])
write("nifti", "bad-short-data", b"\0" + nifti_single((4, 4, 3), 2, 8, u8[:40]))
write("nifti", "bad-huge-dims", b"\0" + nifti_single((32767, 32767, 32767), 2, 8, u8))
write("nifti", "bad-nan-pixdim",
      b"\0" + nifti_single((4, 4, 3), 2, 8, u8, pixdim=(float("nan"), 1, 1)))
write("nifti", "bad-gzip-bomb", b"\0" + gz(nifti_single((1024, 1024, 64), 2, 8, b"\0" * 65536)))
write("nifti", "bad-4d", b"\0" + nifti_single((4, 4, 3, 2), 2, 8, u8 + u8, dim0=4))

# ---- MetaImage -------------------------------------------------------------------------------
def mha(fields, data=b""):
    return ("".join(f"{k} = {v}\n" for k, v in fields)).encode() + data


base = [("ObjectType", "Image"), ("NDims", "3"), ("DimSize", "4 4 3"),
        ("ElementSpacing", "1 1 2"), ("Offset", "-10 -20 5"),
        ("TransformMatrix", "1 0 0 0 1 0 0 0 1")]
write("metaimage", "ok-mha-uchar",
      b"\0" + mha(base + [("ElementType", "MET_UCHAR"), ("ElementDataFile", "LOCAL")], u8))
z = zlib.compress(i16)
write("metaimage", "ok-mha-zlib-short",
      b"\0" + mha(base + [("ElementType", "MET_SHORT"), ("CompressedData", "True"),
                          ("CompressedDataSize", str(len(z))), ("ElementDataFile", "LOCAL")], z))
write("metaimage", "ok-mhd-raw-float",
      b"\1" + mha(base + [("ElementType", "MET_FLOAT"), ("ElementDataFile", "a.raw")]) + SEP + f32)
write("metaimage", "ok-mhd-zraw",
      b"\1" + mha(base + [("ElementType", "MET_SHORT"), ("CompressedData", "True"),
                          ("ElementDataFile", "a.zraw")]) + SEP + SEP + z)
write("metaimage", "bad-escaping-data-file",
      b"\1" + mha(base + [("ElementType", "MET_UCHAR"), ("ElementDataFile", "../../etc/passwd")]))
write("metaimage", "bad-short-data",
      b"\0" + mha(base + [("ElementType", "MET_UCHAR"), ("ElementDataFile", "LOCAL")], u8[:20]))
write("metaimage", "bad-negative-dims",
      b"\0" + mha([("NDims", "3"), ("DimSize", "4 -4 3"), ("ElementType", "MET_UCHAR"),
                   ("ElementDataFile", "LOCAL")], u8))
write("metaimage", "bad-zlib-bomb",
      b"\0" + mha([("NDims", "3"), ("DimSize", "1024 1024 64"), ("ElementType", "MET_UCHAR"),
                   ("CompressedData", "True"), ("ElementDataFile", "LOCAL")],
                  zlib.compress(b"\0" * 65536)))

# ---- NRRD ------------------------------------------------------------------------------------
def nrrd(fields, data=b"", magic="NRRD0004"):
    return (magic + "\n" + "".join(f"{k}: {v}\n" for k, v in fields) + "\n").encode() + data


geo = [("dimension", "3"), ("sizes", "4 4 3"), ("space", "left-posterior-superior"),
       ("space directions", "(1,0,0) (0,1,0) (0,0,2)"), ("space origin", "(-10,-20,5)")]
write("nrrd", "ok-raw-uint8",
      b"\0" + nrrd([("type", "uint8")] + geo + [("encoding", "raw")], u8))
write("nrrd", "ok-gzip-int16-ras",
      b"\0" + nrrd([("type", "short"), ("dimension", "3"), ("sizes", "4 4 3"),
                    ("space", "right-anterior-superior"), ("encoding", "gzip"),
                    ("endian", "little")], gz(i16)))
write("nrrd", "ok-ascii-float-spacings",
      b"\0" + nrrd([("type", "float"), ("dimension", "3"), ("sizes", "4 4 3"),
                    ("spacings", "1 1 2"), ("encoding", "ascii")],
                   " ".join(str(i * 0.5) for i in range(48)).encode()))
write("nrrd", "ok-nhdr-detached",
      b"\1" + nrrd([("type", "uint8")] + geo + [("encoding", "raw"), ("data file", "a.raw")])
      + SEP + u8)
write("nrrd", "ok-4d-size1",
      b"\0" + nrrd([("type", "uint8"), ("dimension", "4"), ("sizes", "1 4 4 3"),
                    ("kinds", "scalar domain domain domain"), ("encoding", "raw")], u8))
write("nrrd", "bad-escaping-data-file",
      b"\1" + nrrd([("type", "uint8")] + geo + [("encoding", "raw"), ("data file", "/etc/passwd")]))
write("nrrd", "bad-gzip-bomb",
      b"\0" + nrrd([("type", "uint8"), ("dimension", "3"), ("sizes", "1024 1024 64"),
                    ("encoding", "gzip")], gz(b"\0" * 65536)))
write("nrrd", "bad-vector-kind",
      b"\0" + nrrd([("type", "uint8"), ("dimension", "4"), ("sizes", "3 4 4 1"),
                    ("kinds", "vector domain domain domain"), ("encoding", "raw")], u8))
write("nrrd", "bad-truncated-header", b"\0NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4")

# ---- DICOM (explicit or implicit VR little endian, written by hand) ----------------------------
EXPLICIT, IMPLICIT = "1.2.840.10008.1.2.1", "1.2.840.10008.1.2"
LONG_VRS = {"OB", "OW", "SQ", "UN", "UT", "OF"}


def uid(s):
    b = s.encode()
    return b + b"\0" if len(b) % 2 else b


def text(s):
    b = s.encode()
    return b + b" " if len(b) % 2 else b


def element(group, elem, vr, value, explicit=True):
    tag = struct.pack("<HH", group, elem)
    if not explicit:
        return tag + struct.pack("<I", len(value)) + value
    if vr in LONG_VRS:
        return tag + vr.encode() + b"\0\0" + struct.pack("<I", len(value)) + value
    return tag + vr.encode() + struct.pack("<H", len(value)) + value


def dicom_slice(z, series="1.2.3.4.5", syntax=EXPLICIT, rows=4, cols=4, extra=b""):
    explicit = syntax == EXPLICIT
    sop = f"1.2.3.4.5.{z + 1}"
    meta = (element(2, 1, "OB", b"\0\1") + element(2, 2, "UI", uid("1.2.840.10008.5.1.4.1.1.2"))
            + element(2, 3, "UI", uid(sop)) + element(2, 0x10, "UI", uid(syntax))
            + element(2, 0x12, "UI", uid("1.2.3.4")))
    meta = element(2, 0, "UL", struct.pack("<I", len(meta))) + meta
    pixels = struct.pack(f"<{rows * cols}H", *[(z * 16 + i) for i in range(rows * cols)])
    e = lambda g, el, vr, v: element(g, el, vr, v, explicit)  # noqa: E731
    ds = (e(8, 0x16, "UI", uid("1.2.840.10008.5.1.4.1.1.2")) + e(8, 0x18, "UI", uid(sop))
          + e(8, 0x60, "CS", text("CT")) + e(0x20, 0xD, "UI", uid("1.2.3.4"))
          + e(0x20, 0xE, "UI", uid(series)) + e(0x20, 0x13, "IS", text(str(z + 1)))
          + e(0x20, 0x32, "DS", text(f"-10\\-20\\{5 + 2 * z}"))
          + e(0x20, 0x37, "DS", text("1\\0\\0\\0\\1\\0")) + extra
          + e(0x28, 2, "US", struct.pack("<H", 1)) + e(0x28, 4, "CS", text("MONOCHROME2"))
          + e(0x28, 0x10, "US", struct.pack("<H", rows)) + e(0x28, 0x11, "US", struct.pack("<H", cols))
          + e(0x28, 0x30, "DS", text("1\\1")) + e(0x28, 0x100, "US", struct.pack("<H", 16))
          + e(0x28, 0x101, "US", struct.pack("<H", 16)) + e(0x28, 0x102, "US", struct.pack("<H", 15))
          + e(0x28, 0x103, "US", struct.pack("<H", 0))
          + e(0x28, 0x1052, "DS", text("-1024")) + e(0x28, 0x1053, "DS", text("1"))
          + e(0x7FE0, 0x10, "OW", pixels))
    return b"\0" * 128 + b"DICM" + meta + ds


write("dicom", "ok-two-slices-explicit", dicom_slice(0) + SEP + dicom_slice(1))
write("dicom", "ok-three-slices-implicit", SEP.join(dicom_slice(z, syntax=IMPLICIT)
                                                    for z in range(3)))
seq = (struct.pack("<HH", 0x8, 0x1140) + b"SQ\0\0" + struct.pack("<I", 0xFFFFFFFF)
       + struct.pack("<HHI", 0xFFFE, 0xE000, 0xFFFFFFFF)
       + element(8, 0x1155, "UI", uid("1.2.3")) + struct.pack("<HHI", 0xFFFE, 0xE00D, 0)
       + struct.pack("<HHI", 0xFFFE, 0xE0DD, 0))
write("dicom", "ok-undefined-length-sequence",
      dicom_slice(0, extra=seq) + SEP + dicom_slice(1, extra=seq))
write("dicom", "bad-one-slice", dicom_slice(0))
write("dicom", "bad-truncated-element", dicom_slice(0) + SEP + dicom_slice(1)[:-40])
write("dicom", "bad-unclosed-sequence", dicom_slice(0, extra=seq[:-16]) + SEP + dicom_slice(1))
write("dicom", "bad-two-series", dicom_slice(0) + SEP + dicom_slice(1, series="1.2.3.9"))
write("dicom", "bad-duplicate-position", dicom_slice(0) + SEP + dicom_slice(0))
write("dicom", "bad-no-marker", b"\0" * 200 + SEP + b"not a dicom file")

# ---- DICOM receive: calling AE choice (0 and 1 are AE titles), then the received file --------
write("dicom_receive", "ok-explicit", b"\0" + dicom_slice(0))
write("dicom_receive", "ok-implicit-other-ae", b"\1" + dicom_slice(1, syntax=IMPLICIT))
write("dicom_receive", "ok-undefined-length-sequence", b"\0" + dicom_slice(2, extra=seq))
write("dicom_receive", "bad-calling-ae-backslash", b"\3" + dicom_slice(0))
write("dicom_receive", "bad-calling-ae-17-characters", b"\5" + dicom_slice(0))
write("dicom_receive", "bad-no-sop-instance-uid",
      b"\0" + dicom_slice(0).replace(element(8, 0x18, "UI", uid("1.2.3.4.5.1")), b""))
write("dicom_receive", "bad-series-uid-not-a-uid", b"\0" + dicom_slice(0, series="1.2.x.4"))
write("dicom_receive", "bad-truncated-element", b"\0" + dicom_slice(0)[:-40])
write("dicom_receive", "bad-not-dicom", b"\0" + b"not a dicom file")


# The receiver reads headers from their first 64 KiB and never inflates (dicom_receiver.h).
def deflated_slice(z, zeros=1 << 20):
    plain = dicom_slice(z, extra=element(0x29, 0x10, "LO", text("DECIMA TEST"))
                        + element(0x29, 0x1001, "OB", b"\0" * zeros))
    meta_end = plain.index(b"\x08\x00\x16\x00")
    meta = plain[132:meta_end].replace(uid(EXPLICIT), uid("1.2.840.10008.1.2.1.99"))
    meta = element(2, 0, "UL", struct.pack("<I", len(meta) - 12)) + meta[12:]
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return b"\0" * 128 + b"DICM" + meta + c.compress(plain[meta_end:]) + c.flush()


nested = (struct.pack("<HH", 0x9, 0x1003) + b"SQ\0\0" + struct.pack("<I", 0xFFFFFFFF)
          + struct.pack("<HHI", 0xFFFE, 0xE000, 0xFFFFFFFF)) * 3500
tiny = element(0x9, 0x1001, "LO", b"") * 9000
write("dicom_receive", "bad-deflated-bomb", b"\0" + deflated_slice(0))
write("dicom_receive", "bad-deep-nesting", b"\0" + dicom_slice(0, extra=nested))
huge_ts = (struct.pack("<HH", 2, 0x10) + b"OB\0\0" + struct.pack("<I", 0xFFFFFFF0)
           + uid(EXPLICIT))
plain = dicom_slice(0)
write("dicom_receive", "bad-meta-value-declares-4-gib",
      b"\0" + plain.replace(element(2, 0x10, "UI", uid(EXPLICIT)), huge_ts, 1))
write("dicom_receive", "bad-uids-past-64-kib", b"\0" + dicom_slice(0).replace(
    b"\x08\x00\x60\x00", tiny + b"\x08\x00\x60\x00", 1))

# ---- DICOM series check (CheckSeriesComplete): the parts are the files of one series ---------
write("dicom_series_check", "ok-two-slices-explicit", dicom_slice(0) + SEP + dicom_slice(1))
write("dicom_series_check", "ok-three-slices-implicit", SEP.join(
    dicom_slice(z, syntax=IMPLICIT) for z in (2, 0, 1)))
write("dicom_series_check", "ok-undefined-length-sequence",
      dicom_slice(0, extra=seq) + SEP + dicom_slice(1, extra=seq))
write("dicom_series_check", "bad-one-slice", dicom_slice(0))
write("dicom_series_check", "bad-missing-slice", SEP.join(dicom_slice(z) for z in (0, 1, 3)))
write("dicom_series_check", "bad-deflated", deflated_slice(0, 64) + SEP + deflated_slice(1, 64))
write("dicom_series_check", "bad-deep-nesting",
      dicom_slice(0, extra=nested) + SEP + dicom_slice(1))

# ---- Upload: flags, chunk, [sha 64], [size], [offset], [cut], payload ------------------------
def varint(v):
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        out.append(b | (0x80 if v else 0))
        if not v:
            return bytes(out)


def zigzag(v):
    return varint((v << 1) ^ (v >> 63) if v < 0 else v << 1)


payload = bytes(range(256)) * 3
write("upload", "ok-one-byte-chunks", b"\0\0" + b"hello, decima")
write("upload", "ok-data-in-first", b"\x10\x10" + payload)
write("upload", "ok-interrupted-and-resumed", b"\x14\x03" + varint(100) + payload)
write("upload", "ok-empty-blob", b"\0\0")
write("upload", "bad-wrong-digest", b"\x01\x05" + b"a" * 64 + payload)
write("upload", "bad-digest-upper-case",
      b"\x01\x05" + hashlib.sha256(payload).hexdigest().upper().encode() + payload)
write("upload", "bad-size-over-limit", b"\x02\x05" + zigzag(5 << 20) + payload)
write("upload", "bad-negative-size", b"\x02\x05" + zigzag(-1) + payload)
write("upload", "bad-more-data-than-declared", b"\x02\x05" + zigzag(10) + payload)
write("upload", "bad-offset-not-held", b"\x08\x05" + zigzag(7) + payload)
write("upload", "bad-chunk-over-1mib", b"\x20\x05" + payload)

# ---- CreateVolume: head, then per file: mode, path, [content length], content ----------------
NAMES = ["v.nii", "v.nii.gz", "v.hdr", "v.img", "v.mha", "v.mhd", "a.raw", "a.zraw", "v.nrrd",
         "v.nhdr", "IM0", "IM1", "s/IM2", "s", "x.txt", "a.raw.gz"]


def manifest(files, fmt=0, request_id=False):
    """files: (mode, path, content); path is a name of NAMES unless mode & 1."""
    out = bytearray([(len(files) - 1) | (fmt << 2) | (0x80 if request_id else 0)])
    for i, (mode, path, content) in enumerate(files):
        out.append(mode)
        if mode & 1:
            out += bytes([len(path)]) + path.encode()
        else:
            out.append(NAMES.index(path))
        if i + 1 < len(files):
            out += varint(len(content))
        out += content
    return bytes(out)


nii = nifti_single((4, 4, 3), 2, 8, u8)
mhd = mha(base + [("ElementType", "MET_UCHAR"), ("ElementDataFile", "a.raw")])
write("create_volume", "ok-nifti", manifest([(0, "v.nii", nii)]))
write("create_volume", "ok-nifti-gz-request-id",
      manifest([(0, "v.nii.gz", gz(nii))], request_id=True))
write("create_volume", "ok-mha",
      manifest([(0, "v.mha", mha(base + [("ElementType", "MET_UCHAR"),
                                          ("ElementDataFile", "LOCAL")], u8))]))
write("create_volume", "ok-mhd-and-raw", manifest([(0, "v.mhd", mhd), (0, "a.raw", u8)]))
write("create_volume", "ok-nrrd",
      manifest([(0, "v.nrrd", nrrd([("type", "uint8")] + geo + [("encoding", "raw")], u8))],
               fmt=3))
write("create_volume", "ok-dicom-folder",
      manifest([(0, "IM0", dicom_slice(0)), (0, "IM1", dicom_slice(1)),
                (0, "s/IM2", dicom_slice(2))], fmt=4))
write("create_volume", "bad-unsafe-path", manifest([(1, "../v.nii", nii)]))
write("create_volume", "bad-absolute-path", manifest([(1, "/etc/v.nii", nii)]))
write("create_volume", "bad-blob-not-uploaded", manifest([(4, "v.nii", nii)]))
write("create_volume", "bad-malformed-blob-name", manifest([(6, "v.nii", b"blobs/xyz")]))
write("create_volume", "bad-duplicate-path", manifest([(0, "v.nii", nii), (0, "v.nii", nii)]))
write("create_volume", "bad-file-and-folder-named-alike",
      manifest([(0, "s", b"plain file"), (0, "s/IM2", dicom_slice(2))]))
write("create_volume", "bad-mhd-without-data", manifest([(0, "v.mhd", mhd)]))
write("create_volume", "bad-unknown-format", manifest([(0, "x.txt", b"hello")], fmt=5))
write("create_volume", "bad-gzip-bomb",
      manifest([(0, "v.nii.gz", gz(nifti_single((1024, 1024, 64), 2, 8, b"\0" * 65536)))]))


# ---- stage checkpoints (core/pipeline/checkpoint.h) -----------------------------------------
# First byte of a seed: bit 0 simplify (else segment) payload, bit 1 the whole file.
def vec(fmt, values):
    return struct.pack("<Q", len(values)) + b"".join(struct.pack("<" + fmt, v) for v in values)


def seg_payload(dims=(2, 2, 1), labels=(0, 1, 1, 2), converged=1):
    n = dims[0] * dims[1] * dims[2]
    out = struct.pack("<3q", *dims) + struct.pack("<3d", 1, 1, 2) + struct.pack("<3d", 0, 0, 0)
    out += struct.pack("<9d", 1, 0, 0, 0, 1, 0, 0, 0, 1) + bytes([0])  # direction, uint8
    out += struct.pack("<Q", len(labels)) + bytes(labels) + struct.pack("<Q", 2) + b"MR"
    out += vec("f", [0.5] * n) + vec("f", [0.5] * n) + vec("d", [10, 20, 30])
    out += vec("q", [1, 2, 1]) + vec("d", [2, 4, 2])
    return out + struct.pack("<i", 7) + bytes([converged]) + struct.pack("<dd", 0.25, 3.5)


def simplify_payload(tets=(0, 1, 2, 3), vertex_map=(0, 1, 2, 3, -1), reached=1):
    out = vec("f", [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]) + vec("f", [1, 2, 3, 4])
    out += vec("B", [0, 0, 1, 1]) + vec("f", [0.5] * 4) + vec("B", [1, 0, 0, 2])
    out += vec("i", tets) + vec("B", [3] * (len(tets) // 4)) + vec("i", vertex_map)
    out += struct.pack("<qqd", 20, 1, 0.95) + bytes([reached, 0]) + struct.pack("<Q", 4) + b"done"
    out += struct.pack("<iqd", 2, 3, 0.125)
    return out + struct.pack("<Q", 1) + struct.pack("<7qd", 5, 3, 19, 1, 0, 2, 0, 0.125)


def ckpt_file(payload, key=b"k", sha=None):
    sha = sha or hashlib.sha256(payload).hexdigest().encode()
    return (b"DECIMA-CHECKPOINT 1\n" + struct.pack("<Q", len(key)) + key +
            struct.pack("<Q", len(payload)) + sha + payload)


write("checkpoint", "ok-segment-payload", b"\x00" + seg_payload())
write("checkpoint", "ok-simplify-payload", b"\x01" + simplify_payload())
write("checkpoint", "ok-segment-file", b"\x02" + ckpt_file(seg_payload()))
write("checkpoint", "ok-simplify-file", b"\x03" + ckpt_file(simplify_payload()))
write("checkpoint", "bad-truncated-segment-payload", b"\x00" + seg_payload()[:-3])
write("checkpoint", "bad-labels-do-not-match-dims", b"\x00" + seg_payload(labels=(0, 1, 1)))
write("checkpoint", "bad-tet-names-missing-vertex", b"\x01" + simplify_payload(tets=(0, 1, 2, 9)))
write("checkpoint", "bad-vertex-map-out-of-range",
      b"\x01" + simplify_payload(vertex_map=(0, 1, 2, 3, 7)))
write("checkpoint", "bad-checksum-file", b"\x03" + ckpt_file(simplify_payload(), sha=b"0" * 64))
write("checkpoint", "bad-other-key-file", b"\x02" + ckpt_file(seg_payload(), key=b"other"))
write("checkpoint", "bad-torn-file", b"\x02" + ckpt_file(seg_payload())[:-10])
write("checkpoint", "bad-huge-count", b"\x01" + struct.pack("<Q", 1 << 62) + b"\0" * 32)
# One encoding per value (the payload must serialize back to itself): a flag byte other than 0
# or 1 is refused (found by the fuzzer: 0xff read back as true and was written as 1).
write("checkpoint", "bad-simplify-reached-target-not-0-or-1", b"\x01" + simplify_payload(reached=255))
write("checkpoint", "bad-segment-converged-not-0-or-1", b"\x00" + seg_payload(converged=2))


# ---- level records (core/simplify/levels_io.h; format in core/simplify/README.md) ------------
M64 = (1 << 64) - 1


def rotl(x, r):
    return ((x << r) | (x >> (64 - r))) & M64


def levels_checksum(data):
    """LevelsChecksum: the digest of every byte before the checksum."""
    h = 0x9e3779b97f4a7c15

    def mix(h, w):
        w = (w * 0x87c37b91114253d5) & M64
        w = (rotl(w, 31) * 0x4cf5ad432745937f) & M64
        h ^= w
        return (rotl(h, 27) * 5 + 0x52dce729) & M64

    n = len(data) - len(data) % 8
    for i in range(0, n, 8):
        h = mix(h, struct.unpack_from("<Q", data, i)[0])
    if n < len(data):
        tail = int.from_bytes(data[n:], "little")
        h = mix(h, tail ^ ((len(data) - n) << 56))
    h = mix(h, len(data))
    for shift, mul in ((33, 0xff51afd7ed558ccd), (33, 0xc4ceb9fe1a85ec53)):
        h ^= h >> shift
        h = (h * mul) & M64
    return h ^ (h >> 33)


def levels_file(nv, nt, collapses, version=1, flags=0, refit=10, digest=0x1234, count=None,
                payload=None):
    raw = b"".join(struct.pack("<i", u) for u, v, k in collapses)
    raw += b"".join(struct.pack("<i", v - u) for u, v, k in collapses)
    raw += b"".join(struct.pack("<H", k) for u, v, k in collapses)
    packed = zlib.compress(raw, 6) if payload is None else payload
    n = len(collapses) if count is None else count
    out = b"DECIMALV" + struct.pack("<IIQQQIIQQ", version, flags, nv, nt, n, refit, 0, digest,
                                    len(packed)) + packed
    return out + struct.pack("<Q", levels_checksum(out))


LEVELS = [(1, 0, 2), (3, 2, 1), (5, 0, 3)]
write("levels", "ok-three-collapses", levels_file(8, 12, LEVELS))
write("levels", "ok-exhausted-empty", levels_file(4, 1, [], flags=1))
write("levels", "bad-magic", b"DECIMALX" + levels_file(8, 12, LEVELS)[8:])
write("levels", "bad-version", levels_file(8, 12, LEVELS, version=2))
write("levels", "bad-truncated", levels_file(8, 12, LEVELS)[:-5])
write("levels", "bad-count-above-payload", levels_file(8, 12, LEVELS, count=4))
write("levels", "bad-huge-count", levels_file(1 << 30, 12, LEVELS, count=1 << 29))
write("levels", "bad-vertex-removed-twice", levels_file(8, 12, [(1, 0, 2), (1, 2, 1)]))
write("levels", "bad-more-cells-deleted-than-base", levels_file(8, 2, LEVELS))
write("levels", "bad-checksum", levels_file(8, 12, LEVELS)[:-1] + b"\0")


# ---- streamed simplify window records (core/simplify/stream.h) ------------------------------
# First byte: bits 0-1 the pass; bit 2 the fixture's real records patched by (record, offset
# low, offset high, byte) quadruples, else the records themselves cut at the file separator.
def patches(*quads):
    return b"".join(bytes(q) for q in quads)


def window_record(pass_=0, window=0, slabs=4, nv=1260, written=(), carried=(), samples=(),
                  merged=(), share_costs=(), tag=b"decima-stream-window 3"):
    out = struct.pack("<Q", len(tag)) + tag + struct.pack("<qqiq", slabs, nv, pass_, window)
    out += bytes([1]) + struct.pack("<i", 0) + struct.pack("<ddd", 5.0, 10.0, -1.0)
    out += struct.pack("<qqqq", 0, 405, 1, 425) + bytes([0, 0]) + struct.pack("<qd", 10, 5.0)
    out += struct.pack("<Q", 0)  # no pass stats
    # carried_samples: (vertex, cell) pairs, counted as pairs
    pairs = struct.pack("<Q", len(samples) // 2) + b"".join(struct.pack("<i", v) for v in samples)
    # share_cost: (cost, share) of the window, at most one
    share_cost = struct.pack("<Q", len(share_costs)) + b"".join(
        struct.pack("<dq", c, n) for c, n in share_costs)
    return out + vec("i", written) + vec("i", merged) + vec("i", carried) + pairs + share_cost


write("stream_window", "ok-real-records-pass-0", b"\x04")
write("stream_window", "ok-real-records-pass-1", b"\x05")
write("stream_window", "ok-real-records-window-1-patched-late",
      b"\x04" + patches((1, 0xf0, 0xff, 0x00)))
write("stream_window", "bad-real-record-tag-patched", b"\x04" + patches((0, 9, 0, ord("X"))))
write("stream_window", "bad-real-record-counts-patched",
      b"\x04" + patches((0, 60, 0, 0xff), (0, 61, 0, 0x7f)))
# Offsets 200-203 are in the pass statistics: read back, the run goes on.
write("stream_window", "ok-real-records-patched-in-their-statistics",
      b"\x05" + patches((0, 200, 0, 0xff), (1, 201, 0, 0xff), (2, 202, 0, 0x80), (3, 203, 0, 1)))
write("stream_window", "bad-forged-window-out-of-range-cell",
      b"\x00" + window_record(written=(0, 1, 2, 5000)))
write("stream_window", "bad-forged-window-repeated-vertex",
      b"\x00" + window_record(carried=(0, 0, 1, 2)))
# A survivor cycle in a measuring pass's record: read back; the run fails cleanly (InternalError)
# only if that pass is kept as the final one, else its survivors are never used.
write("stream_window", "ok-forged-measuring-window-with-a-cycle",
      b"\x00" + window_record(merged=(0, 1, 1, 0)))
write("stream_window", "bad-forged-window-negative-share-cost",
      b"\x00" + window_record(share_costs=((-1.0, 100),)))
write("stream_window", "bad-forged-window-two-share-costs",
      b"\x00" + window_record(share_costs=((1.0, 100), (2.0, 100))))
write("stream_window", "ok-forged-window-with-a-share-cost",
      b"\x00" + window_record(share_costs=((3.5, 100),)))
write("stream_window", "bad-forged-window-truncated", b"\x00" + window_record()[:-5])
write("stream_window", "bad-forged-other-run", b"\x00" + window_record(slabs=7))
