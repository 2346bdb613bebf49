"""Perspective projection of LPS points onto the fluoroscopic frame (paper eq. 1).

Conventions (docs/DESIGN.md section 3)
---------------------------------
* World points are DICOM patient LPS in millimetres.
* Image coordinates: ``u`` = column, ``v`` = row, 0-based, (0, 0) is the centre of the
  first stored pixel.
* ``P`` is a 3x4 matrix with ``[w*u, w*v, w]^T = P @ [x, y, z, 1]^T``. Nothing here assumes
  that its 3x3 part is a rotation times intrinsics: a mirrored display is a valid ``P``.

C-arm convention (the one place it is written down)
---------------------------------------------------
The C-arm rotates about its isocentre ``c`` (LPS mm). At PositionerPrimaryAngle = 0 and
PositionerSecondaryAngle = 0 the view is antero-posterior: the source lies posterior to
the patient at ``c + SOD * (0, +1, 0)``, the detector anterior, and the image is shown as
seen from the front (radiological display): columns (``+u``) run towards the patient's
left (``+x``), rows (``+v``) towards the feet (``-z``).

The primary angle ``a`` (LAO positive, RAO negative) turns the detector towards the
patient's left about the cranio-caudal axis; the secondary angle ``b`` (cranial positive,
caudal negative) tilts it towards the head. With ``d`` the unit vector from source to
detector,

    d      = (sin a cos b, -cos a cos b, sin b)
    u_axis = (cos a, sin a, 0)          (stays in the axial plane)
    v_axis = u_axis x d

The principal point is the detector centre, ``((cols-1)/2, (rows-1)/2)``, and the
magnification follows from SID (source-detector) and the detector pixel size
(ImagerPixelSpacing = [row spacing, column spacing] in mm). DICOM XA frames do not say
where the isocentre lies in the CT; callers pass it (the case reader uses the centre of
the CT volume, which is where the phantoms put it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .conventions import LPS_DIRECTIONS

__all__ = [
    "CArmGeometry",
    "project",
    "projection_jacobian",
    "homogeneous_columns",
    "pull_back_columns",
    "depth",
    "projection_matrix_from_carm",
    "image_directions",
    "source_position",
    "view_spread_deg",
    "validate_projection_matrix",
    "read_geometry_json",
    "write_geometry_json",
    "in_plane_transform",
    "principal_point",
    "patient_motion",
    "GeometrySource",
    "view_label",
    "GeometryAssumptionWarning",
    "read_geometry_file",
    "facing_the_scan",
    "apply_in_plane_correction",
    "update_in_plane_correction",
]


@dataclass(frozen=True)
class CArmGeometry:
    """The C-arm tags of an XA/RF frame that define its projection.

    Attributes
    ----------
    sid, sod : float
        DistanceSourceToDetector and DistanceSourceToPatient (isocentre), mm.
    pixel_spacing : tuple of float
        ImagerPixelSpacing ``(row spacing, column spacing)`` at the detector, mm.
    primary_angle, secondary_angle : float
        PositionerPrimaryAngle (LAO +) and PositionerSecondaryAngle (cranial +), degrees.
    rows, cols : int
        Image size in pixels.
    """

    sid: float
    sod: float
    pixel_spacing: tuple[float, float]
    primary_angle: float
    secondary_angle: float
    rows: int
    cols: int


def _homogeneous(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    return np.concatenate([points, np.ones((*points.shape[:-1], 1))], axis=-1)


def project(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Project LPS points (..., 3) to image coordinates (..., 2): ``f(Y)`` of eq. (1)."""
    # eq. (1): f(Y) = (p1^T Y^h / p3^T Y^h, p2^T Y^h / p3^T Y^h)
    h = _homogeneous(points) @ np.asarray(P, dtype=float).T
    return h[..., :2] / h[..., 2:3]


