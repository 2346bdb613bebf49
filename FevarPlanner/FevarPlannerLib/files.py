"""The ground floor: input errors, stat-before-open checks and atomic writes.

Knows no stage and imports nothing from the package, so every module may use it. Every
writer goes through a temporary file in the target folder and a rename (or a whole
folder swapped in one step), so a failure never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import glob
import json
import os
import re
import shutil
import socket
import stat
import tempfile
from pathlib import Path

__all__ = [
    "InputError",
    "InputWarning",
    "MAX_JSON_BYTES",
    "display_path",
    "check_readable",
    "check_input_file",
    "check_inside",
    "read_json_file",
    "output_mode",
    "atomic_path",
    "write_bytes_atomic",
    "write_text_atomic",
    "swap_folder",
    "staging_folder",
    "remove_stale_staging",
    "atomic_folder",
]

#: JSON inputs (geometry.json, gt.json) larger than this are refused unread.
MAX_JSON_BYTES = 64_000_000


class InputError(ValueError):
    """Bad input: the message names the file and the problem (one line)."""


class InputWarning(UserWarning):
    """Input accepted with a caveat the user should hear of (the CLI prints it, result.json keeps it)."""


def display_path(path) -> str:
    """``path`` as printable text: bytes that are not UTF-8 appear as ``\\xNN`` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


