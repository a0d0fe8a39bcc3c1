"""Where every file lives inside a dataset directory (paths relative to its root).

::

    manifest.json                               what was built, how, checksums, counts
    objects.parquet, poses.parquet              consolidated from the shards at the end
    actions/object_id=<id>/part-0.parquet       one partition per object (hive style)
    transitions/object_id=<id>/part-0.parquet
    arrays/<id>.h5                              dense arrays, see schema.hdf5
    _shards/<id>/objects.parquet                the object's rows of objects.parquet ...
    _shards/<id>/poses.parquet                  ... and of poses.parquet
    _shards/<id>/complete.json                  completion record, written last

A shard is everything written for one object; it is complete when its completion
record exists and every file it lists has the recorded SHA-256.  Readers of
``actions/`` and ``transitions/`` skip ``_shards`` and dot-files (pyarrow's
default), and temporary files end in ``.tmp``.
"""

from __future__ import annotations

import re

MANIFEST = "manifest.json"
OBJECTS_FILE = "objects.parquet"
POSES_FILE = "poses.parquet"
SHARDS_DIR = "_shards"
ARRAYS_DIR = "arrays"
TEMP_SUFFIX = ".tmp"

OBJECT_ID_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,127}$")
"""Object ids are file names and hive partition values: no '/', '=', spaces; they start
with a letter or '_' so that no reader mistakes them for numbers."""

READER_WORDS = frozenset({"inf", "infinity", "nan", "true", "false", "epoch"})
"""Ids (in any case) that a reader of one object's partition would type as something other than a
string: duckdb 2.0 reads ``inf``, ``infinity`` and ``epoch`` as DATEs, polars 2.1 ``inf`` and ``NaN``
as floats and ``true``/``false`` as booleans.  tests/test_layout.py reads every accepted near miss
back as a string through each of them."""

HIVE_NULL = "__HIVE_DEFAULT_PARTITION__"
"""The hive partition value every reader reads as null (pyarrow refuses a dataset of it alone);
refused in this spelling only, the readers' own."""


def check_object_id(object_id: str) -> str:
    """Return ``object_id`` or raise ValueError saying why it cannot be used."""
    if not OBJECT_ID_PATTERN.match(object_id):
        raise ValueError(
            f"bad object id {object_id!r}: use letters, digits, '_', '.', '-', starting with a letter or '_'"
        )
    if object_id.lower() in READER_WORDS or object_id == HIVE_NULL:
        raise ValueError(
            f"bad object id {object_id!r}: Parquet readers would read it as a number, date, boolean or null, not a name"
        )
    return object_id


def object_id_key(object_id: str) -> str:
    """What tells two object ids apart: their lower case.  An id names files
    (``arrays/<id>.h5``, a partition directory), which a file system that ignores case (macOS,
    Windows) would store as one for ``Part`` and ``part``."""
    return object_id.lower()


def partition_file(table: str, object_id: str) -> str:
    """The Parquet file of one object's rows of a partitioned table."""
    return f"{table}/object_id={object_id}/part-0.parquet"


def arrays_file(object_id: str) -> str:
    return f"{ARRAYS_DIR}/{object_id}.h5"


def shard_dir(object_id: str) -> str:
    return f"{SHARDS_DIR}/{object_id}"


def shard_rows_file(table: str, object_id: str) -> str:
    """One object's rows of a consolidated table (``objects`` or ``poses``)."""
    return f"{SHARDS_DIR}/{object_id}/{table}.parquet"


def completion_record(object_id: str) -> str:
    return f"{SHARDS_DIR}/{object_id}/complete.json"
