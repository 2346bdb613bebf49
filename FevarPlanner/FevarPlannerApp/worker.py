"""Running the pipeline off the GUI thread.

:class:`PlanWorker` lives in a :class:`QThread`; it loads the case, takes the
pre-operative model from the cache (:func:`FevarPlannerLib.cache.preop_model`: the CT is
segmented once per patient, not on every click), runs
:func:`FevarPlannerLib.pipeline.run_case` (the one logic entry point) and reports progress,
the outcome or a one-line error through Qt signals, which Qt delivers on the GUI thread.
A refusal by a quality gate also sends the QC picture's path, written where ``plan --out``
writes it (or to a temporary folder), so the window can show why.
It reads nothing itself: the case, its files and the aorta surface come from the core.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from PySide6.QtCore import QObject, Signal, Slot

__all__ = ["PlanRequest", "PlanOutcome", "PlanWorker"]


@dataclass
class PlanRequest:
    """What the panel asks for: the case, the options and the overriding input files."""

    case_dir: Path
    method: str = "proposed"
    start: str = "iliac_right"
    target: str = "renal_left"
    out_dir: Path | None = None
    overrides: dict = field(default_factory=dict)
    with_surface: bool = True
    use_cache: bool = True


@dataclass
class PlanOutcome:
    """A planning result and the pre-operative lumen surface, when the case has a mask."""

    result: object
    surface: object = None
    written: dict = field(default_factory=dict)
    model: object = None
    case: object = None


class PlanWorker(QObject):
    """Runs one :class:`PlanRequest`; emits ``progress``, then ``succeeded`` or ``failed``.

    ``failed`` carries the one-line message and the QC picture's path ("" when the failure
    has no picture: a file that cannot be read, say).
    """

    progress = Signal(float, str)
    succeeded = Signal(object)
    failed = Signal(str, str)
    done = Signal()

    def __init__(self, request: PlanRequest):
        super().__init__()
        self.request = request

    @Slot()
    def run(self) -> None:
        from FevarPlannerLib import cache
        from FevarPlannerLib.io import load_case
        from FevarPlannerLib.pipeline import check_result, run_case, write_outputs

        request = self.request
        progress = lambda fraction, message: self.progress.emit(float(fraction), str(message))  # noqa: E731
        try:
            case = load_case(request.case_dir, **{key: value for key, value in request.overrides.items() if value})
            model = cache.preop_model(case, progress=progress, use_cache=request.use_cache)
            result = run_case(case, method=request.method, start=request.start, target=request.target,
                              preop=model, progress=progress, mirror_test=True)
            result.warnings.extend(check_result(case, result))     # the gates plan runs: refuse, or warn
            outcome = PlanOutcome(result, model=model, case=case)
            if request.out_dir is not None:
                self.progress.emit(1.0, f"writing the outputs to {request.out_dir}")
                outcome.written = write_outputs(result, request.out_dir)
            if request.with_surface:
                self.progress.emit(1.0, "extracting the aorta surface")
                outcome.surface = model.surface(case)
            self.succeeded.emit(outcome)
        except Exception as exc:  # the GUI shows any failure as one line and stays usable
            picture = self._refusal_picture(exc)
            self.failed.emit(f"{type(exc).__name__}: {exc}".splitlines()[0], str(picture or ""))
        finally:
            self.done.emit()

    def _refusal_picture(self, failure: Exception):
        """The QC picture of a refusal (:func:`FevarPlannerLib.pipeline.refusal_picture`); None if it has none."""
        from FevarPlannerLib.pipeline import refusal_picture

        try:
            return refusal_picture(failure, self.request.out_dir)
        except Exception as exc:  # the refusal's own message matters more than its picture
            failure.args = (f"{failure} (its QC picture could not be written: {exc})".splitlines()[0],)
            return None
