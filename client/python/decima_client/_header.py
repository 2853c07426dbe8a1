"""The dims of a volume file from its header alone, for the memory check before an upload
(Jobs.CheckJobMemory, issue 30): NIfTI-1/2 (.nii, .nii.gz, .hdr/.img), MetaImage (.mha, .mhd:
DimSize) and NRRD (.nrrd, .nhdr: sizes). The C++ CLI uses core/io's ProbeVolume; this is the
same fields read in Python, since the package carries no core/io.

read_dims never raises on a bad file: it returns None, and submit() then uploads as before and
the server's CreateVolume names what is wrong (so a bad file gets the server's one error).
A DICOM folder has no dims here: the series' dims are known only after reading its files.
"""
import gzip
import os
import struct
import zlib

_MAX_TEXT_HEADER = 1 << 16  # a MetaImage or NRRD header longer than this is left to the server


def _head(path, n):
    with open(path, "rb") as f:
        magic = f.read(2)
    opener = gzip.open if magic == b"\x1f\x8b" else open
    with opener(path, "rb") as f:
        return f.read(n)


def _three(dims):
    dims = list(dims)
    if len(dims) > 3 and any(d != 1 for d in dims[3:]):
        return None
    dims = (dims + [1, 1, 1])[:3]
    return tuple(dims) if all(isinstance(d, int) and d >= 1 for d in dims) else None


def _nifti(path):
    if path.lower().endswith((".img", ".img.gz")):
        base = path[:-7] if path.lower().endswith(".img.gz") else path[:-4]
        for name in (base + ".hdr", base + ".hdr.gz"):
            if os.path.isfile(name):
                path = name
                break
    h = _head(path, 540)
    for order in "<>":
        if len(h) >= 348 and struct.unpack(order + "i", h[:4])[0] == 348:
            dim = struct.unpack(order + "8h", h[40:56])
            break
        if len(h) >= 540 and struct.unpack(order + "i", h[:4])[0] == 540:
            dim = struct.unpack(order + "8q", h[16:80])
            break
    else:
        return None
    if not 1 <= dim[0] <= 7:
        return None
    return _three(dim[1:1 + dim[0]])


def _text_lines(path):
    with open(path, "rb") as f:
        text = f.read(_MAX_TEXT_HEADER).decode("latin-1")
    return text.splitlines()


def _metaimage(path):
    for line in _text_lines(path):
        key, sep, value = line.partition("=")
        if not sep:
            continue
        if key.strip() == "DimSize":
            return _three(int(v) for v in value.split())
        if key.strip() == "ElementDataFile":
            return None
    return None


def _nrrd(path):
    lines = _text_lines(path)
    if not lines or not lines[0].startswith("NRRD000"):
        return None
    for line in lines[1:]:
        if not line:
            break
        key, sep, value = line.partition(":")
        if sep and key.strip() == "sizes":
            return _three(int(v) for v in value.split())
    return None


def read_dims(path):
    """(x, y, z) voxels from the header of the file `path`, or None (a folder, an unknown
    format, or a header that does not parse)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        return None
    low = path.lower()
    try:
        if low.endswith((".nii", ".nii.gz", ".hdr", ".hdr.gz", ".img", ".img.gz")):
            return _nifti(path)
        if low.endswith((".mha", ".mhd")):
            return _metaimage(path)
        if low.endswith((".nrrd", ".nhdr")):
            return _nrrd(path)
    except (OSError, EOFError, ValueError, struct.error, zlib.error):  # BadGzipFile is an OSError
        return None
    return None
