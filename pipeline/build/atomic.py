"""Atomic file writes: a file is either absent, the old version, or the complete
new one, whatever moment the process is killed at (power loss included).

Every file of a dataset goes through ``write_atomic``: written to a temporary name
beside its target, optionally read back, flushed to disk, renamed into place, and
then the directory entry is flushed too, so the rename itself survives a crash.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from pathlib import Path
from typing import Callable

from schema import layout
from schema.manifest import file_sha256  # noqa: F401 (the pipeline's callers import it from here)


def write_atomic(path: str | Path, write: Callable[[Path], None], check: Callable[[Path], None] | None = None) -> str:
    """Write ``path`` via ``write(temp)``; ``check(temp)`` (read it back) if given; fsync the
    file, rename it into place, fsync the directory.  Returns the file's SHA-256.

    The temporary file (``.<name>.<random>.tmp``, which dataset readers skip) is removed
    when anything fails, and the old ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}{layout.TEMP_SUFFIX}")
    try:
        write(temp)
        if check is not None:
            check(temp)
        with open(temp, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
            os.fsync(f.fileno())
        os.replace(temp, path)
        fsync_directory(path.parent)
    finally:
        temp.unlink(missing_ok=True)
    return digest


def write_text_atomic(path: str | Path, text: str) -> str:
    """``write_atomic`` for a text file (UTF-8); returns its SHA-256."""
    return write_atomic(path, lambda temp: temp.write_text(text, encoding="utf-8"))


def write_json_atomic(path: str | Path, record) -> str:
    """``write_text_atomic`` of a JSON-ready record, indented one space a level, as every study writes its
    report; returns its SHA-256."""
    return write_text_atomic(path, json.dumps(record, indent=1) + "\n")


def figure_format(path: str | Path) -> str:
    """The image format a figure's file name asks for: its suffix, lower case, without the dot."""
    return Path(path).suffix.lstrip(".").lower()


def write_figure_atomic(path: str | Path, figure, dpi: int = 100) -> str:
    """``write_atomic`` of a matplotlib figure in the format its suffix names (the temporary file's
    own suffix would say nothing); returns its SHA-256."""
    return write_atomic(path, lambda temp: figure.savefig(temp, format=figure_format(path), dpi=dpi))


def fsync_directory(directory: str | Path) -> None:
    """Flush a directory's entries (renames, unlinks) to disk."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
