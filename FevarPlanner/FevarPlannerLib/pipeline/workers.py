"""A persistent worker process for the per-view 2D work of a multi-view frame (issue 10).

Two views on two cores: the second view's vessel mask, 2D skeleton, graph, Algorithm 1 and
pose check (:func:`frame._view_stage`) run in a worker process while this process does
the first view's; threads cannot do it (the work holds the GIL). The worker is one child
process, started on first use and kept for the frames that follow.
Nothing ever waits for it to start: a job is given to it only once it has reported ready
(imports done); before that, and whenever it cannot start or fails, the work runs here,
serially, with the same result (the same code on the same data; the tests compare the two).
It ends when its pipe closes: when this process exits (however it ends) or :func:`shutdown`.

The pre-operative model is sent once and kept by the worker for the frames that follow.
``FEVARPLANNER_VIEW_WORKER=0`` (or :func:`set_enabled`) turns the worker off.
"""

from __future__ import annotations

import atexit
import itertools
import os
import pickle
import signal
import subprocess
import sys
import threading
import weakref
from multiprocessing.connection import Connection

#: The environment switch: "0" keeps all per-view work in this process.
ENV_SWITCH = "FEVARPLANNER_VIEW_WORKER"
#: How many workers may fail (die, or not start) before no new one is started.
MAX_FAILURES = 2

_state = {"enabled": None, "worker": None, "failures": 0, "in_worker": False}
_tokens = itertools.count(1)


def set_enabled(enabled: bool | None) -> bool | None:
    """Use the worker (True), never (False), or as ``FEVARPLANNER_VIEW_WORKER`` says (None, the default).

    A running worker stays (idle) while it is off; :func:`shutdown` ends it. Returns the
    setting it replaces, so that a caller can put it back.
    """
    previous, _state["enabled"] = _state["enabled"], enabled
    return previous


def enabled() -> bool:
    """Whether per-view work may go to the worker process here."""
    if _state["in_worker"]:
        return False            # the worker never starts a worker of its own
    if _state["enabled"] is not None:
        return bool(_state["enabled"])
    return os.environ.get(ENV_SWITCH, "1").strip() not in ("0", "false", "no", "off") and _can_spawn()


def _can_spawn() -> bool:
    """The worker runs ``sys.executable`` with inherited pipes: POSIX only, and only a Python
    interpreter (not an application embedding Python, such as Slicer's main executable,
    which would open a second window)."""
    return os.name == "posix" and os.path.basename(sys.executable or "").lower().startswith("python")


@atexit.register
def shutdown() -> None:
    """End the worker process, if one runs (and was started by this process)."""
    worker = _state["worker"]
    _state["worker"] = None
    if worker is not None and worker.owner == os.getpid():
        worker.close()


def wait_until_ready(timeout: float = 60.0) -> bool:
    """Start the worker if needed and wait until it takes work (for tests and benchmarks)."""
    worker = _worker()
    return worker is not None and worker.ready(timeout)


def submit(function, preop, *args) -> "Pending":
    """Run ``function(preop, *args)`` in the worker if it is ready, else here when asked for the result.

    ``function`` must be importable by name (a module-level function); its arguments and
    result are pickled. The worker is started here when it does not run yet.
    """
    worker = _worker()
    if worker is not None and worker.ready() and worker.lock.acquire(blocking=False):   # one job at a time
        try:
            worker.send(preop, function, args)
            return Pending(function, preop, args, worker)
        except (pickle.PicklingError, TypeError, AttributeError):      # not picklable: done here instead
            worker.lock.release()
    return Pending(function, preop, args, None)


