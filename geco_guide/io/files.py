"""Atomic file writes: every artifact appears whole under its final name, or not at all.

Outputs are written to a hidden temporary file in the destination folder (``.<stem>.<random>.tmp
<suffix>``) and moved into place with ``os.replace`` (atomic on one file system), so an
interrupted run never leaves a truncated video, sidecar or report behind. The temporary file is
removed on any error; what a killed process (``kill -9``) left of it is removed by the next write
of the same file (:func:`remove_temp_files`). A failed write (full disk, no permission) is one
:class:`WriteError` line naming the file. Files that belong together (a report's JSON and its
Markdown) are written all or none (:func:`write_texts_atomic`), and an output folder can be checked
before the work that fills it (:func:`check_output_dir`).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["TEMP_NAME_EXTRA", "WriteError", "atomic_path", "check_output_dir", "check_output_paths", "json_ready", "json_text", "output_lock",
           "probe_writable", "remove_temp_files", "take_pid_lock", "unique_names", "write_bytes_atomic",
           "write_json_atomic", "write_text_atomic", "write_texts_atomic"]


class WriteError(OSError):
    """An output could not be written (disk full, no permission, a writer that failed); one line
    naming the file. Nothing is left under its name or as a temporary file."""


def _temp_name(stem: str, suffix: str | None) -> re.Pattern[str]:
    """The names :func:`atomic_path` gives the temporaries of ``<stem><suffix>`` (any suffix when
    None). The random part holds no dot, so the stem ``a`` never matches a temporary of ``a.b.mp4``."""
    ending = r"(\.[^.]*)?" if suffix is None else re.escape(suffix)
    return re.compile(rf"\.{re.escape(stem)}\.[A-Za-z0-9_]+\.tmp{ending}")


def remove_temp_files(folder: str | os.PathLike, stems: Sequence[str], suffix: str | None = None) -> None:
    """Delete the temporary files that killed atomic writes of ``<stem>*`` left in ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    patterns = [_temp_name(stem, suffix) for stem in stems]
    for path in folder.iterdir():
        if any(p.fullmatch(path.name) for p in patterns) and path.is_file():
            path.unlink(missing_ok=True)


