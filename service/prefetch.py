"""The served files mapped and hashed on a thread of their own as soon as ``python -m service``
has read its arguments, while the interpreter imports the rest of the service.

Every load checks the served files against the manifest's SHA-256 (``schema.served``): about
0.1 s for the default dataset's 180 MB from the file cache, 0.5 s from disk, which a launch
would otherwise wait for on top of its 0.35 s of imports.  Hashing releases the interpreter
lock, so on a second core it costs the launch next to nothing.

Only the standard library: this module is imported before numpy, pyarrow and pydantic, and
so it cannot use ``schema`` (whose package imports pyarrow).  It is a hint, never a source
of truth: ``Store.load`` takes its mappings only for the directory and the manifest bytes it
loads itself, and maps and hashes the files on its own otherwise (or when anything here
failed; then the load says what is wrong).
"""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import threading
from pathlib import Path

SERVED_PREFIX = "served/"
"""The manifest's ``tables`` entries that are served files (``schema.served.FILES``)."""


def map_and_hash(path: Path) -> tuple[mmap.mmap, str]:
    """A file mapped read-only and the hex SHA-256 of the mapped bytes.

    Hashed through the map, so the digest is of the very bytes served, in one call that releases
    the interpreter lock throughout (``hashlib.file_digest`` reads in a Python loop, which contends
    with the imports it should overlap: 1.26-1.36 s to the first /health from disk, against
    0.81-0.89 this way, stop 64); then advised away (MADV_DONTNEED), so the pages stay in the file cache but
    leave this process's resident set until a request touches them.  OSError, or ValueError for an empty file or one that is
    not a regular file (opening a named pipe would wait for a writer)."""
    if not Path(path).is_file():
        raise ValueError(f"{path}: not a regular file")
    with open(path, "rb") as f:
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # outlives the descriptor
    digest = hashlib.sha256(mapped).hexdigest()
    if hasattr(mmap, "MADV_DONTNEED"):
        mapped.madvise(mmap.MADV_DONTNEED)
    return mapped, digest


class Prefetch:
    """``map_and_hash`` of every served file the manifest of ``root`` lists, on a daemon thread."""

    def __init__(self, root: str | Path):
        self.root = os.path.realpath(root)  # not Path.resolve: a symlink loop is the load's to report
        self._files: dict[str, tuple[mmap.mmap, str]] = {}
        self._manifest_sha256 = ""
        self._thread = threading.Thread(target=self._run, name="prefetch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            manifest = (Path(self.root) / "manifest.json").read_bytes()
            relatives = [name for name in json.loads(manifest)["tables"] if name.startswith(SERVED_PREFIX)]
            files = {relative: map_and_hash(Path(self.root) / relative) for relative in relatives}
        except Exception:  # noqa: BLE001 (a hint: the load maps, hashes and reports by itself)
            return
        self._files, self._manifest_sha256 = files, hashlib.sha256(manifest).hexdigest()

    def mapped(self, root: str | Path, manifest_sha256: str) -> dict[str, tuple[mmap.mmap, str]]:
        """Relative path -> (mapping, SHA-256) of the served files, once the thread is done; empty
        unless they were mapped for ``root`` under the manifest whose bytes hash to ``manifest_sha256``.
        Handed over once: this object keeps no mapping, so a later rebuild's old files are freed
        with the store that serves them."""
        self._thread.join()
        files, self._files = self._files, {}
        if os.path.realpath(root) != self.root or manifest_sha256 != self._manifest_sha256:
            return {}
        return files