_SPECIAL_FILES = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
                  (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _special_kind(mode: int) -> str | None:
    return next((what for test, what in _SPECIAL_FILES if test(mode)), None)


def check_readable(path: Path, folder_ok: bool = True) -> os.stat_result:
    """Refuse what cannot be read as an input, from ``stat`` alone (nothing is opened).

    A missing path or broken link, a named pipe, device or socket (reading one could block
    for ever or never end), a 0-byte file, a folder where a file is expected and a name
    that is not valid UTF-8 (SimpleITK cannot take it) raise :class:`InputError`.
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise InputError(f"{display_path(path)}: a broken link (to {display_path(os.readlink(path))})") from None
        raise InputError(f"{display_path(path)}: no such file") from None
    except OSError as exc:
        raise InputError(f"{display_path(path)}: cannot open ({exc.strerror})") from None
    kind = _special_kind(info.st_mode)
    if kind is not None:
        raise InputError(f"{display_path(path)}: is {kind}, not a file; refusing to read from it")
    if stat.S_ISDIR(info.st_mode) and not folder_ok:
        raise InputError(f"{display_path(path)}: is a folder, expected a file")
    if stat.S_ISREG(info.st_mode) and info.st_size == 0:
        raise InputError(f"{display_path(path)}: file is empty (0 bytes)")
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{display_path(path)}: the file name is not valid UTF-8 (the image readers cannot "
                         f"open it); rename it") from None
    return info


def check_input_file(path) -> os.stat_result:
    """:func:`check_readable` for a path that must be a regular file."""
    return check_readable(path, folder_ok=False)


def check_inside(path, folder, what: str) -> None:
    """Refuse ``path`` if it resolves (through links) to a place outside ``folder``."""
    target = Path(os.path.realpath(path))
    root = Path(os.path.realpath(folder))
    if target != root and root not in target.parents:
        raise InputError(f"{display_path(path)}: leads to {display_path(target)}, outside {what} "
                         f"{display_path(folder)}; give it explicitly with its flag to use it")


def _current_umask() -> int:
    """The process umask, read without changing it (Linux), else set and restored."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def output_mode(folder: bool = False) -> int:
    """The mode a new file (0666) or folder (0777) gets under the current umask."""
    return (0o777 if folder else 0o666) & ~_current_umask()


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The file gets the mode of a newly created file under the umask (``mkstemp`` makes 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, output_mode())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file and a rename."""
    write_bytes_atomic(path, text.encode("utf-8"))


_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EPERM):
        return False
    raise OSError(code, os.strerror(code), str(b))


def _moved_into_free_place(new: Path, folder: Path) -> bool:
    """Rename ``new`` to the absent ``folder``; False when another run put a folder there first."""
    try:
        os.replace(new, folder)
    except OSError as exc:
        if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
            return False
        raise
    return True


def _staging_owner() -> str:
    """``host-pid`` of this process, as it appears in the names of its staging folders."""
    return f"{socket.gethostname().replace('.', '_')}-{os.getpid()}"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_staging(folder) -> list:
    """Delete the staging folders that killed runs on this host left beside ``folder``.

    A staging folder is named ``.<folder>.<kind>.<host>-<pid>.<random>``; it is stale when
    its process is gone. Nothing is deleted while ``folder`` itself is absent: a run killed
    in the middle of a non-atomic swap may have left the only copy of the old set there.
    Returns the folders deleted.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    pattern = re.compile(r"\." + re.escape(folder.name) + r"\.(?:staging|writing|old)\."
                         + re.escape(socket.gethostname().replace(".", "_")) + r"-(\d+)\.\w+")
    removed = []
    for candidate in folder.parent.glob(f".{glob.escape(folder.name)}.*"):
        match = pattern.fullmatch(candidate.name)
        if match and candidate.is_dir() and not candidate.is_symlink() and not _process_alive(int(match[1])):
            shutil.rmtree(candidate, ignore_errors=True)
            removed.append(candidate)
    return removed


def staging_folder(folder, kind: str, *, clean: bool = True) -> Path:
    """A new empty folder beside ``folder`` to build its next content in.

    Its name says which output it is for, why (``kind``: ``staging``, ``writing``, ``old``)
    and which process owns it, so that the next run can remove it if that process was
    killed (:func:`remove_stale_staging`, done here unless ``clean`` is false).
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    if clean:
        remove_stale_staging(folder)
    return Path(tempfile.mkdtemp(prefix=f".{folder.name}.{kind}.{_staging_owner()}.", dir=folder.parent))


def swap_folder(new: Path, folder: Path) -> None:
    """Put the complete folder ``new`` in the place of ``folder`` and delete the old one.

    Where the system can, the two are exchanged in one step, so ``folder`` always holds
    either the old or the new set. Elsewhere the old one is moved aside first and deleted
    only once the new one is in place.
    """
    new, folder = Path(new), Path(folder)
    if not os.path.lexists(folder) and _moved_into_free_place(new, folder):
        return
    if _exchange(new, folder):
        shutil.rmtree(new)
        return
    old = staging_folder(folder, "old", clean=False)
    os.replace(folder, old)
    os.replace(new, folder)
    shutil.rmtree(old)


@contextlib.contextmanager
def atomic_folder(folder):
    """Yield a temporary folder beside ``folder``; it replaces ``folder`` if the block succeeds.

    The old content stays in place until the new set is complete (:func:`swap_folder`), so
    a failure or a killed process leaves it untouched. The new folder gets the umask's mode.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    tmp = staging_folder(folder, "staging")
    try:
        os.chmod(tmp, output_mode(folder=True))
        yield tmp
        swap_folder(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def read_json_file(path, what: str = "JSON"):
    """Parse a JSON input; size, encoding, syntax and nesting problems raise :class:`InputError`."""
    path = Path(path)
    info = check_input_file(path)
    if info.st_size > MAX_JSON_BYTES:
        raise InputError(f"{display_path(path)}: {what} file of {info.st_size} bytes exceeds the "
                         f"{MAX_JSON_BYTES}-byte limit")
    try:
        text = path.read_bytes().decode("utf-8")
        return json.loads(text)
    except UnicodeDecodeError:
        raise InputError(f"{display_path(path)}: {what} file is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{display_path(path)}: not valid {what} ({exc.msg} at line {exc.lineno} "
                         f"column {exc.colno})") from None
    except RecursionError:
        raise InputError(f"{display_path(path)}: {what} nested too deeply to be a {what} file") from None
    except OSError as exc:
        raise InputError(f"{display_path(path)}: cannot read ({exc.strerror})") from None
