"""Rigid pre-alignment (paper eq. 1) and the in-plane pose check.

The paper pre-aligns the 3D skeleton with the projection matrix ``P`` alone. When the
frame and ``P`` disagree (a moved table, a mis-calibrated C-arm: the misaligned cases of
the paper's Fig. 5), the deformation explains the offset as a 3D shift. ``fit_in_plane_rigid``
finds the rotation and translation of the image plane between corresponding points and
folds it into ``P`` (``A @ P``), so that everything downstream keeps working with one matrix.

``check_misalignment`` decides whether such a correction is called for. A stiff wire moves
the iliacs and the sac; it barely moves the aorta above the renal arteries, and the renal
ostia only by a few millimetres (as much as a misalignment of a few pixels). A misaligned
``P`` moves all of them by one in-plane rigid motion. So the rotation and the offset
across the upper aorta are fitted on the upper aorta alone, the offset along it (which a
straight vessel cannot show) on the renal ostia, and the correction is applied only when
the upper aorta is off under ``P`` (or turned as a whole: a pose off along it barely moves it
off itself, but turns it) and the rigid motion explains it; otherwise the offset is read as
deformation and ``P`` is kept. The upper aorta's lever is short (about 130 px in an
abdominal frame, about 1.2 mm of 3D error per degree of turn), so its points beyond the ends
of the frame's vessels (an upper aorta that the CT shows further up than the frame, or that
slid along itself in the fit) get no weight: they meet the curve's end sample, not the vessel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .graph.skeleton_graph import row_norms
from .projection import in_plane_transform, project

__all__ = ["PoseRefinement", "PoseCheck", "fit_in_plane_rigid", "robust_fit_in_plane_rigid",
           "check_misalignment", "pose_residual", "MIN_OFFSET_PX"]

#: Below this mean displacement of the stable points (px) the frame and ``P`` agree.
MIN_OFFSET_PX = 2.0
#: A misalignment is explained by the rigid fit: the stable points' mean distance to the
#: frame's stable vessels must drop to this fraction of what it was under ``P``; a
#: deformation leaves a distance of its own size.
MAX_RESIDUAL_FRACTION = 0.5
#: Without the reference region, every region must support the motion on its own: come at
#: least this much nearer (mean px) to the frame's stable vessels. A misaligned ``P`` puts
#: all of them off; a deformation (renals pulled by the wire) leaves them apart.
REGION_GAIN_PX = 0.5
#: A stable point further than this from the frame's stable vessels counts as this far.
DISTANCE_CAP_PX = 30.0
#: A correction turning the frame further than this is a failed fit, not a misalignment (the
#: paper's robustness sweep turns the frame by up to 30 degrees: a right fit there must pass).
MAX_ROTATION_DEG = 35.0
#: The upper aorta's own turn (issue 10): a pose off along the upper aorta barely moves it off
#: itself (under ``MIN_OFFSET_PX``), but a wire does not turn it. Turned by ``MIN_TURN_DEG`` or
#: more, its two halves fitted on their own turned alike (the smaller turn at least
#: ``HALF_TURN_AGREEMENT`` of the larger: a bend that the deformation gave it fakes a turn of
#: its lower or upper half only) and taken by the rigid fit to ``TURN_RESIDUAL_FRACTION`` of
#: its distance under ``P``, the pose is corrected below ``MIN_OFFSET_PX``.
MIN_TURN_DEG = 1.0
HALF_TURN_AGREEMENT = 0.65
TURN_RESIDUAL_FRACTION = 0.6
#: Huber threshold in robust standard deviations (1.4826 MAD) of the residuals.
HUBER_K = 1.345
ROBUST_ITERATIONS = 10


@dataclass
class PoseRefinement:
    """The in-plane correction found, and the corrected projection matrix."""

    P: np.ndarray
    translation: tuple
    rotation_deg: float
    scale: float
    cost_before: float
    cost_after: float
    weights: np.ndarray | None = None
    moved: np.ndarray | None = None


def _weighted_kabsch(source_uv, target_uv, weights):
    w = weights / weights.sum()
    centre_s, centre_t = w @ source_uv, w @ target_uv
    covariance = ((source_uv - centre_s) * w[:, None]).T @ (target_uv - centre_t)
    theta = np.arctan2(covariance[0, 1] - covariance[1, 0], covariance[0, 0] + covariance[1, 1])
    c, s = np.cos(theta), np.sin(theta)
    moved = (source_uv - centre_s) @ np.array([[c, -s], [s, c]]).T + centre_t
    return theta, centre_s, centre_t, moved


def fit_in_plane_rigid(source_uv: np.ndarray, target_uv: np.ndarray, P: np.ndarray,
                       weights: np.ndarray | None = None) -> PoseRefinement:
    """Least-squares rotation and translation of the image plane taking ``source`` to ``target``.

    The closed-form 2D Procrustes (Kabsch) solution for corresponding points, e.g. the
    projected 3D nodes of the stable vessels and their soft-assigned 2D targets, with
    optional non-negative ``weights``. ``cost_*`` are the (weighted) mean squared distances
    (px^2) before and after.
    """
    source_uv, target_uv = np.asarray(source_uv, float), np.asarray(target_uv, float)
    if len(source_uv) < 3 or source_uv.shape != target_uv.shape:
        raise ValueError(f"need three or more corresponding points, got {source_uv.shape} and {target_uv.shape}")
    weights = np.ones(len(source_uv)) if weights is None else np.asarray(weights, float)
    theta, centre_s, centre_t, moved = _weighted_kabsch(source_uv, target_uv, weights)
    translation = centre_t - centre_s
    refined = in_plane_transform(P, translation=translation, rotation_deg=np.rad2deg(theta), center=centre_s)
    w = weights / weights.sum()
    before = float(w @ np.sum((source_uv - target_uv) ** 2, axis=1))
    after = float(w @ np.sum((moved - target_uv) ** 2, axis=1))
    return PoseRefinement(refined, (float(translation[0]), float(translation[1])), float(np.rad2deg(theta)), 1.0,
                          before, after, weights, moved)


def robust_fit_in_plane_rigid(source_uv: np.ndarray, target_uv: np.ndarray, P: np.ndarray) -> PoseRefinement:
    """:func:`fit_in_plane_rigid` with a Huber loss (iteratively reweighted least squares).

    A few wrong correspondences (a renal target on an accessory artery, a node soft-assigned
    to the wrong end of a branch) get weights below one instead of dragging the fit.
    """
    source_uv, target_uv = np.asarray(source_uv, float), np.asarray(target_uv, float)
    if len(source_uv) < 3 or source_uv.shape != target_uv.shape:
        return fit_in_plane_rigid(source_uv, target_uv, P)      # its error message
    weights = np.ones(len(source_uv))
    moved = _weighted_kabsch(source_uv, target_uv, weights)[3]
    for _ in range(ROBUST_ITERATIONS):
        residual = row_norms(moved - target_uv)
        scale = max(1.4826 * _median(residual), 0.1)      # below 0.1 px the fit is exact
        new = np.minimum(1.0, HUBER_K * scale / np.maximum(residual, 1e-12))
        if np.all(np.abs(new - weights) <= 1e-4 + 1e-5 * weights):      # np.allclose(atol=1e-4); all finite
            break
        weights = new
        moved = _weighted_kabsch(source_uv, target_uv, weights)[3]
    return fit_in_plane_rigid(source_uv, target_uv, P, weights)


@dataclass
class PoseCheck:
    """What :func:`check_misalignment` found and decided (``P``: corrected if ``applied``).

    ``offset_px``: mean displacement of the stable points by the fitted motion;
    ``before_px`` / ``after_px``: mean distance of the stable points to the frame's stable
    vessels under the given and the fitted pose; ``regions_px``: the same per region
    (before, after); ``halves_deg``: the turn of each half of the reference region fitted on
    its own (empty without a reference or when it turns less than ``MIN_TURN_DEG``).
    """

    P: np.ndarray
    translation_px: tuple
    rotation_deg: float
    offset_px: float
    before_px: float
    after_px: float
    regions_px: dict = field(default_factory=dict)
    applied: bool = False
    why: str = ""
    halves_deg: tuple = ()

    def to_dict(self) -> dict:
        return {"translation_px": [round(float(t), 3) for t in self.translation_px],
                "rotation_deg": round(float(self.rotation_deg), 3), "offset_px": round(float(self.offset_px), 3),
                "distance_before_px": round(float(self.before_px), 3),
                "distance_after_px": round(float(self.after_px), 3),
                "regions_px": {k: [round(float(b), 3), round(float(a), 3)] for k, (b, a) in self.regions_px.items()},
                "halves_deg": [round(float(t), 3) for t in self.halves_deg],
                "applied": bool(self.applied), "why": self.why}


def _distances(tree, uv: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest curve point, capped (a stray match counts as ``DISTANCE_CAP_PX``)."""
    return np.minimum(tree.query(uv)[0], DISTANCE_CAP_PX)