def projection_jacobian(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The Jacobian ``d f / d y`` of eq. (1) at LPS points (..., 3), shape (..., 2, 3).

    ``d f_u / d y = (p1 - u p3) / w`` and ``d f_v / d y = (p2 - v p3) / w`` (first three
    columns of the rows of ``P``); its null space is the ray through the point.
    """
    P = np.asarray(P, dtype=float)
    h = _homogeneous(points) @ P.T
    f = h[..., :2] / h[..., 2:3]
    return (P[:2, :3] - f[..., :, None] * P[2, :3]) / h[..., 2, None, None]


def homogeneous_columns(P: np.ndarray, points_cm: np.ndarray) -> np.ndarray:
    """``P [y; 1]`` for component-major points ``(3, n)``: rows ``w u``, ``w v``, ``w`` (eq. 1).

    The registration energies work on (3, n) arrays; ``f = h[:2] / h[2]``.
    """
    return P[:, :3] @ points_cm + P[:, 3:4]


def pull_back_columns(P: np.ndarray, fu: np.ndarray, fv: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum_k (d f_k / d y)^T g_k`` per point, component-major (3, n), from ``(a, b) = g / w``.

    With ``g`` the gradient of a function of the projections ``f = (fu, fv)`` (eq. 1),
    the chain rule through :func:`projection_jacobian` gives
    ``P[:, :3]^T [a, b, -(a fu + b fv)]`` where the caller has already divided ``g`` by
    ``w`` (it usually has ``1 / w`` at hand).
    """
    return P[:, :3].T @ np.vstack([a, b, -(a * fu + b * fv)])


def depth(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The homogeneous weight ``w = p3^T y^h`` of each point (proportional to depth)."""
    return _homogeneous(points) @ np.asarray(P, dtype=float)[2]


def carm_axes(primary_deg: float, secondary_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (source->detector ``d``, image ``u`` axis, image ``v`` axis) in LPS."""
    a, b = np.deg2rad(primary_deg), np.deg2rad(secondary_deg)
    d = np.array([np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)])
    u_axis = np.array([np.cos(a), np.sin(a), 0.0])
    v_axis = np.cross(u_axis, d)
    return d, u_axis, v_axis


def projection_matrix_from_carm(geometry: CArmGeometry, isocenter=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Build ``P`` from the C-arm tags, with the isocentre at ``isocenter`` (LPS mm).

    Parameters
    ----------
    geometry : CArmGeometry
        SID, SOD, detector pixel spacing, angles and image size.
    isocenter : array_like, shape (3,)
        Where the C-arm isocentre lies in the CT's LPS frame.

    Returns
    -------
    numpy.ndarray, shape (3, 4)
    """
    g = geometry
    if not (g.sid > 0 and 0 < g.sod < g.sid):
        raise ValueError(f"C-arm distances must satisfy 0 < SOD < SID (got SOD={g.sod}, SID={g.sid})")
    if min(g.pixel_spacing) <= 0 or g.rows <= 0 or g.cols <= 0:
        raise ValueError("C-arm pixel spacing and image size must be positive")
    d, u_axis, v_axis = carm_axes(g.primary_angle, g.secondary_angle)
    source = np.asarray(isocenter, dtype=float) - g.sod * d
    row_mm, col_mm = g.pixel_spacing
    cu, cv = (g.cols - 1) / 2.0, (g.rows - 1) / 2.0
    p3 = np.append(d, -d @ source)
    p1 = (g.sid / col_mm) * np.append(u_axis, -u_axis @ source) + cu * p3
    p2 = (g.sid / row_mm) * np.append(v_axis, -v_axis @ source) + cv * p3
    return np.vstack([p1, p2, p3])


def source_position(P: np.ndarray) -> np.ndarray:
    """The camera centre (X-ray source) of ``P``: its right null vector, in LPS mm."""
    P = np.asarray(P, dtype=float)
    return -np.linalg.solve(P[:, :3], P[:, 3])


def view_spread_deg(Ps, at) -> float:
    """The widest angle (degrees, 0-90) between the X-rays of several views through ``at`` (LPS).

    One view sees nothing along its ray; two views whose rays through the anatomy cross at
    an angle see depth, the better the nearer that angle is to 90 degrees. A ray and its
    reverse are the same line, so the angle is folded into 0-90.
    """
    rays = [np.asarray(at, dtype=float) - source_position(P) for P in Ps]
    rays = [ray / np.linalg.norm(ray) for ray in rays]
    cosines = [abs(float(a @ b)) for k, a in enumerate(rays) for b in rays[k + 1:]]
    return float(np.degrees(np.arccos(min(min(cosines), 1.0)))) if cosines else 0.0


#: Largest magnitude accepted for an entry of P; P is defined up to scale, so a P whose
#: entries exceed it (a P times 1e300) is refused rather than overflowing in the maths.
MAX_P_ENTRY = 1e12


def validate_projection_matrix(P, name: str = "projection matrix") -> np.ndarray:
    """Return ``P`` as a float (3, 4) array or raise ``ValueError`` saying what is wrong.

    Refused: anything that is not 3x4 numbers (text, booleans, nesting), NaN or infinity,
    entries beyond :data:`MAX_P_ENTRY` or all below its inverse (badly scaled), and a
    singular 3x3 part.
    """
    if isinstance(P, (list, tuple)):
        _check_json_matrix(P, name)
    try:
        P = np.asarray(P, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric 3x4 matrix ({exc})") from None
    if P.shape != (3, 4):
        raise ValueError(f"{name}: expected a 3x4 matrix, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    largest = float(np.abs(P).max())
    if largest < 1.0 / MAX_P_ENTRY:
        raise ValueError(f"{name}: degenerate (every entry is below {1.0 / MAX_P_ENTRY:g})")
    if largest > MAX_P_ENTRY:
        raise ValueError(f"{name}: badly scaled (largest entry {largest:.3g}; P is defined up to scale, divide it "
                         f"so that its entries lie within 1e-12..1e12)")
    rows = P[:, :3] / np.maximum(np.linalg.norm(P[:, :3], axis=1, keepdims=True), 1e-300)
    if abs(np.linalg.det(rows)) < 1e-9:
        raise ValueError(f"{name}: degenerate (its 3x3 part is singular)")
    return P


def _check_json_matrix(rows, name: str) -> None:
    """Refuse a nested list that is not 3 rows of 4 plain numbers, naming the offending entry."""
    if len(rows) != 3 or not all(isinstance(row, (list, tuple)) and len(row) == 4 for row in rows):
        raise ValueError(f"{name}: expected a 3x4 matrix (3 rows of 4 numbers)")
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise ValueError(f"{name}: entry [{i}][{j}] is {type(value).__name__} {str(value)[:20]!r}, "
                                 f"not a number")


def image_directions(P: np.ndarray, at: np.ndarray, step_mm: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit image vectors of the patient's left (+x) and superior (+z) directions at ``at``.

    They let 2D code name left/right and up/down whatever the view (mirrored displays,
    LAO/RAO, a flipped detector) without decomposing ``P``.
    """
    at = np.asarray(at, dtype=float)
    base = project(P, at)
    left = project(P, at + step_mm * LPS_DIRECTIONS["left"]) - base
    superior = project(P, at + step_mm * LPS_DIRECTIONS["superior"]) - base
    return left / np.linalg.norm(left), superior / np.linalg.norm(superior)


def pixels_per_mm(P: np.ndarray, at) -> float | np.ndarray:
    """Image pixels per mm at the depth of ``at`` (the perspective magnification of eq. 1).

    The mean of the image lengths of one mm towards the patient's left and one mm superior.
    ``at`` is one LPS point (3,), giving a float, or points (n, 3), giving an (n,) array.
    """
    at = np.asarray(at, dtype=float)
    uv = project(P, np.array([at, at + LPS_DIRECTIONS["left"], at + LPS_DIRECTIONS["superior"]]))
    per_mm = 0.5 * (np.linalg.norm(uv[1] - uv[0], axis=-1) + np.linalg.norm(uv[2] - uv[0], axis=-1))
    return float(per_mm) if per_mm.ndim == 0 else per_mm


def in_plane_transform(P: np.ndarray, translation=(0.0, 0.0), rotation_deg: float = 0.0,
                       scale: float = 1.0, center=(0.0, 0.0)) -> np.ndarray:
    """Compose ``P`` with a similarity transform of the image plane about ``center`` (u, v).

    Used to simulate misaligned frames (paper Fig. 5) and by the in-plane pose refinement.
    """
    t = np.deg2rad(rotation_deg)
    c = np.asarray(center, dtype=float)
    R = scale * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    A = np.eye(3)
    A[:2, :2] = R
    A[:2, 2] = c - R @ c + np.asarray(translation, dtype=float)
    return A @ np.asarray(P, dtype=float)


def principal_point(P: np.ndarray) -> np.ndarray:
    """Where the principal axis (the ray normal to the detector) meets the image, ``(u, v)``."""
    P = np.asarray(P, dtype=float)
    axis = P[2, :3] / np.linalg.norm(P[2, :3])
    return project(P, source_position(P) + axis)


def patient_motion(P: np.ndarray, at, translation_px=(0.0, 0.0), rotation_deg: float = 0.0) -> np.ndarray:
    """The rigid motion of the patient that moves their image by an in-plane offset.

    A rotation about the principal axis by ``rotation_deg`` turns the image about
    :func:`principal_point` exactly as ``in_plane_transform(P, rotation_deg=...,
    center=principal_point(P))`` does; then a translation parallel to the detector moves the
    image of ``at`` by ``translation_px`` (points at other depths move by their own
    magnification, a fraction of a pixel apart over an abdomen). So a frame that shows the
    anatomy offset in-plane is read as "the patient moved and ``P`` is still right".

    Parameters
    ----------
    P : (3, 4)
    at : (3,)
        LPS point whose image moves by exactly ``translation_px`` (the anatomy's centre).
    translation_px : (2,)
    rotation_deg : float

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        Homogeneous LPS motion: ``moved = points @ T[:3, :3].T + T[:3, 3]``.
    """
    P = np.asarray(P, dtype=float)
    source, axis = source_position(P), P[2, :3] / np.linalg.norm(P[2, :3])
    # about the axis through the source; the sign makes the image turn as in
    # in_plane_transform (u right, v down)
    R = Rotation.from_rotvec(-np.deg2rad(rotation_deg) * axis).as_matrix()
    turned = source + (np.asarray(at, dtype=float) - source) @ R.T
    # the image of ``turned`` moves by J d for a small shift d; the least-norm d is parallel
    # to the detector (J's null space is the ray), and linear in d at fixed depth
    jacobian = projection_jacobian(P, turned)
    shift = np.linalg.pinv(jacobian) @ np.asarray(translation_px, dtype=float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = source - source @ R.T + shift
    return T


def read_geometry_json(path) -> np.ndarray:
    """Read ``{"projection_matrix": [[4], [4], [4]]}`` and return a validated ``P``."""
    P, _ = read_geometry_file(path)
    if P is None:
        raise ValueError(f"{path}: no 'projection_matrix' key")
    return P


def write_geometry_json(path, P: np.ndarray, **extra) -> None:
    """Write ``P`` (and any JSON-serialisable extras) to ``path`` atomically."""
    from .files import write_text_atomic

    P = validate_projection_matrix(P)
    payload = {"projection_matrix": P.tolist(), **extra}
    write_text_atomic(path, json.dumps(payload, indent=2))


# ----------------------------------------------------------------------------- provenance

def view_label(primary_deg: float, secondary_deg: float) -> str:
    """The clinical name of a C-arm view: ``view_label(30, -10) == "LAO 30 / CAU 10"``."""
    return (f"{'LAO' if primary_deg >= 0 else 'RAO'} {abs(primary_deg):.0f} / "
            f"{'CRA' if secondary_deg >= 0 else 'CAU'} {abs(secondary_deg):.0f}")


class GeometryAssumptionWarning(UserWarning):
    """``P`` rests on an assumption the input files do not state (e.g. where the isocentre is)."""


#: The geometry.json key of the user's in-plane correction (a drag / rotate of the overlay).
CORRECTION_KEY = "in_plane_correction"


@dataclass
class GeometrySource:
    """Where a case's ``P`` came from and what it assumed; written into result.json as ``geometry``.

    Attributes
    ----------
    kind : {"geometry.json", "dicom-tags"}
        A calibrated matrix, or one built from the frame's C-arm tags.
    file : str
        The file ``P`` was read or built from.
    tags : dict
        The C-arm tag values used (``dicom-tags`` only).
    isocenter_lps : list of float or None
        Where the isocentre was placed (``dicom-tags`` only).
    assumptions : list of str
        Plain statements of what the files did not say and was assumed.
    in_plane_correction : dict or None
        ``{"translation_px": [du, dv], "rotation_deg": r, "file": ...}`` applied on top.
    sign_flipped : bool
        The file's matrix put the scan behind the source (``w < 0``), so its negative is used
        (:func:`facing_the_scan`): the same projection, the sign the pipeline reads depth by.
    """

    kind: str
    file: str
    tags: dict = field(default_factory=dict)
    isocenter_lps: list | None = None
    assumptions: list = field(default_factory=list)
    in_plane_correction: dict | None = None
    sign_flipped: bool = False

    @classmethod
    def from_carm(cls, carm: CArmGeometry, file, isocenter) -> "GeometrySource":
        """The note for ``P`` built by :func:`projection_matrix_from_carm` with the isocentre at ``isocenter``."""
        isocenter = [round(float(c), 3) for c in isocenter]
        tags = {"DistanceSourceToDetector": carm.sid, "DistanceSourceToPatient": carm.sod,
                "ImagerPixelSpacing": list(carm.pixel_spacing), "PositionerPrimaryAngle": carm.primary_angle,
                "PositionerSecondaryAngle": carm.secondary_angle, "Rows": carm.rows, "Columns": carm.cols}
        assumptions = [f"the C-arm isocentre lies at the centre of the CT volume, LPS {isocenter} mm",
                       "the table position (the patient's offset from the isocentre) is unknown and taken as zero",
                       "the patient lies supine, head first, as in the CT"]
        return cls("dicom-tags", str(file), tags, isocenter, assumptions)

    def view_name(self) -> str | None:
        """``"LAO 30 / CRA 15"`` from the tags, or None when ``P`` did not come from tags."""
        if "PositionerPrimaryAngle" not in self.tags:
            return None
        return view_label(self.tags["PositionerPrimaryAngle"], self.tags["PositionerSecondaryAngle"])

    def describe(self) -> str:
        """One line for stderr: which geometry, and what it assumed."""
        text = f"geometry from {self.kind} ({self.file})"
        if self.assumptions:
            text += ": assumed " + "; ".join(self.assumptions)
            text += ". Check drr_check.png; correct with `fevar-planner geometry CASE --shift DU DV --rotate R`"
        if self.in_plane_correction:
            c = self.in_plane_correction
            text += (f"; in-plane correction {c['translation_px']} px, {c['rotation_deg']} deg applied")
        if self.sign_flipped:
            text += "; its matrix negated (w > 0 in front of the source: the same projection)"
        return text

    def to_dict(self) -> dict:
        return {"source": self.kind, "file": self.file, "tags": dict(self.tags), "isocenter_lps": self.isocenter_lps,
                "assumptions": list(self.assumptions), "in_plane_correction": self.in_plane_correction,
                "sign_flipped": self.sign_flipped}


def facing_the_scan(P: np.ndarray, centre_lps) -> tuple[np.ndarray, bool]:
    """``P`` with the overall sign that puts the scan's centre in front of the X-ray source.

    A projection matrix is homogeneous (eq. 1): ``P`` and ``-P`` draw the same picture and
    differ only in the sign of ``w``, which the pipeline reads as the side of the source a
    point lies on. Calibrations give either sign (a DLT solved by SVD; a camera looking down
    its -z axis), so the sign is taken from the anatomy rather than from the file. Anatomy on
    both sides of the source stays wrong whatever the sign
    (:func:`plausibility.check_anatomy_in_view` refuses it).

    Returns
    -------
    (P, flipped) : the matrix with ``w > 0`` at ``centre_lps``, and whether it was negated.
    """
    P = np.asarray(P, dtype=float)
    if depth(P, np.asarray(centre_lps, dtype=float).reshape(1, 3))[0] < 0:
        return -P, True
    return P, False


def _json_number(value) -> float:
    """A JSON number as float; text and booleans are not numbers (``TypeError``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"not a number: {value!r}")
    return float(value)


def _correction(data: dict, path: Path) -> dict | None:
    correction = data.get(CORRECTION_KEY)
    if correction is None:
        return None
    try:
        translation = [_json_number(x) for x in correction.get("translation_px", (0.0, 0.0))]
        rotation = _json_number(correction.get("rotation_deg", 0.0))
    except (AttributeError, TypeError, ValueError):
        raise ValueError(f"{path}: {CORRECTION_KEY} must be {{'translation_px': [du, dv], 'rotation_deg': r}}") from None
    if len(translation) != 2 or not np.all(np.isfinite(translation + [rotation])):
        raise ValueError(f"{path}: {CORRECTION_KEY} needs two finite translation_px values and a finite rotation_deg")
    return {"translation_px": translation, "rotation_deg": rotation}


def read_geometry_file(path) -> tuple[np.ndarray | None, dict | None]:
    """Read geometry.json: ``(P or None, in-plane correction or None)``.

    The file holds ``projection_matrix`` (a calibrated ``P``), ``in_plane_correction``
    (``{"translation_px": [du, dv], "rotation_deg": r}``, the user's fix of ``P`` from the
    C-arm tags, or of a calibrated one), or both. It must hold at least one of them.
    """
    from .files import display_path, read_json_file

    path = Path(path)
    data = read_json_file(path, "geometry JSON")
    if not isinstance(data, dict) or not ({"projection_matrix", CORRECTION_KEY} & set(data)):
        raise ValueError(f"{display_path(path)}: neither a 'projection_matrix' nor an '{CORRECTION_KEY}' key")
    P = None
    if "projection_matrix" in data:
        if not isinstance(data["projection_matrix"], list):
            raise ValueError(f"{display_path(path)}: key 'projection_matrix' must be a list of 3 rows of 4 numbers")
        P = validate_projection_matrix(data["projection_matrix"], name=f"{display_path(path)}: key 'projection_matrix'")
    return P, _correction(data, path)


def apply_in_plane_correction(P: np.ndarray, correction: dict | None, image_shape) -> np.ndarray:
    """``P`` with the user's in-plane correction: a rotation about the image centre, then a shift."""
    if not correction:
        return np.asarray(P, dtype=float)
    rows, cols = image_shape
    return in_plane_transform(P, correction["translation_px"], correction["rotation_deg"],
                              center=((cols - 1) / 2.0, (rows - 1) / 2.0))


def update_in_plane_correction(case_dir, *, shift=None, rotate: float | None = None, reset: bool = False) -> Path:
    """Store (or remove, with ``reset``) the in-plane correction in ``case_dir/geometry.json``.

    ``shift`` ``(du, dv)`` pixels and ``rotate`` degrees replace the stored values; what is
    not given keeps its stored value. A calibrated ``projection_matrix`` in the file is kept.
    The file is removed when nothing is left in it. Returns the geometry.json path.
    """
    from .files import InputError, write_text_atomic

    case_dir = Path(case_dir)
    if not case_dir.is_dir():
        raise InputError(f"{case_dir}: case folder does not exist")
    path = case_dir / "geometry.json"
    try:
        data = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read geometry JSON ({exc})") from None
    if reset:
        data.pop(CORRECTION_KEY, None)
    elif shift is not None or rotate is not None:
        old = data.get(CORRECTION_KEY, {})
        data[CORRECTION_KEY] = {
            "translation_px": [float(x) for x in (shift if shift is not None else old.get("translation_px", (0, 0)))],
            "rotation_deg": float(rotate if rotate is not None else old.get("rotation_deg", 0.0))}
    else:
        return path
    if data:
        _correction(data, path)  # refuse what read_geometry_file would refuse
        write_text_atomic(path, json.dumps(data, indent=2) + "\n")
    else:
        path.unlink(missing_ok=True)
    return path
