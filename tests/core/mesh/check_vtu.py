#!/usr/bin/env python3
"""Independent check of Decima's .vtu files with VTK's own XML reader and writer.

  check_vtu.py stats FILE
      Reads FILE with vtkXMLUnstructuredGridReader and prints one "key value" line per fact:
      counts, cell types, array types and sums, minimum signed tet volume.
  check_vtu.py rewrite IN OUTDIR
      Reads IN and writes it to OUTDIR with vtkXMLUnstructuredGridWriter in every data mode
      (ascii, inline base64 "binary", appended raw, appended base64) x compressor (none, zlib,
      lzma) x header type (UInt32, UInt64), printing "written PATH" per file, so the C++ test
      can check that ReadVtu reads files written by VTK itself.
  check_vtu.py same A B
      Reads A and B with VTK and compares every array exactly: points, connectivity, offsets,
      cell types, every point, cell and field data array by name and type. Prints "same" or
      exits non-zero naming the first difference (checks one encoding against another, e.g. an
      LZMA file against the raw file of the same mesh).
  check_vtu.py decimate IN OUT REDUCTION
      Runs vtkUnstructuredGridQuadricDecimation on IN (ScalarsName "scalar") and writes its
      output to OUT with VTK's writer: a file whose field VTK itself renamed to "scalars".

Exits non-zero (printing the reason on stderr) if VTK reports any error.
"""
import sys

import numpy as np
import vtk
from vtk.util.numpy_support import vtk_to_numpy


class ErrorCatcher:
    def __init__(self):
        self.errors = []

    def __call__(self, obj, event):
        self.errors.append(event)


def read(path):
    catcher = ErrorCatcher()
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.AddObserver("ErrorEvent", catcher)
    reader.SetFileName(path)
    reader.Update()
    if catcher.errors or reader.GetErrorCode() != 0:
        sys.exit(f"VTK failed to read {path}: {catcher.errors} code {reader.GetErrorCode()}")
    return reader.GetOutput()


def stats(path):
    grid = read(path)
    print("points", grid.GetNumberOfPoints())
    print("cells", grid.GetNumberOfCells())
    types = vtk_to_numpy(grid.GetCellTypesArray())
    print("cell_types", ",".join(str(t) for t in sorted(set(types.tolist()))))
    pts = vtk_to_numpy(grid.GetPoints().GetData()).astype(np.float64)
    print("points_type", grid.GetPoints().GetData().GetDataTypeAsString())
    print("points_abs_sum", repr(float(np.abs(pts).sum())))
    conn = vtk_to_numpy(grid.GetCells().GetConnectivityArray()).astype(np.int64)
    print("connectivity_sum", int(conn.sum()))
    if len(types):
        tets = conn.reshape(-1, 4)
        p = pts[tets]
        vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0],
                        np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0
        print("min_volume", repr(float(vol.min())))
        print("total_volume", repr(float(vol.sum())))
    for data, kind in ((grid.GetPointData(), "point"), (grid.GetCellData(), "cell")):
        for i in range(data.GetNumberOfArrays()):
            arr = data.GetArray(i)
            values = vtk_to_numpy(arr).astype(np.float64)
            finite = values[np.isfinite(values)]
            name = arr.GetName()
            print(f"{kind}_array {name} {arr.GetDataTypeAsString()} {arr.GetNumberOfTuples()}")
            print(f"sum_{name}", repr(float(finite.sum())))
            print(f"nonfinite_{name}", int(values.size - finite.size))
    # Field data (the region table): strings one per line, numbers comma-separated per tuple.
    fd = grid.GetFieldData()
    for i in range(fd.GetNumberOfArrays()):
        arr = fd.GetAbstractArray(i)
        name = arr.GetName()
        if arr.IsA("vtkStringArray"):
            for t in range(arr.GetNumberOfValues()):
                print(f"field_{name}_{t}", arr.GetValue(t))
        else:
            for t in range(arr.GetNumberOfTuples()):
                print(f"field_{name}_{t}", ",".join(str(int(v)) for v in arr.GetTuple(t)))


