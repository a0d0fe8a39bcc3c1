"""Atomic file writes: a file is either absent, the old version, or the complete
new one, whatever moment the process is killed at (power loss included).

Every file of a dataset goes through ``write_atomic`` (``schema.files``, where a robot's push
log is written too); here are its text, JSON and figure forms.
"""

from __future__ import annotations

import json
from pathlib import Path

from schema.files import file_sha256, fsync_directory, write_atomic  # noqa: F401 (the pipeline's callers import them from here)


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