def _stable_regions_fit(source, regions, curve, P, starts, tree, reference):
    """The in-plane rigid fit of the stable points, the reference region first.

    With the reference region (the upper aorta, which a wire does not move) in the frame,
    its closest-point fit alone fixes the rotation and the offset across it (from each
    start, the one leaving it nearest to the curve); the offset along it, which a nearly
    straight vessel cannot show, is then taken from the other regions
    (:func:`_along_reference_shift`): their ostia may have moved with the wire, so they
    decide only what the reference leaves open. Without a usable reference all regions are
    fitted at once. Returns the fit of ``source`` (all regions, in order) and the turns of the
    reference's halves (:func:`_half_turns`; empty without a reference or below ``MIN_TURN_DEG``).
    """
    normals = _curve_normals(curve, tree)
    names = list(regions)
    bounds = np.cumsum([0] + [len(regions[name]) for name in names])
    if reference not in regions or len(regions[reference]) < MIN_REFERENCE_POINTS:
        fits = [_closest_point_fit(source, curve, P, start, tree, normals) for start in starts]
        return min(fits, key=lambda fit: _distances(tree, fit.moved).mean()), ()
    k = names.index(reference)
    own = slice(bounds[k], bounds[k + 1])
    along = _principal_direction(source[own])
    fits = [_closest_point_fit(source[own], curve, P, None if start is None else _restricted(start, own), tree, normals,
                               free=along) for start in starts]
    best = min(fits, key=lambda fit: _distances(tree, fit.moved).mean())
    # the halves matter only to a turn the rule can read (:func:`_reference_turned`); they cost 2 fits
    halves = (_half_turns(source[own], best, curve, P, tree, normals, along)
              if abs(best.rotation_deg) >= MIN_TURN_DEG else ())
    moved = _apply_rigid(source, source[own], best.moved)
    others = np.ones(len(source), bool)
    others[own] = False
    if np.count_nonzero(others) >= 3:
        direction = _principal_direction(best.moved)
        moved = moved + _along_reference_shift(moved[others], direction, curve, tree, normals) * direction
    return fit_in_plane_rigid(source, moved, P), halves