class Pending:
    """A job given to the worker (or kept here): :meth:`result` gives its value either way."""

    def __init__(self, function, preop, args, worker):
        self._call = (function, preop, args)
        self._worker = worker
        self.remote = worker is not None        # the worker does the job

    def result(self):
        """The job's value; computed here when it was not sent or the worker failed.

        A job given to the worker must be collected (its answer would otherwise wait in the pipe).
        """
        function, preop, args = self._call
        worker, self._worker = self._worker, None
        if worker is not None:
            try:
                return worker.receive()
            except Exception:       # noqa: BLE001  (the worker died or its answer did not unpickle: do it here)
                _discard(worker)
            finally:
                worker.lock.release()
        return function(preop, *args)


def _discard(worker) -> None:
    """Drop a worker that failed."""
    _state["failures"] += 1
    if _state["worker"] is worker:
        _state["worker"] = None
    worker.close()


def _worker():
    """The running worker, started when there is none (None: not to be used here)."""
    if not enabled():
        return None
    worker = _state["worker"]
    if worker is not None and worker.owner != os.getpid():
        worker = _state["worker"] = None     # a forked copy of the process: the worker is the parent's
    if worker is not None and not worker.alive():
        _discard(worker)
        worker = None
    if worker is None and _state["failures"] < MAX_FAILURES:
        try:
            worker = _state["worker"] = _Worker()
        except (OSError, subprocess.SubprocessError):
            _state["failures"] += 1
            worker = None
    return worker


class _Worker:
    """One child process serving jobs over a pair of pipes, in the order they were sent.

    The child is this interpreter started on :func:`_serve` directly (not by
    :mod:`multiprocessing`, whose ``spawn`` would first run the caller's main script again),
    with this process's ``sys.path``, in a session of its own (a terminal's Ctrl-C goes to the
    caller, which ends the worker by closing its pipe; and where the system shares the
    processor between sessions, the worker does not halve the caller's share); the pipes carry pickled messages
    (:class:`multiprocessing.connection.Connection`), a shared file in memory the large
    arrays of a job (:func:`_packed`).
    """

    def __init__(self):
        child_reads, parent_writes = os.pipe()
        parent_reads, child_writes = os.pipe()
        self._arrays = _shared_file()
        shared = -1 if self._arrays is None else self._arrays
        code = (f"import sys; sys.path[:] = {list(sys.path)!r}; "
                f"from {__package__}.workers import _serve; _serve({child_reads}, {child_writes}, {shared})")
        try:
            self._process = subprocess.Popen([sys.executable, "-c", code],
                                             pass_fds=tuple(fd for fd in (child_reads, child_writes, shared) if fd >= 0),
                                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                             start_new_session=True)
        except BaseException:
            for fd in (parent_writes, parent_reads, shared):
                if fd >= 0:
                    os.close(fd)
            raise
        finally:
            os.close(child_reads)
            os.close(child_writes)
        self._send = Connection(parent_writes, readable=False)
        self._receive = Connection(parent_reads, writable=False)
        self._ready = False
        self._preop = (None, 0)         # (weak reference to the model the worker holds, its token)
        self.owner = os.getpid()
        self.lock = threading.Lock()    # held from sending a job until its answer is read
        for fd in (parent_writes, parent_reads):
            _widen_pipe(fd)

    def alive(self) -> bool:
        return self._process.poll() is None

    def ready(self, timeout: float = 0.0) -> bool:
        """Whether the worker has reported ready (waits up to ``timeout`` s for it)."""
        if not self._ready and self.alive() and self._receive.poll(timeout):
            try:
                self._ready = self._receive.recv() == "ready"
            except (EOFError, OSError):
                return False
        return self._ready

    def send(self, preop, function, args) -> None:
        """Send a job: its large arrays (a frame is megabytes) through the shared file, the rest
        pickled through the pipe, which then holds a few kilobytes and never waits for the worker."""
        held, token = self._preop
        fresh = held is None or held() is not preop     # the model goes along with the first job only
        if fresh:
            token = next(_tokens)
        job = (token, preop if fresh else None, function, args)
        self._send.send(_packed(job, self._arrays))
        if fresh:
            self._preop = (weakref.ref(preop), token)

    def receive(self):
        status, value = self._receive.recv()
        if status != "ok":
            raise RuntimeError(f"view worker: {value}")
        return value

    def close(self) -> None:
        """Close the pipes (the worker then ends) and wait for it briefly, else end it; a worker
        still starting is ended at once (it would read its pipe only after its imports)."""
        for conn in (self._send, self._receive):
            conn.close()
        if self._arrays is not None:
            os.close(self._arrays)
            self._arrays = None
        if not self._ready:
            self._process.kill()
        try:
            self._process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


