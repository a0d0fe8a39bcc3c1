"""toppledb's data contract: what a dataset directory holds, shared by the
pipeline that writes it and the service and analysts that read it.

- ``schema.tables``: Arrow schemas of the four tables (objects, poses, actions,
  transitions), every column documented in its field metadata.
- ``schema.hdf5``: the layout of the per-object HDF5 file of dense arrays.
- ``schema.layout``: where each file lives inside a dataset directory.

``SCHEMA_VERSION`` changes whenever any of these change; a dataset records the
version it was written with, and shards of another version are rebuilt.
"""

from schema.tables import (
    ACTIONS,
    OBJECTS,
    PARTITION_KEY,
    POLICIES,
    POSES,
    TABLES,
    TRANSITIONS,
    describe,
    file_schema,
)
from schema.version import SCHEMA_VERSION

__all__ = [
    "SCHEMA_VERSION",
    "ACTIONS",
    "OBJECTS",
    "PARTITION_KEY",
    "POLICIES",
    "POSES",
    "TABLES",
    "TRANSITIONS",
    "describe",
    "file_schema",
]