def _reason(err: BaseException) -> str:
    lines = str(err).strip().splitlines()  # writers' errors can carry a whole ffmpeg log
    return lines[0] if lines else type(err).__name__


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to; on success it replaces ``path``.

    The temporary name keeps the suffix (writers such as ffmpeg pick the format from it) and
    gets ordinary permissions (``mkstemp`` would leave it private). Temporaries of ``path`` left by
    a killed earlier run are removed first.

    Raises:
        WriteError: an OSError while writing or moving (disk full, ...), naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_temp_files(path.parent, [path.stem], path.suffix)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
        os.close(fd)
    except OSError as err:
        raise WriteError(f"cannot write {str(path)!r}: {_reason(err)}") from err
    try:
        yield Path(tmp)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)
        os.replace(tmp, path)
    except BaseException as err:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, WriteError):
            raise WriteError(f"cannot write {str(path)!r}: {_reason(err)}") from err
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (flushed to disk before the rename)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` atomically."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_texts_atomic(texts: Mapping[str | os.PathLike, str | bytes]) -> list[Path]:
    """Write each ``{path: text}`` (a str as UTF-8, or bytes) all or none: every file goes to its
    temporary first, and they take their names only once all of them are written, so a failed
    write (a full disk) leaves none of them, not one file of a pair that describes the other."""
    with contextlib.ExitStack() as stack:
        for path, text in texts.items():
            tmp = stack.enter_context(atomic_path(path))
            with open(tmp, "wb") as fh:
                fh.write(text.encode("utf-8") if isinstance(text, str) else text)
                fh.flush()
                os.fsync(fh.fileno())
    return [Path(path) for path in texts]


def json_ready(data: Any) -> Any:
    """``data`` with every non-finite float (NaN, inf) replaced by None, so that it is standard
    JSON (``NaN`` and ``Infinity`` are not) that every reader parses, and means "no value"."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, Mapping):
        return {key: json_ready(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_ready(value) for value in data]
    return data


def json_text(data: Any) -> str:
    """``data`` as indented standard JSON (non-finite floats as null, see :func:`json_ready`)."""
    return json.dumps(json_ready(data), indent=2, allow_nan=False) + "\n"


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented standard JSON to ``path`` atomically (NaN and inf as null)."""
    return write_text_atomic(path, json_text(data))


def probe_writable(folder: str | os.PathLike) -> None:
    """Make and remove a temporary file in ``folder``; OSError where files cannot be made there
    (read-only, full, a name too long), found before the work instead of after it."""
    fd, probe = tempfile.mkstemp(prefix=".write-check.", suffix=".tmp", dir=folder)
    os.close(fd)
    os.unlink(probe)


def check_output_dir(folder: str | os.PathLike, option: str = "--out") -> Path:
    """Create ``folder`` if needed and check that files can be made in it, before the work that
    fills it: otherwise a file in its place or a read-only folder shows only at the end.

    Raises:
        WriteError: one line naming ``option`` and the folder.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise WriteError(f"{option} {str(folder)!r} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe_writable(folder)
    except OSError as err:
        raise WriteError(f"cannot write to {option} {str(folder)!r}: {_reason(err)}") from err
    return folder


def unique_names(names: Iterable[str]) -> list[str]:
    """``names`` with repeats numbered ``-2``, ``-3``, ... in order (``a, a, a`` -> ``a, a-2,
    a-3``), never reusing a name given or made (``a, a, a-2`` -> ``a, a-3, a-2``): inputs that
    share a stem get outputs of their own instead of overwriting each other's."""
    names = list(names)
    taken = set(names)
    seen: set[str] = set()
    out = []
    for name in names:
        unique = name
        if name in seen:
            count = 2
            while f"{name}-{count}" in taken:
                count += 1
            unique = f"{name}-{count}"
            taken.add(unique)
        seen.add(name)
        out.append(unique)
    return out


def lock_holder(lock: Path) -> int | None:
    """The pid in a lock file, or None when it holds none (a damaged or vanished lock)."""
    try:
        pid = int(lock.read_text(encoding="utf-8").strip())
    except (OSError, ValueError):
        return None
    return pid if pid > 0 else None  # os.kill(0 or -1, ...) would ask about other processes


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # OverflowError: a pid no process can have
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def take_pid_lock(lock: Path, busy: str, elsewhere: str) -> Path:
    """Create the file ``lock`` holding this pid (``O_CREAT | O_EXCL``: one process wins), taking
    over a lock whose process is gone (a killed run). ValueError (one line) while a live process
    holds it (``busy``, with ``{pid}`` for its pid), when ``lock`` is a folder, or when it cannot
    be written; ``elsewhere`` says what to do instead (e.g. "use another --out folder")."""
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if lock.is_dir():
                raise ValueError(f"{lock} is a folder, not a run lock; remove it (or {elsewhere})") from None
            holder = lock_holder(lock)
            if holder is not None and pid_alive(holder):
                raise ValueError(busy.format(pid=holder)) from None
            lock.unlink(missing_ok=True)  # its run was killed
            continue
        except OSError as err:
            raise ValueError(f"cannot write {str(lock)!r}: {err.strerror or err}") from None
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{os.getpid()}\n")
        return lock
    raise ValueError(f"another run took {lock} at the same moment; {elsewhere}")


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, instead: str = "choose another --out or output.name") -> Iterator[None]:
    """Hold ``.<name>.lock`` beside the output ``path`` while a run makes it, released however the
    block ends: a second run that would write the same file fails at once (one line naming the
    pid of the first, and ``instead``: what else to do) instead of both writing and one result
    silently replacing the other."""
    path = Path(path)
    lock = path.with_name(f".{path.name}.lock")
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot write {str(path)!r}: {_reason(err)}") from None
    take_pid_lock(lock, f"another run (pid {{pid}}) is writing {str(path)!r}; wait for it to end or {instead}", instead)
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


#: Longest name a temporary of an atomic write adds to ``<name>``: ``.<name>.<8 random>.tmp``
#: before the suffix (see :func:`atomic_path`).
TEMP_NAME_EXTRA = len("..12345678.tmp")


def _nearest_existing(path: Path) -> Path:
    """``path``'s nearest ancestor that exists (the folder an atomic write would create the rest in)."""
    return next((parent for parent in path.parents if os.path.exists(parent)), Path.cwd())


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):  # no pathconf for this file system: the common limit
        return 255


def _name_problem(path: Path, existing: Path) -> str | None:
    """Why a name of ``path`` below ``existing`` is too long for the file system (the file's with
    the temporary name its atomic write uses), or None."""
    limit = _name_max(existing)
    too_long = next((part for part in path.parent.parts[len(existing.parts):] if len(part.encode()) > limit), None)
    if too_long is not None:
        return (f"the folder name {too_long[:24]!r}... is {len(too_long.encode())} bytes, over the {limit} this "
                "file system allows")
    if len(path.name.encode()) + TEMP_NAME_EXTRA > limit:
        return (f"the name is {len(path.name.encode())} bytes, over the {limit - TEMP_NAME_EXTRA} this file system "
                "allows (a shorter output.name or --out)")
    return None


def check_output_paths(paths: Sequence[Path], overwrite: bool = False) -> None:
    """ValueError (one line) for anything that would make writing ``paths`` fail after sampling:
    a name too long for the file system, a file where a folder must be, a folder or (without
    ``overwrite``) a file under an output's name, a folder that cannot be written."""
    for path in paths:
        existing = _nearest_existing(path)
        problem = _name_problem(path, existing)
        if problem is None and not existing.is_dir():
            problem = f"{str(existing)!r} is a file, not a folder"
        if problem is None and path.is_dir():
            problem = "a folder of that name is in the way"
        if problem is None and not os.access(existing, os.W_OK | os.X_OK):
            problem = f"the folder {str(existing)!r} is not writable"
        if problem is not None:
            raise ValueError(f"cannot write {str(path)!r}: {problem}")
        if path.exists() and not overwrite:
            raise ValueError(f"{str(path)!r} already exists; pass --overwrite to replace it, or choose another "
                             "--out or output.name")
