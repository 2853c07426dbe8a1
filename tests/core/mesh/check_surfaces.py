#!/usr/bin/env python3
"""Independent check of Decima's region surfaces with VTK's own readers.

  check_surfaces.py FILE...
      A .stl FILE is read with vtkSTLReader (which joins vertices by position, as slicers and
      printers do): prints "FILE triangles N boundary_edges N non_manifold_edges N", the edge
      counts from vtkFeatureEdges. A .glb FILE is read with vtkGLTFReader: prints
      "FILE meshes N" and then "FILE mesh I points N triangles N" per mesh.

Exits non-zero (printing the reason on stderr) if VTK reports any error.
"""
import sys

import vtk


def check_glb(path):
    errors = []
    reader = vtk.vtkGLTFReader()
    reader.AddObserver("ErrorEvent", lambda obj, event: errors.append(event))
    reader.SetFileName(path)
    reader.Update()
    if errors:
        sys.exit(f"VTK failed to read {path}: {errors}")
    out = reader.GetOutput()
    meshes = []
    it = out.NewIterator()
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        meshes.append(it.GetCurrentDataObject())
        it.GoToNextItem()
    print(path, "meshes", len(meshes))
    for i, m in enumerate(meshes):
        print(path, "mesh", i, "points", m.GetNumberOfPoints(), "triangles", m.GetNumberOfCells())


def check(path):
    if path.endswith(".glb"):
        return check_glb(path)
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
        sys.exit("usage: check_surfaces.py FILE...")
    for p in sys.argv[1:]:
        check(p)
