"""``python -m FevarPlannerApp [CASE_DIR] [--run] [--screenshot PNG]``."""

from FevarPlannerApp.app import main

raise SystemExit(main())
