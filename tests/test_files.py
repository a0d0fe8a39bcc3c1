"""Files written whole or not at all (``schema.files``): ``write_atomic`` never replaces a file when told
not to, whatever way the name is taken, and leaves no temporary; ``fsync_directory`` flushes directories."""

from __future__ import annotations

import errno

import pytest

import schema.files
from schema.files import file_sha256, fsync_directory, write_atomic


def test_an_exclusive_write_never_replaces_a_file(tmp_path):
    path = tmp_path / "log" / "pushes.parquet"
    digest = write_atomic(path, lambda temp: temp.write_bytes(b"first"), exclusive=True)
    assert path.read_bytes() == b"first" and digest == file_sha256(path)
    with pytest.raises(FileExistsError, match=r"pushes.parquet exists: it is not replaced"):
        write_atomic(path, lambda temp: temp.write_bytes(b"second"), exclusive=True)
    assert path.read_bytes() == b"first" and [p.name for p in path.parent.iterdir()] == ["pushes.parquet"]
    assert write_atomic(path, lambda temp: temp.write_bytes(b"second")) == file_sha256(path) and path.read_bytes() == b"second"
    assert file_sha256(tmp_path / "absent") == ""


def test_a_failed_move_onto_the_claimed_name_raises_its_own_error(tmp_path, monkeypatch):
    """Without hard links the name is claimed and the file moved onto it; when the move fails after the claim
    has gone (another process removed it), the caller sees why the move failed and nothing is left."""
    def no_links(source, target):
        raise OSError(errno.EPERM, "Operation not permitted")

    def failed_move(source, target):
        target.unlink()
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(schema.files.os, "link", no_links)
    monkeypatch.setattr(schema.files.os, "replace", failed_move)
    with pytest.raises(OSError, match="Input/output error"):
        write_atomic(tmp_path / "pushes.parquet", lambda temp: temp.write_bytes(b"data"), exclusive=True)
    assert list(tmp_path.iterdir()) == []


def test_fsync_directory_flushes_directories_only(tmp_path):
    fsync_directory(tmp_path)
    (tmp_path / "a-file").write_text("")
    with pytest.raises(NotADirectoryError):
        fsync_directory(tmp_path / "a-file")