#: Pipe buffer asked for (bytes): an answer (a mask, a 2D graph) in one hand-over.
PIPE_BYTES = 1 << 20


def _widen_pipe(fd: int) -> None:
    """Ask for a :data:`PIPE_BYTES` pipe buffer (Linux; elsewhere, or when refused, the default stays)."""
    try:
        import fcntl

        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass


#: Arrays smaller than this (bytes) go through the pipe with the rest of a job.
SHARED_ABOVE_BYTES = 64 * 1024


def _shared_file() -> int | None:
    """A file in memory (Linux ``memfd``) for the arrays of the jobs; None where there is none."""
    try:
        return os.memfd_create("FevarPlanner-view-worker")
    except (AttributeError, OSError):
        return None


def _packed(job, shared: int | None) -> tuple:
    """``job`` as (pickle, [(offset, length) of each out-of-band buffer]) with the large buffers
    (pickle protocol 5: contiguous NumPy arrays) written into the ``shared`` file, one after the
    other; without a shared file, everything in the pickle."""
    if shared is None:
        return pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL), None
    buffers = []
    data = pickle.dumps(job, protocol=5, buffer_callback=lambda b: _kept_in_band(b, buffers))
    places, offset = [], 0
    for buffer in buffers:
        view = buffer.raw()
        places.append((offset, view.nbytes))
        offset += view.nbytes
    if os.fstat(shared).st_size < offset:
        os.ftruncate(shared, offset)
    for buffer, (start, _) in zip(buffers, places):
        os.pwrite(shared, buffer.raw(), start)
    return data, places


def _kept_in_band(buffer: pickle.PickleBuffer, out_of_band: list) -> bool:
    """``buffer_callback`` of :func:`_packed`: False (out of band) for the large buffers."""
    if buffer.raw().nbytes < SHARED_ABOVE_BYTES:
        return True
    out_of_band.append(buffer)
    return False


def _unpacked(message, shared: int | None):
    """The job of a :func:`_packed` message (its arrays copied out of the shared file: writable)."""
    data, places = message
    if places is None:
        return pickle.loads(data)
    buffers = []
    for offset, length in places:
        buffer = bytearray(length)
        if os.preadv(shared, [buffer], offset) != length:
            raise EOFError("view worker: the shared file is shorter than a job says")
        buffers.append(buffer)
    return pickle.loads(data, buffers=buffers)


def _serve(receive_fd: int, send_fd: int, shared_fd: int = -1) -> None:
    """The worker's loop: import the pipeline, report ready, then run jobs until the pipe closes."""
    _state["in_worker"] = True
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # the caller's Ctrl-C is the caller's; the pipe ends this
    from .. import pipeline, segmentation  # noqa: F401  (the imports, before reporting ready)

    jobs, answers = Connection(receive_fd, writable=False), Connection(send_fd, readable=False)
    shared = shared_fd if shared_fd >= 0 else None
    answers.send("ready")
    models = {}
    while True:
        try:
            token, preop, function, args = _unpacked(jobs.recv(), shared)
        except (EOFError, OSError):
            return
        if preop is not None:
            models = {token: preop}
        try:
            answers.send(("ok", function(models[token], *args)))
        except Exception as exc:     # noqa: BLE001  (reported to the caller, which then works alone)
            answers.send(("error", f"{type(exc).__name__}: {exc}"))
