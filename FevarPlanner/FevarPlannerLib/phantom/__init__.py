"""Synthetic AAA phantoms with ground truth, for the paper's simulation experiment (Sec. III).

A phantom is a set of vessel centrelines (LPS mm) with a lumen radius per point: the aorta
(upper aorta, neck, fusiform aneurysm sac with non-enhancing thrombus, distal aorta), the
left and right renal arteries, the common iliacs and, by parameter, the SMA, the coeliac
trunk and the internal iliacs (label ``other``). From it we render

* a contrast CT (int16 HU, DICOM series) and the pre-operative lumen mask on its grid;
* a DSA-like fluoroscopic frame of the intra-operative shape (DICOM XA with the C-arm
  tags) and its projected lumen mask;
* the ground truth: the dense pre- and intra-operative centrelines (node ``n`` of one is
  node ``n`` of the other) and the true projection matrix.

Intra-operative deformation
---------------------------
The intra-operative shape comes from rotating the segments of each centreline (aortic
bending about the renal level, iliac straightening and swing as a stiff wire causes, a
change of the renal take-off angle). Rotating segments keeps every segment length, so the
vessel lengths are preserved exactly and both shapes resample to the same graph.

Paper protocol
--------------
Sec. III-A/B: five deformed states of one phantom; each state's pre-operative 3D skeleton
is paired with the intra-operative 2D skeleton of each of the other four states, giving
20 cases. :func:`paper_protocol` builds one rest anatomy and five deformation states of it
(same shape parameters, different deformations) and returns the 20 ordered pairs
``(state i, state j)``, ``i != j``. Pairing states of the SAME phantom is what makes the
pairs geometrically meaningful: the true intra-operative shape is a smooth, length
preserving deformation of the pre-operative one, as for the physical phantom bent by a
string in the paper. The paper's simulated frames are projected without misalignment; the
in-plane misalignment of its robustness test is a parameter here (``misalign_*``).

Coordinates: LPS (+x patient left, +y posterior, +z superior), mm. The CT grid is axis
aligned (identity direction), the C-arm isocentre is the CT grid centre, so the P built
from the DICOM tags with :func:`projection.projection_matrix_from_carm` equals ``P_true``.

Modules
-------
:mod:`.params` (:class:`PhantomParams`, :func:`random_params`), :mod:`.anatomy` (the rest
anatomy), :mod:`.deform` (the intra-operative deformation), :mod:`.raster` (CT grid, tube
distance fields, lumen mask), :mod:`.ct` (the CT), :mod:`.fluoro` (the frame, the detector,
the misaligned pose), :mod:`.case` (a case and its folder), :mod:`.protocol` (the paper
protocol and sets of cases). The public names of the former ``phantom.py`` import from
here as before.
"""

from .anatomy import BASE_STEP_MM, Anatomy, Vessel, build_preop_anatomy
from .case import PhantomCase, generate_case, write_case
from .ct import render_ct
from .deform import deform_anatomy, state_anatomy
from .fluoro import fit_detector, render_fluoro
from .params import PARAM_RANGES, PhantomParams, random_params
from .protocol import PAPER_OUT_OF_PLANE_DEG, PAPER_STATES, paper_protocol, write_phantom_set
from .raster import Grid, ct_grid, rasterize_lumen

__all__ = [
    "PhantomParams",
    "random_params",
    "Vessel",
    "Anatomy",
    "build_preop_anatomy",
    "deform_anatomy",
    "state_anatomy",
    "Grid",
    "ct_grid",
    "PhantomCase",
    "generate_case",
    "rasterize_lumen",
    "render_ct",
    "render_fluoro",
    "fit_detector",
    "write_case",
    "write_phantom_set",
    "paper_protocol",
]