def _half_turns(reference: np.ndarray, fit: PoseRefinement, curve, P, tree, normals, along) -> tuple:
    """The turn (degrees) of each half of the reference region (split at its middle along
    ``along``), each fitted on its own from the whole region's ``fit``. A rigid misalignment
    turns both halves alike; a bend of the vessel turns one more than the other (the phantom
    generator bends the upper aorta from its middle: the lower half stays, the upper turns)."""
    position = reference @ along
    lower = position <= np.median(position)
    turns = []
    for half in (lower, ~lower):
        if np.count_nonzero(half) < 3:
            return ()
        start = _restricted(fit, half)
        turns.append(_closest_point_fit(reference[half], curve, P, start, tree, normals, free=along).rotation_deg)
    return tuple(turns)


#: The reference region needs this many points in the frame to fix the rotation on its own.
MIN_REFERENCE_POINTS = 10


def _restricted(fit: PoseRefinement, rows: slice) -> PoseRefinement:
    """A fit's moved points of ``rows`` only (a start for a subset of its points)."""
    return PoseRefinement(fit.P, fit.translation, fit.rotation_deg, fit.scale, fit.cost_before, fit.cost_after,
                          None, np.asarray(fit.moved)[rows])


def _apply_rigid(points: np.ndarray, fitted_from: np.ndarray, fitted_to: np.ndarray) -> np.ndarray:
    """``points`` moved by the rigid motion taking ``fitted_from`` exactly onto ``fitted_to``."""
    theta, centre_s, centre_t, _ = _weighted_kabsch(fitted_from, fitted_to, np.ones(len(fitted_from)))
    c, s = np.cos(theta), np.sin(theta)
    return (points - centre_s) @ np.array([[c, -s], [s, c]]).T + centre_t


