"""Files written whole or not at all, and their checksums: what the build, the studies and a
robot's push log all write with (``pipeline.build.atomic`` adds the text, JSON and figure forms).

``write_atomic`` writes to a temporary name beside the target (``.<name>.<random>.tmp``, which
every reader skips), optionally reads it back, flushes it to disk, puts it in place and flushes
the directory, so the file is absent, the old version or the complete new one whatever moment
the process is killed at, power loss included.
"""

from __future__ import annotations

import errno
import hashlib
import os
import uuid
from collections.abc import Callable
from pathlib import Path

from schema import layout

NO_HARD_LINKS = (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.EXDEV)
"""``os.link`` errors of a file system without hard links (FAT, SMB without unix extensions, FUSE)."""


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, "" when it cannot be read."""
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return ""


def fsync_directory(directory: str | Path) -> None:
    """Flush a directory's entries (renames, links, unlinks) to disk."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, write: Callable[[Path], None], check: Callable[[Path], None] | None = None,
                 exclusive: bool = False) -> str:
    """Write ``path`` via ``write(temp)``; ``check(temp)`` (read it back) if given; fsync the
    file, put it in place, fsync the directory.  Returns the file's SHA-256.

    exclusive : never replace a file at ``path`` (FileExistsError): the file is linked in, which
      fails where a rename would replace; where the file system has no hard links, the name is
      claimed by an exclusive create and the whole file moved onto the claim

    The temporary file is removed when anything fails, and the old ``path`` is left as it was.
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
        if exclusive:
            _link_new(temp, path)
        else:
            os.replace(temp, path)
        fsync_directory(path.parent)
    finally:
        temp.unlink(missing_ok=True)
    return digest


def _link_new(temp: Path, path: Path) -> None:
    """``temp`` in place as ``path`` only if no file is there."""
    try:
        os.link(temp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists: it is not replaced") from None
    except OSError as err:
        if err.errno not in NO_HARD_LINKS:
            raise
        with open(path, "xb"):  # claim the name
            pass
        try:
            os.replace(temp, path)
        except BaseException:
            path.unlink(missing_ok=True)  # the empty claim, which a reader would take for a broken file
            raise
