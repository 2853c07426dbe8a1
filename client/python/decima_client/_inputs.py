"""The files of one submitted volume, collected as the `decima` CLI collects them
(client/client_lib.cc: CollectInputs, AddHeaderDataFiles, KeepDicomFiles, HashInputs), so that
the same path gives the same manifest, the same blobs and the same error messages."""
import hashlib
import os
from dataclasses import dataclass

from .errors import InputError, MissingInputError

_CHUNK = 1 << 20


@dataclass
class InputFile:
    name: str  # manifest path: the file's base name, or its path inside the folder ("a/IM1")
    path: str  # where it is on this machine, as the caller spelled it
    size: int = 0
    sha256: str = ""


def collect(input_path):
    """A file -> itself; a folder -> every regular, non-hidden file below it, sorted by name.

    Raises MissingInputError for a path that is neither, InputError for an empty folder or a
    symbolic link inside it (refused by name, never followed: it may point anywhere)."""
    path = os.fspath(input_path)
    if os.path.isfile(path):
        return [InputFile(os.path.basename(path), path, os.path.getsize(path))]
    if not os.path.isdir(path):
        raise MissingInputError(f"{path}: no such file or folder")
    out = []
    for root, dirs, files in os.walk(path, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for d in dirs:
            if os.path.islink(os.path.join(root, d)):
                _refuse_link(os.path.join(root, d), path)
        for f in files:
            if f.startswith("."):
                continue
            p = os.path.join(root, f)
            if os.path.islink(p):
                _refuse_link(p, path)
            if not os.path.isfile(p):
                continue
            rel = os.path.relpath(p, path).replace(os.sep, "/")
            out.append(InputFile(rel, p, os.path.getsize(p)))
    if not out:
        raise InputError(f"{path}: the folder holds no files")
    out.sort(key=lambda f: f.name)
    return out


def _refuse_link(p, folder):
    raise InputError(f"{p}: is a symbolic link; only regular files inside {folder} are uploaded "
                     "(copy the file into the folder instead)")


def add_header_data_files(files):
    """For a single .mhd / .nhdr header: appends the data file(s) it names (MetaImage
    ElementDataFile, NRRD "data file:", single names or LIST), named relative to the header's
    folder. LOCAL data or an attached NRRD adds nothing. Raises InputError naming the header
    (and the line) for a missing file, one outside the header's folder, or a pattern."""
    if len(files) != 1:
        return files
    header = files[0]
    lname = header.name.lower()
    mhd, nhdr = lname.endswith(".mhd"), lname.endswith(".nhdr")
    if not mhd and not nhdr:
        return files
    try:
        with open(header.path, "r", encoding="latin-1") as f:
            lines = f.read().split("\n")[:10000]
    except OSError:
        raise InputError(f"{header.path}: cannot open") from None
    names, in_list = [], False
    for lineno, line in enumerate(lines, start=1):
        if in_list:
            if line.strip():
                names.append(line.strip())
            continue
        if mhd:
            key, eq, value = line.partition("=")
            if not eq or key.strip().lower() != "elementdatafile":
                continue
        else:
            if not line.strip():
                break  # the blank line ends an NRRD header
            key, colon, value = line.partition(":")
            if not colon or value.strip().startswith("="):
                continue
            if key.strip().lower() not in ("data file", "datafile"):
                continue
        value = value.strip()
        if value.lower() == "local":
            return files
        if value.lower().startswith("list"):
            in_list = True
            continue
        if "%" in value or " " in value:
            raise InputError(f"{header.path}:{lineno}: data file '{value}' is a pattern; copy "
                             "the slices and a LIST header into one folder")
        names.append(value)
        if mhd:
            break
    if not names:
        if mhd:
            raise InputError(f"{header.path}: no ElementDataFile line (a MetaImage header names "
                             "its data file)")
        return files
    folder = os.path.dirname(header.path)
    for n in names:
        rel = os.path.normpath(n)
        if os.path.isabs(rel) or rel in ("", ".") or rel.split(os.sep)[0] == "..":
            raise InputError(f"{header.path}: data file '{n}' is outside the header's folder; "
                             "copy it beside the header")
        p = os.path.join(folder, rel)
        if os.path.islink(p):
            raise InputError(f"{header.path}: its data file {p} is a symbolic link (copy the "
                             "file instead)")
        if not os.path.isfile(p):
            raise InputError(f"{header.path}: its data file {p} does not exist or is not a "
                             "regular file")
        files.append(InputFile(rel.replace(os.sep, "/"), p, os.path.getsize(p)))
    return files


def keep_dicom_files(files):
    """Keeps the files with the DICM marker at byte 128, minus DICOMDIR; returns (kept, the
    names dropped)."""
    kept, dropped = [], []
    for f in files:
        dicom = False
        if os.path.basename(f.path).lower() != "dicomdir":
            with open(f.path, "rb") as fh:
                magic = fh.read(132)
            dicom = len(magic) == 132 and magic[128:132] == b"DICM"
        (kept if dicom else dropped).append(f if dicom else f.name)
    return kept, dropped


def hash_files(files):
    """Fills each file's sha256 and size (from the bytes read, as the upload sends them)."""
    for f in files:
        h = hashlib.sha256()
        total = 0
        try:
            with open(f.path, "rb") as fh:
                while True:
                    chunk = fh.read(_CHUNK)
                    if not chunk:
                        break
                    h.update(chunk)
                    total += len(chunk)
        except OSError:
            raise InputError(f"{f.path}: cannot open") from None
        f.sha256 = h.hexdigest()
        f.size = total
    return files