def _principal_direction(points: np.ndarray) -> np.ndarray:
    """Unit direction of the largest spread of 2D points (the course of a vessel)."""
    centred = points - points.mean(axis=0)
    return np.linalg.eigh(centred.T @ centred)[1][:, -1]


def _along_reference_shift(moved: np.ndarray, direction: np.ndarray, curve, tree, normals) -> float:
    """The shift along ``direction`` that brings ``moved`` nearest to the curve (px).

    Point-to-line residuals, one degree of freedom, Huber weights, closest points renewed
    each pass; points whose curve runs along ``direction`` carry no weight.
    """
    shift = 0.0
    for _ in range(ICP_ITERATIONS):
        at = moved + shift * direction
        _, nearest = tree.query(at)
        n = normals[nearest]
        residual = np.einsum("ij,ij->i", n, at - curve[nearest])
        slope = n @ direction
        w = _huber_weights(residual)
        denominator = float(w @ slope ** 2)
        if denominator < 1e-9:
            return shift
        step = -float(w @ (slope * residual)) / denominator
        shift += step
        if abs(step) < ICP_SETTLED_PX:
            break
    return shift


def check_misalignment(regions: dict, curve_uv: np.ndarray, P: np.ndarray, *, targets: dict | None = None,
                       reference: str | None = None, force: bool = False,
                       min_offset_px: float = MIN_OFFSET_PX) -> PoseCheck:
    """Is the frame misaligned against ``P``? The in-plane rigid fit and the decision.

    Parameters
    ----------
    regions : dict of name -> (n, 2) array
        The stable regions' pre-operative nodes projected through ``P`` (e.g. "upper_aorta",
        "renal_left", "renal_right"). Regions with fewer than three points are left out.
    curve_uv : (m, 2) array
        Points of the frame's stable vessels (the 2D skeleton's aorta and renal branches).
    P : (3, 4)
        The given projection matrix.
    targets : dict of name -> (n, 2) array, optional
        Corresponded 2D targets of the same points (soft assignment): a coarse start for
        offsets beyond the closest points' reach. The fit starts from ``P`` as well.
    reference : str, optional
        The stiffest region (e.g. "upper_aorta"): it fixes the rotation and the offset
        across it (:func:`_stable_regions_fit`) and must carry the offset (see below).
    force : bool
        Apply any fit that is not a failure (too few points, turned too far), without the test.
    min_offset_px : float
        The smallest mean displacement treated as a misalignment.

    Returns
    -------
    PoseCheck
        The fit, the test's numbers and the decision. The correction is applied when (a) the
        offset exceeds ``min_offset_px``, two or more regions take part and, with a
        ``reference`` region in the frame, (b) the reference is off under ``P`` by
        ``min_offset_px`` or more and the fit takes it to ``MAX_RESIDUAL_FRACTION`` of that:
        a wire moves the renal ostia and leaves the upper aorta, so renals off the frame
        alone are deformation, and renals that moved as well may stay off after the fit. A
        reference less than ``min_offset_px`` off is still corrected when it is turned
        rigidly (:func:`_reference_turned`: a pose off along it and turned a little; a wire
        does not turn it, and a bend it gave it turns one half only). (A shift purely along
        a straight upper aorta, without a turn, is not corrected: one view cannot tell it from
        renals that moved.) Without a reference, (c) the fit explains the
        mismatch: the mean distance of the stable points to the frame's stable vessels drops
        to ``MAX_RESIDUAL_FRACTION`` of what it was, and each region comes ``REGION_GAIN_PX``
        nearer (they agree on one motion).
    """
    from scipy.spatial import cKDTree

    regions = {name: np.asarray(uv, float) for name, uv in regions.items() if len(uv) >= 3}
    curve_uv = np.asarray(curve_uv, float)
    if sum(len(uv) for uv in regions.values()) < 10 or len(curve_uv) < 3:
        return PoseCheck(np.asarray(P, float), (0.0, 0.0), 0.0, 0.0, 0.0, 0.0,
                         why="too few stable points (upper aorta, renal ostia) in the frame to test the pose")
    source = np.concatenate(list(regions.values()))
    tree = cKDTree(curve_uv)
    starts = [None]
    if targets is not None:
        coarse = robust_fit_in_plane_rigid(source, np.concatenate([targets[name] for name in regions]), P)
        if abs(coarse.rotation_deg) <= MAX_ROTATION_DEG:
            starts.append(coarse)
    fit, halves = _stable_regions_fit(source, regions, curve_uv, P, starts, tree, reference)
    before, after = _distances(tree, source), _distances(tree, fit.moved)
    offset = float(row_norms(fit.moved - source).mean())
    bounds = np.cumsum([0] + [len(uv) for uv in regions.values()])
    per_region = {name: (float(before[i:j].mean()), float(after[i:j].mean()))
                  for name, i, j in zip(regions, bounds[:-1], bounds[1:])}
    check = PoseCheck(np.asarray(P, float), fit.translation, fit.rotation_deg, offset, float(before.mean()),
                      float(after.mean()), per_region, halves_deg=halves)
    check.applied, check.why = _decide(check, len(regions), reference if reference in per_region and
                                       len(regions[reference]) >= MIN_REFERENCE_POINTS else None, force, min_offset_px)
    if check.applied:
        check.P = fit.P
    return check


