"""A second lumen beside a renal the mask already follows (a support rail, a catheter) dropped,
a renal deformed away from its projection kept (segmentation/off_tree.py
:func:`without_second_lumens`, issue 11).

On unsubtracted bench frames a rail running a few millimetres beside a renal joined the mask
(development seed 238: 3 061 rail pixels, 240: 2 319) and Algorithm 1 took it for the renal's
outer part (seed 240: that renal 4.6 mm off, 0.7 mm with the true mask).
"""

import numpy as np

from FevarPlannerLib.quality import FluoroPrior
from FevarPlannerLib.segmentation import off_tree

AORTA_COL, RENAL_ROW = 60, 50          # u = x + 60, v = 10 - z: the renals leave at z = -40 mm
AORTA_RADIUS, RENAL_RADIUS = 7.0, 2.0


def _prior():
    """A vertical aorta (z 0 .. -150 mm) with two horizontal renals 40 mm long at z = -40 mm."""
    aorta = np.column_stack([np.zeros(151), np.zeros(151), -np.arange(151.0)])
    left = np.column_stack([np.arange(1.0, 41.0), np.zeros(40), np.full(40, -40.0)])
    right = left * np.array([-1.0, 1.0, 1.0])
    edges = [(k, k + 1) for k in range(150)]
    for start in (151, 191):
        edges += [(40, start)] + [(start + k, start + k + 1) for k in range(39)]
    P = np.array([[1.0, 0.0, 0.0, 60.0], [0.0, 0.0, -1.0, 10.0], [0.0, 0.0, 0.0, 1.0]])
    return FluoroPrior(np.vstack([aorta, left, right]), edges, ["aorta"] * 151 + ["renal_left"] * 40 + ["renal_right"] * 40,
                       P, [AORTA_RADIUS] * 151 + [RENAL_RADIUS] * 80)


def _grid():
    prior = _prior()
    where = prior.band((170, 130), 1, 0)
    frames = off_tree.renal_frames(prior, where, 1)
    rows, cols = np.indices(where.band.shape)
    return where, frames, rows + where.box[0].start, cols + where.box[1].start


def _aorta_and_renal(rows, cols):
    aorta = (np.abs(cols - AORTA_COL) <= AORTA_RADIUS) & (rows >= 12) & (rows <= 158)
    renal = (np.abs(rows - RENAL_ROW) <= RENAL_RADIUS) & (cols > AORTA_COL) & (cols <= AORTA_COL + 40)
    return aorta, renal


def test_renal_frames_measure_along_and_off_the_projected_renal():
    where, frames, rows, cols = _grid()
    at = (rows == RENAL_ROW + 6) & (cols == AORTA_COL + 25)
    assert frames.vessel[at][0] >= 0
    assert abs(float(frames.along[at][0]) - 25.0) <= 1.0 and abs(float(frames.off[at][0]) - 6.0) <= 0.5
    assert frames.ostium == off_tree.OSTIUM_PX_RADII * AORTA_RADIUS


def test_a_rail_beside_a_found_renal_is_dropped():
    where, frames, rows, cols = _grid()
    aorta, renal = _aorta_and_renal(rows, cols)
    rail = (np.abs(rows - RENAL_ROW - 12) <= 2) & (cols >= AORTA_COL + 12) & (cols <= AORTA_COL + 38)
    link = (np.abs(cols - AORTA_COL - 20) <= 1) & (rows > RENAL_ROW) & (rows < RENAL_ROW + 12)   # a catheter
    vessel = (aorta | renal | rail | link) & where.band
    kept = off_tree.without_second_lumens(vessel, frames)
    assert kept[(aorta | renal) & where.band].all()                        # the vessels stay whole
    assert (kept & rail).sum() <= 0.1 * rail.sum()                          # 12 px off (limit 3 x 2 + 2): gone


def test_a_renal_deformed_away_from_its_projection_is_kept():
    where, frames, rows, cols = _grid()
    aorta, renal = _aorta_and_renal(rows, cols)
    inner = renal & (cols <= AORTA_COL + 20)
    outer = (np.abs(rows - RENAL_ROW - (cols - AORTA_COL - 20) * 0.6) <= RENAL_RADIUS) & (cols > AORTA_COL + 20) \
        & (cols <= AORTA_COL + 40)                                          # swung 12 px down at its tip
    vessel = (aorta | inner | outer) & where.band
    assert np.array_equal(off_tree.without_second_lumens(vessel, frames), vessel)
