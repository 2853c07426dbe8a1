"""A job's label map and mesh as numpy arrays, read with VTK (Debian's python3-vtk9:
vtkNIFTIImageReader for labels.nii.gz, vtkXMLUnstructuredGridReader for mesh.vtu) rather than
with readers of our own. Optional: numpy and vtk are imported only here, when asked for."""
import tempfile

import grpc

from . import errors


def _modules():
    try:
        import numpy
        from vtkmodules.util import numpy_support
        from vtkmodules.vtkIOImage import vtkNIFTIImageReader
        from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader
    except ImportError as e:
        raise errors.MissingDependencyError(
            f"arrays need numpy and VTK's Python modules ({e.name} is missing; Debian: "
            "apt-get install python3-numpy python3-vtk9, and a venv made with "
            "--system-site-packages)") from None
    return numpy, numpy_support, vtkNIFTIImageReader, vtkXMLUnstructuredGridReader


def _fetched(job, kind, out_dir, read):
    """Fetches one artifact of `job` into out_dir (a temporary folder when None) and returns
    read(path)."""
    if out_dir is not None:
        return read(job.fetch(out_dir, outputs=[kind])[0])
    with tempfile.TemporaryDirectory(prefix="decima-arrays-") as tmp:
        return read(job.fetch(tmp, outputs=[kind])[0])


def label_map(job, out_dir=None):
    """labels.nii.gz of a succeeded job as a numpy array indexed [x, y, z] (the file's voxel
    order, as nibabel's get_fdata), one region label per voxel."""
    numpy, numpy_support, nifti_reader, _ = _modules()

    def read(path):
        r = nifti_reader()
        r.SetFileName(path)
        r.Update()
        image = r.GetOutput()
        nx, ny, nz = image.GetDimensions()
        scalars = image.GetPointData().GetScalars()
        if scalars is None or nx * ny * nz == 0:
            raise errors.from_status(grpc.StatusCode.DATA_LOSS,
                                     f"{path}: VTK read no voxels", "label map " + job.name)
        flat = numpy_support.vtk_to_numpy(scalars)
        # VTK keeps x fastest: (z, y, x) in C order, turned into [x, y, z].
        return numpy.ascontiguousarray(flat.reshape(nz, ny, nx).transpose(2, 1, 0))

    return _fetched(job, "labels", out_dir, read)


def mesh(job, out_dir=None):
    """mesh.vtu of a succeeded job as numpy arrays: {"points": (N, 3) float32 in mm,
    "tets": (M, 4) vertex indices, and every point and cell array of the file by name
    ("scalar", "label", "feature", "boundary", "interface_distance", "region")}."""
    numpy, numpy_support, _, vtu_reader = _modules()

    def read(path):
        r = vtu_reader()
        r.SetFileName(path)
        r.Update()
        grid = r.GetOutput()
        if grid is None or grid.GetNumberOfPoints() == 0:
            raise errors.from_status(grpc.StatusCode.DATA_LOSS,
                                     f"{path}: VTK read no points", "mesh " + job.name)
        out = {"points": numpy_support.vtk_to_numpy(grid.GetPoints().GetData()).copy()}
        conn = numpy_support.vtk_to_numpy(grid.GetCells().GetConnectivityArray())
        out["tets"] = conn.reshape(-1, 4).copy()
        for data in (grid.GetPointData(), grid.GetCellData()):
            for i in range(data.GetNumberOfArrays()):
                out[data.GetArrayName(i)] = numpy_support.vtk_to_numpy(data.GetArray(i)).copy()
        return out

    return _fetched(job, "vtu", out_dir, read)
