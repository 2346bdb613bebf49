"""Shared pytest set-up: headless rendering and Qt, and small geometry fixtures."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("MPLBACKEND", "Agg")

# the pre-operative cache of the tests lives in a temporary folder, never in ~/.cache
if not os.environ.get("FEVAR_PLANNER_CACHE"):
    import tempfile

    os.environ["FEVAR_PLANNER_CACHE"] = tempfile.mkdtemp(prefix="fevar-planner-test-cache-")