def _decide(check: PoseCheck, n_regions: int, reference: str | None, force: bool, min_offset_px: float):
    """(apply?, why) of :func:`check_misalignment` from its numbers."""
    offset, per_region = check.offset_px, check.regions_px
    if abs(check.rotation_deg) > MAX_ROTATION_DEG:
        return False, f"fit turned the frame {check.rotation_deg:.1f} deg: a failed fit, not a misalignment"
    if force:
        return True, "pose correction forced"
    turned = reference is not None and _reference_turned(check, per_region[reference])
    if offset < min_offset_px and not turned:
        return False, f"frame and P agree: best rigid offset {offset:.1f} px (< {min_offset_px:g} px)"
    if n_regions < 2:
        return False, f"only {', '.join(per_region)} in the frame: one region cannot tell misalignment from deformation"
    if reference is not None:
        # renals the wire moved may stay off or come no nearer: the reference alone decides
        held, moved_to = per_region[reference]
        if turned and held < min_offset_px:
            return True, (f"{reference} is turned {check.rotation_deg:+.1f} deg against the frame: {held:.1f} px off "
                          f"under P, {moved_to:.1f} px after one rigid offset of {offset:.1f} px (a wire does not "
                          f"turn it; along it from the other regions)")
        if held < min_offset_px:
            return False, (f"read as deformation: {reference} is {held:.1f} px off the frame under P "
                           f"(< {min_offset_px:g} px), the rest moved")
        if moved_to > MAX_RESIDUAL_FRACTION * held:
            return False, (f"read as deformation: a rigid motion takes {reference} only from {held:.1f} to "
                           f"{moved_to:.1f} px off the frame's")
    elif check.after_px > MAX_RESIDUAL_FRACTION * check.before_px:
        return False, (f"read as deformation: a rigid {offset:.1f} px offset takes the stable vessels only from "
                       f"{check.before_px:.1f} to {check.after_px:.1f} px off the frame's")
    else:
        unmoved = [name for name, (b, a) in per_region.items() if a > b - REGION_GAIN_PX]
        if unmoved:
            return False, (f"read as deformation: the {offset:.1f} px offset brings {', '.join(unmoved)} no nearer "
                           f"to the frame (less than {REGION_GAIN_PX:g} px)")
    if reference is not None:
        others = ", ".join(name for name in per_region if name != reference)
        return True, (f"{reference} is {held:.1f} px off the frame under P, {moved_to:.1f} px after one rigid "
                      f"offset of {offset:.1f} px (its turn and cross offset; along it from {others})")
    return True, (f"{', '.join(per_region)} agree on one rigid offset of {offset:.1f} px (stable vessels "
                  f"{check.before_px:.1f} -> {check.after_px:.1f} px off the frame's)")


