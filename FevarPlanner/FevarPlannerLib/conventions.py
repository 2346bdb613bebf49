"""The ground floor: names, directions, lengths and colours that every stage shares.

This module imports nothing from the package (only NumPy), so any stage, exporter or front
end can use it without pulling in another stage. See docs/DESIGN.md, "Conventions".

* Anatomy: :data:`ANATOMY_LABELS` name centreline nodes in result.json and every export;
  :data:`BRANCH_LABELS` are the five branches Algorithm 1 preserves (``tau = 5``).
* Directions: world points are DICOM patient LPS millimetres (+x the patient's left,
  +y posterior, +z superior); :data:`LPS_DIRECTIONS` gives the unit vectors the anatomy
  labelling needs.
* Lengths: :data:`IOTA_MM`, the one spur length of Algorithm 1, for the 3D graph (mm) and
  the 2D graph (converted to pixels with the pixel size at the anatomy's depth).
* Colours: :data:`PALETTE`, one RGB (0..1) per drawn role, shared by the overlay PNG, the
  3D picture, the workstation and the Slicer module.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ANATOMY_LABELS", "BRANCH_LABELS", "LPS_DIRECTIONS", "IOTA_MM", "PALETTE"]

#: Anatomical labels of centreline nodes, as result.json and the exports name them.
ANATOMY_LABELS = ("aorta", "renal_left", "renal_right", "iliac_left", "iliac_right", "other")
#: Labels of the five branches that Algorithm 1 preserves (``tau = 5``).
BRANCH_LABELS = ANATOMY_LABELS[:5]

#: The patient's directions as unit vectors in DICOM LPS.
LPS_DIRECTIONS = {"left": np.array([1.0, 0.0, 0.0]), "superior": np.array([0.0, 0.0, 1.0]),
                  "anterior": np.array([0.0, -1.0, 0.0])}

#: Algorithm 1's iota: branches shorter than this are spurs and deleted, mm (about one
#: vessel diameter). The 2D graph uses the same length in pixels at the anatomy's depth.
IOTA_MM = 10.0

#: Display colour (RGB, 0..1) of each drawn role. "recovered" and "deformed" are one role:
#: the registered (intra-operative) centreline.
PALETTE = {
    "preop": (1.0, 0.50, 0.05),        # orange
    "recovered": (0.09, 0.75, 0.81),   # cyan
    "deformed": (0.09, 0.75, 0.81),
    "path": (0.20, 0.95, 0.20),        # green
    "skeleton2d": (1.0, 0.90, 0.10),   # yellow
    "truth": (1.0, 1.0, 1.0),          # white
    "surface": (0.93, 0.72, 0.66),     # translucent flesh
    "warning": (1.0, 0.30, 0.30),      # light red: plausibility warnings
}
