"""A renal cut off at its ostium bridged back to the mask, a rail beside it not
(segmentation/off_tree.py :func:`cut_renal_bridges`, issue 11)."""

import math

import numpy as np
from scipy import ndimage as ndi

from FevarPlannerLib.quality import PriorBand
from FevarPlannerLib.segmentation import off_tree
from FevarPlannerLib.segmentation.threshold import _remove_small_objects

SHAPE = (100, 120)
AORTA_COL, AORTA_RADIUS = 30, 6
RENAL_ROW, RENAL_RADIUS, RENAL_END = 40, 2.0, 75
MARGIN = 12.0
MIN_AREA = 200.0


def _prior_maps():
    """A reduced grid's prior: a vertical aorta (col 30, radius 6) and a horizontal renal leaving
    it at row 40 (radius 2) up to col 75; band = distance <= radius + 12 px."""
    rows, cols = np.indices(SHAPE)
    to_aorta = np.abs(cols - AORTA_COL).astype(np.float32)
    to_renal = np.hypot(rows - RENAL_ROW, np.clip(cols, AORTA_COL, RENAL_END) - cols).astype(np.float32)
    renal = (to_renal < to_aorta) & (cols > AORTA_COL)
    distance = np.where(renal, to_renal, to_aorta)
    radius = np.where(renal, RENAL_RADIUS, float(AORTA_RADIUS)).astype(np.float32)
    node_angle = np.where(renal, 0.0, math.pi / 2).astype(np.float32)      # renal along u, aorta along v
    band = distance <= radius + MARGIN
    where = PriorBand((slice(0, SHAPE[0]), slice(0, SHAPE[1])), distance, renal.astype(int), radius, band)
    return where, node_angle, renal, band


def _aorta_and(piece_cols, row=RENAL_ROW, half_width=1):
    """The aorta's mask and a horizontal piece of a renal (rows row +- half_width) over ``piece_cols``."""
    rows, cols = np.indices(SHAPE)
    aorta = (np.abs(cols - AORTA_COL) <= AORTA_RADIUS) & (rows >= 5) & (rows < 95)
    piece = (np.abs(rows - row) <= half_width) & (cols >= piece_cols[0]) & (cols < piece_cols[1])
    return aorta, piece


def _tidied(aorta, piece):
    where, node_angle, renal, band = _prior_maps()
    vessel = (aorta | piece) & band
    bridges = off_tree.cut_renal_bridges(vessel, where, node_angle, renal, MIN_AREA)
    return bridges, _remove_small_objects(vessel | bridges, MIN_AREA)


def test_a_renal_cut_at_its_ostium_is_bridged_and_kept():
    aorta, piece = _aorta_and((AORTA_COL + AORTA_RADIUS + 6, 66))     # a 5-px gap off the aorta's edge
    assert piece.sum() < MIN_AREA                                        # alone it would be dropped
    bridges, kept = _tidied(aorta, piece)
    assert kept[piece].all() and kept[aorta].all()
    assert ndi.label(kept, structure=np.ones((3, 3)))[1] == 1            # one piece: the skeleton connects
    bridge_rows, bridge_cols = np.nonzero(bridges)
    assert np.abs(bridge_rows - RENAL_ROW).max() <= 2                   # along the renal, 3 px wide
    assert bridge_cols.min() >= AORTA_COL + AORTA_RADIUS and bridge_cols.max() <= AORTA_COL + AORTA_RADIUS + 7


def test_without_the_bridge_the_cut_renal_is_dropped():
    aorta, piece = _aorta_and((AORTA_COL + AORTA_RADIUS + 6, 66))
    assert not _remove_small_objects(aorta | piece, MIN_AREA)[piece].any()


def test_a_rail_running_to_the_band_edge_is_not_bridged():
    aorta, rail = _aorta_and((AORTA_COL + AORTA_RADIUS + 6, SHAPE[1]))   # runs on past the renal's end
    bridges, kept = _tidied(aorta, rail)
    assert not bridges.any()
    assert not kept[rail].any()


def test_a_piece_across_the_renal_is_not_bridged():
    rows, cols = np.indices(SHAPE)
    aorta, _ = _aorta_and((0, 0))
    across = (np.abs(cols - 50) <= 1) & (rows >= 33) & (rows < 48)      # vertical, inside the renal's band
    bridges, kept = _tidied(aorta, across)
    assert not bridges.any()
    assert not kept[across].any()


def test_a_piece_far_from_the_aorta_is_not_bridged():
    aorta, piece = _aorta_and((62, 75))                                   # a 26-px gap
    bridges, _ = _tidied(aorta, piece)
    assert not bridges.any()


def test_a_piece_wider_than_the_renal_is_not_bridged():
    aorta, blob = _aorta_and((AORTA_COL + AORTA_RADIUS + 6, 58), half_width=4)   # 9 px wide, renal 4
    bridges, _ = _tidied(aorta, blob)
    assert not bridges.any()


def test_the_small_object_removal_is_unchanged_when_nothing_is_bridged():
    where, node_angle, renal, band = _prior_maps()
    rng = np.random.default_rng(5)
    aorta, _ = _aorta_and((0, 0))
    specks = ndi.binary_dilation(rng.random(SHAPE) < 0.01) & ~renal      # small pieces, none a renal's
    vessel = (aorta | specks) & band
    kept, bridges = off_tree.without_small_pieces_but_cut_renals(vessel, where, node_angle, renal, MIN_AREA,
                                                                 ndi.binary_erosion(band, structure=np.ones((3, 3))))
    assert not bridges.any()
    assert np.array_equal(kept, _remove_small_objects(vessel, MIN_AREA))
    assert kept[aorta].all() and not (kept & ~ndi.binary_dilation(aorta, iterations=4)).any()


def test_the_cut_renal_survives_the_combined_removal():
    where, node_angle, renal, band = _prior_maps()
    aorta, piece = _aorta_and((AORTA_COL + AORTA_RADIUS + 6, 66))
    kept, bridges = off_tree.without_small_pieces_but_cut_renals((aorta | piece) & band, where, node_angle, renal,
                                                                 MIN_AREA, ndi.binary_erosion(band, structure=np.ones((3, 3))))
    assert bridges.any() and kept[piece].all() and kept[bridges].all()
