#!/usr/bin/env python3
"""Independent check of Decima's STL surfaces with VTK's own reader.

  check_stl.py FILE...
      Reads each FILE with vtkSTLReader (which joins vertices by position, as slicers and
      printers do) and prints "FILE triangles N boundary_edges N non_manifold_edges N" per file,
      the edge counts from vtkFeatureEdges.

Exits non-zero (printing the reason on stderr) if VTK reports any error.
"""
import sys

import vtk


def check(path):
    errors = []
    reader = vtk.vtkSTLReader()
    reader.AddObserver("ErrorEvent", lambda obj, event: errors.append(event))
    reader.SetFileName(path)
    reader.Update()
    if errors or reader.GetErrorCode() != 0:
        sys.exit(f"VTK failed to read {path}: {errors} code {reader.GetErrorCode()}")
    poly = reader.GetOutput()

    def edges(boundary, non_manifold):
        fe = vtk.vtkFeatureEdges()
        fe.SetInputData(poly)
        fe.SetBoundaryEdges(boundary)
        fe.SetNonManifoldEdges(non_manifold)
        fe.SetFeatureEdges(False)
        fe.SetManifoldEdges(False)
        fe.Update()
        return fe.GetOutput().GetNumberOfCells()

    print(path, "triangles", poly.GetNumberOfCells(), "boundary_edges", edges(True, False),
          "non_manifold_edges", edges(False, True))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: check_stl.py FILE...")
    for p in sys.argv[1:]:
        check(p)