def _reference_turned(check: PoseCheck, reference_px: tuple) -> bool:
    """Is the reference region (the upper aorta) turned against the frame, rigidly? Its fitted
    turn is at least ``MIN_TURN_DEG``, its halves' turns agree (same sign, the smaller at least
    ``HALF_TURN_AGREEMENT`` of the larger) and the rigid fit takes it to
    ``TURN_RESIDUAL_FRACTION`` of its distance under ``P``."""
    held, moved_to = reference_px
    if abs(check.rotation_deg) < MIN_TURN_DEG or len(check.halves_deg) != 2 or moved_to > TURN_RESIDUAL_FRACTION * held:
        return False
    small, large = sorted(check.halves_deg, key=abs)
    return small * large > 0 and abs(small) >= HALF_TURN_AGREEMENT * abs(large)


#: A point meeting the frame's curve this far (px) along it from its nearest sample lies beyond
#: the curve's end (the samples of a 2D skeleton are 1 to 1.4 px apart).
CURVE_END_PX = 1.5
#: Closest-point passes of :func:`closest_point_rigid` and the change (px) that ends them.
ICP_ITERATIONS = 50
ICP_SETTLED_PX = 1e-3
#: Curve points whose local principal direction gives a point's normal.
NORMAL_NEIGHBOURS = 7


