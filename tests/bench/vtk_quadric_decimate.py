#!/usr/bin/env python3
"""decima-compare's VTK side: VTK's quadric decimation of a tetrahedral .vtu.

  vtk_quadric_decimate.py IN OUT REDUCTION SCALARS_NAME

Reads IN with vtkXMLUnstructuredGridReader, runs vtkUnstructuredGridQuadricDecimation with VTK's
defaults except SetTargetReduction(REDUCTION) and SetScalarsName(SCALARS_NAME), writes the
output to OUT (appended raw, uncompressed: the file is temporary), and prints one JSON object on
stdout:
  execute_seconds  the filter's Update() alone (its RequestData: the decimation)
  read_seconds, write_seconds, cells_in, points_in, cells_out, points_out, vtk_version,
  point_arrays_out (VTK renames the field to "scalars" and drops every other array)
Exits non-zero with the reason on stderr if VTK reports an error.
"""
import json
import sys
import time

import vtk


class ErrorCatcher:
    def __init__(self):
        self.errors = []

    def __call__(self, obj, event):
        self.errors.append(event)


def checked(algorithm):
    catcher = ErrorCatcher()
    algorithm.AddObserver("ErrorEvent", catcher)
    return catcher


def main(argv):
    if len(argv) != 5:
        sys.exit(__doc__)
    src, dst, reduction, scalars_name = argv[1], argv[2], float(argv[3]), argv[4]

    start = time.perf_counter()
    reader = vtk.vtkXMLUnstructuredGridReader()
    read_errors = checked(reader)
    reader.SetFileName(src)
    reader.Update()
    if read_errors.errors or reader.GetErrorCode() != 0:
        sys.exit(f"VTK failed to read {src}")
    grid = reader.GetOutput()
    read_seconds = time.perf_counter() - start
    if grid.GetPointData().GetArray(scalars_name) is None:
        sys.exit(f"{src} has no point array '{scalars_name}'")

    decimation = vtk.vtkUnstructuredGridQuadricDecimation()
    decimation_errors = checked(decimation)
    decimation.SetInputData(grid)
    decimation.SetTargetReduction(reduction)
    decimation.SetScalarsName(scalars_name)
    start = time.perf_counter()
    decimation.Update()
    execute_seconds = time.perf_counter() - start
    if decimation_errors.errors:
        sys.exit("vtkUnstructuredGridQuadricDecimation reported an error")
    out = decimation.GetOutput()

    start = time.perf_counter()
    writer = vtk.vtkXMLUnstructuredGridWriter()
    write_errors = checked(writer)
    writer.SetInputData(out)
    writer.SetFileName(dst)
    writer.SetDataModeToAppended()
    writer.SetEncodeAppendedData(0)
    writer.SetCompressorTypeToNone()
    writer.SetHeaderTypeToUInt64()
    if writer.Write() != 1 or write_errors.errors:
        sys.exit(f"VTK failed to write {dst}")
    write_seconds = time.perf_counter() - start

    data = out.GetPointData()
    arrays = [data.GetArrayName(i) for i in range(data.GetNumberOfArrays())]
    print(json.dumps({
        "execute_seconds": execute_seconds,
        "read_seconds": read_seconds,
        "write_seconds": write_seconds,
        "cells_in": grid.GetNumberOfCells(),
        "points_in": grid.GetNumberOfPoints(),
        "cells_out": out.GetNumberOfCells(),
        "points_out": out.GetNumberOfPoints(),
        "point_arrays_out": arrays,
        "vtk_version": vtk.vtkVersion.GetVTKVersion(),
    }))


if __name__ == "__main__":
    main(sys.argv)