def rewrite(src, outdir):
    grid = read(src)
    for mode in ("ascii", "binary", "appended", "appended-base64"):
        for compress in ("none", "zlib", "lzma"):
            if mode == "ascii" and compress != "none":
                continue
            for header in ("32", "64"):
                dst = f"{outdir}/{mode}-{compress}-{header}.vtu"
                write(grid, dst, mode, compress, header)
                print("written", dst)


def write(grid, dst, mode, compress, header):
    writer = vtk.vtkXMLUnstructuredGridWriter()
    catcher = ErrorCatcher()
    writer.AddObserver("ErrorEvent", catcher)
    writer.SetInputData(grid)
    writer.SetFileName(dst)
    if mode == "ascii":
        writer.SetDataModeToAscii()
    elif mode == "binary":
        writer.SetDataModeToBinary()
    else:
        writer.SetDataModeToAppended()
        writer.SetEncodeAppendedData(1 if mode == "appended-base64" else 0)
    if compress == "zlib":
        writer.SetCompressorTypeToZLib()
    elif compress == "lzma":
        writer.SetCompressorTypeToLZMA()
    else:
        writer.SetCompressorTypeToNone()
    if header == "64":
        writer.SetHeaderTypeToUInt64()
    else:
        writer.SetHeaderTypeToUInt32()
    if writer.Write() != 1 or catcher.errors:
        sys.exit(f"VTK failed to write {dst}")


def arrays(grid):
    out = {
        "points": grid.GetPoints().GetData(),
        "connectivity": grid.GetCells().GetConnectivityArray(),
        "offsets": grid.GetCells().GetOffsetsArray(),
        "types": grid.GetCellTypesArray(),
    }
    for data, kind in ((grid.GetPointData(), "point"), (grid.GetCellData(), "cell"),
                       (grid.GetFieldData(), "field")):
        for i in range(data.GetNumberOfArrays()):
            arr = data.GetAbstractArray(i)
            out[f"{kind} {arr.GetName()}"] = arr
    return out


def same(path_a, path_b):
    a, b = arrays(read(path_a)), arrays(read(path_b))
    if sorted(a) != sorted(b):
        sys.exit(f"different arrays: {sorted(a)} against {sorted(b)}")
    for name in sorted(a):
        x, y = a[name], b[name]
        if x.IsA("vtkStringArray") or y.IsA("vtkStringArray"):
            xs = [x.GetValue(i) for i in range(x.GetNumberOfValues())]
            ys = [y.GetValue(i) for i in range(y.GetNumberOfValues())]
            if xs != ys:
                sys.exit(f"{name}: {xs} against {ys}")
            continue
        if x.GetDataTypeAsString() != y.GetDataTypeAsString():
            sys.exit(f"{name}: type {x.GetDataTypeAsString()} against {y.GetDataTypeAsString()}")
        u, v = vtk_to_numpy(x), vtk_to_numpy(y)
        # Bit patterns, so NaN/inf compare exactly.
        if u.shape != v.shape or u.tobytes() != v.tobytes():
            sys.exit(f"{name}: values differ ({u.shape} against {v.shape})")
    print("same")


def decimate(src, dst, reduction):
    decimation = vtk.vtkUnstructuredGridQuadricDecimation()
    decimation.SetInputData(read(src))
    decimation.SetTargetReduction(float(reduction))
    decimation.SetScalarsName("scalar")
    decimation.Update()
    write(decimation.GetOutput(), dst, "appended", "zlib", "64")


def main(argv):
    if len(argv) >= 3 and argv[1] == "stats":
        stats(argv[2])
    elif len(argv) == 4 and argv[1] == "rewrite":
        rewrite(*argv[2:])
    elif len(argv) == 4 and argv[1] == "same":
        same(*argv[2:])
    elif len(argv) == 5 and argv[1] == "decimate":
        decimate(*argv[2:])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main(sys.argv)
