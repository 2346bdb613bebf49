"""Lumen mask -> surface (marching cubes) and its VTP file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import vtk
from scipy import ndimage as ndi
from skimage import measure
from vtk.util import numpy_support

from ..files import InputError, atomic_path
from ..io import Volume
from .threshold import _bounding_box


def mask_surface(mask: Volume, *, smooth_sigma_vox: float = 0.0) -> vtk.vtkPolyData:
    """Closed triangle surface of a binary mask by marching cubes, points in LPS mm.

    The mask is cropped to its bounding box, padded by one voxel (so the surface closes) and
    iso-surfaced at 0.5 (optionally after a Gaussian blur of ``smooth_sigma_vox`` voxels).
    Normals point out of the lumen.
    """
    array = np.asarray(mask.array) > 0
    if not array.any():
        raise InputError("mask is empty: no surface to extract")
    box = _bounding_box(array)
    lo = np.array([b.start for b in box])
    field = np.pad(array[box].astype(np.float32), 1)
    if smooth_sigma_vox > 0:
        field = ndi.gaussian_filter(field, smooth_sigma_vox)
    verts, faces, normals, _ = measure.marching_cubes(field, level=0.5, gradient_direction="descent")
    points = mask.index_to_lps(verts + lo - 1)
    linear = mask.direction @ np.diag(mask.spacing)
    normals_lps = normals[:, ::-1] @ np.linalg.inv(linear)      # covector transform, (i, j, k) order
    normals_lps /= np.linalg.norm(normals_lps, axis=1, keepdims=True) + 1e-12
    faces = _wind_like_normals(points, faces, normals_lps)
    return _polydata(points, faces, normals_lps)


def _wind_like_normals(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Faces reordered, if needed, so that their right-hand normals agree with the vertex normals."""
    a, b, c = (points[faces[:, n]] for n in range(3))
    agreement = np.einsum("ij,ij->i", np.cross(b - a, c - a), normals[faces].sum(axis=1))
    return faces[:, ::-1] if agreement.sum() < 0 else faces


def _polydata(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> vtk.vtkPolyData:
    poly = vtk.vtkPolyData()
    vtk_points = vtk.vtkPoints()
    vtk_points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    poly.SetPoints(vtk_points)
    offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
    polys = vtk.vtkCellArray()
    polys.SetData(numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(faces.astype(np.int64).ravel(), deep=True))
    poly.SetPolys(polys)
    vtk_normals = numpy_support.numpy_to_vtk(np.ascontiguousarray(normals, dtype=np.float32), deep=True)
    vtk_normals.SetName("Normals")
    poly.GetPointData().SetNormals(vtk_normals)
    return poly


def write_surface_vtp(path, polydata: vtk.vtkPolyData) -> None:
    """Write a surface as VTK XML PolyData (``.vtp``), atomically."""
    path = Path(path)
    with atomic_path(path, suffix=".vtp") as tmp:
        writer = vtk.vtkXMLPolyDataWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputData(polydata)
        writer.SetDataModeToBinary()
        if writer.Write() != 1:
            raise OSError(f"{path}: VTK could not write the surface")
