"""FevarPlanner workstation: a standalone Qt + VTK front end for people without 3D Slicer.

It shows the same control panel as the Slicer module (``Resources/UI/FevarPlanner.ui``)
beside a 3D view (pre-operative and recovered centrelines, the planned path, the aorta
surface) and a 2D view (the fluoroscopic frame with its skeleton and the projected
centrelines; one tab per view when the case holds several, ``views/<name>/``), and runs
:func:`FevarPlannerLib.pipeline.run_case` in a worker thread.

Launch: ``fevar-planner-gui [CASE_DIR]`` or ``python -m FevarPlannerApp [CASE_DIR]``.

Importing this package imports neither Qt nor VTK. It talks to the core only
(:mod:`FevarPlannerLib`); the results table's rows come from
:func:`FevarPlannerLib.export.summary_rows`, as in the Slicer module.
"""