def _curve_normals(curve_uv: np.ndarray, tree) -> np.ndarray:
    """Unit normal of a 2D point-sampled curve at each point (local principal direction)."""
    _, near = tree.query(curve_uv, k=min(NORMAL_NEIGHBOURS, len(curve_uv)))
    local = curve_uv[near] - curve_uv[near].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return vectors[:, :, 0]                      # the smallest spread: across the curve


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1D float array without NaNs, to the bit (the middle pair's mean), at a
    fraction of its call overhead (it runs in every closest-point pass)."""
    half = len(values) // 2
    if len(values) % 2:
        return np.partition(values, half)[half]
    middle = np.partition(values, (half - 1, half))
    return (middle[half - 1] + middle[half]) / 2.0


def _huber_weights(residual: np.ndarray) -> np.ndarray:
    size = np.abs(residual)
    scale = max(1.4826 * _median(size), 0.05)
    return np.minimum(1.0, HUBER_K * scale / np.maximum(size, 1e-12))


def closest_point_rigid(source_uv: np.ndarray, curve_uv: np.ndarray, P: np.ndarray,
                        start: PoseRefinement | None = None) -> PoseRefinement:
    """In-plane rigid fit of ``source`` onto a point-sampled 2D ``curve`` (2D ICP, point to line).

    Refines a fit from correspondences (``start``) to sub-pixel: soft-assigned targets slide
    along a vessel whose 2D length differs from its projected 3D length; the distance to
    the curve along its normal does not depend on where along the vessel a point lies.
    Gauss-Newton steps of the rotation and translation with Huber weights. Returns the fit
    from ``source`` (through ``P``).
    """
    from scipy.spatial import cKDTree

    source_uv, curve_uv = np.asarray(source_uv, float), np.asarray(curve_uv, float)
    tree = cKDTree(curve_uv)
    return _closest_point_fit(source_uv, curve_uv, P, start, tree, _curve_normals(curve_uv, tree))


def _closest_point_fit(source_uv, curve_uv, P, start, tree, normals, free=None) -> PoseRefinement:
    """:func:`closest_point_rigid` on float arrays, with the curve's KD-tree and normals given.

    ``free``: a unit direction whose motion does not count towards settling (the course of a
    straight reference vessel, along which the points may slide for many passes while the fit
    itself has settled; the offset along it is found elsewhere). Points of such a reference
    beyond the curve's ends get no weight (:func:`_within_curve`).
    """
    moved = source_uv.copy() if start is None else np.asarray(start.moved, float).copy()
    for _ in range(ICP_ITERATIONS):
        _, nearest = tree.query(moved)
        n = normals[nearest]
        offset = moved - curve_uv[nearest]
        residual = np.einsum("ij,ij->i", n, offset)
        centre = moved.mean(axis=0)
        arm = moved - centre
        jacobian = np.column_stack([n[:, 1] * arm[:, 0] - n[:, 0] * arm[:, 1], n])
        w = _huber_weights(residual)
        if free is not None:
            w = w * _within_curve(offset, n, w)
        step = np.linalg.lstsq(jacobian * np.sqrt(w)[:, None], -residual * np.sqrt(w), rcond=None)[0]
        c, s = np.cos(step[0]), np.sin(step[0])
        new = arm @ np.array([[c, -s], [s, c]]).T + centre + step[1:]
        delta = new - moved
        if free is not None:
            delta = delta - np.outer(delta @ free, free)
        change = row_norms(delta).max()
        moved = new
        if change < ICP_SETTLED_PX:
            break
    return fit_in_plane_rigid(source_uv, moved, P)


def _within_curve(offset: np.ndarray, normals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """1 for points that meet the frame's curve across it, 0 for points beyond one of its ends.

    ``offset``: each point minus its nearest curve sample; ``normals`` there. A point past an
    end (an upper aorta the CT shows further up than the frame, a reference slid along a
    straight vessel) meets the end sample at a distance along the curve: its distance across
    says nothing about the pose. Every point counts when fewer than three weighted ones are left.
    """
    inside = np.abs(offset[:, 0] * normals[:, 1] - offset[:, 1] * normals[:, 0]) <= CURVE_END_PX
    return inside if np.count_nonzero(inside & (weights > 0)) >= 3 else np.ones(len(offset))


def pose_residual(P_used: np.ndarray, P_true: np.ndarray, vessel_points: np.ndarray) -> dict:
    """How far a pose is off the true one on a vessel, split along and across it (px, degrees).

    The evaluation side of the pose check: ``vessel_points`` (3D, ordered along the vessel,
    e.g. the upper aorta from its top down) are projected through both matrices (eq. 1).
    The mean image offset from the used to the true projection is split along the vessel's
    course (the principal direction of its true projection, pointing from its first point
    towards its last) and across it (that direction turned by +90 degrees); ``rotation_deg``
    is the in-plane turn taking the used projection onto the true one (2D Procrustes).

    Returns
    -------
    dict
        ``along_px``, ``across_px``, ``rotation_deg`` and ``mean_px`` (mean distance between
        the two projections of each point).
    """
    points = np.asarray(vessel_points, float)
    if len(points) < 2:
        raise ValueError(f"need two or more vessel points, got {len(points)}")
    used, true = project(P_used, points), project(P_true, points)
    course = _principal_direction(true)
    if (true[-1] - true[0]) @ course < 0:
        course = -course
    offset = (true - used).mean(axis=0)
    theta = _weighted_kabsch(used, true, np.ones(len(points)))[0]
    return {"along_px": float(offset @ course), "across_px": float(offset @ np.array([-course[1], course[0]])),
            "rotation_deg": float(np.rad2deg(theta)), "mean_px": float(row_norms(true - used).mean())}
