"""Atomic file writes: every artifact appears whole under its final name, or not at all.

Outputs are written to a hidden temporary file in the destination folder (``.<stem>.<random>.tmp
<suffix>``) and moved into place with ``os.replace`` (atomic on one file system), so an
interrupted run never leaves a truncated video, sidecar or report behind. The temporary file is
removed on any error; what a killed process (``kill -9``) left of it is removed by the next write
of the same file (:func:`remove_temp_files`). A failed write (full disk, no permission) is one
:class:`WriteError` line naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any


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
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` atomically."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    return write_text_atomic(path, json.dumps(data, indent=2, allow_nan=True) + "\n")
