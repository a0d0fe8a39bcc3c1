"""The dataset schema version, in its own module so every schema module can import it."""

SCHEMA_VERSION = "1.0"
"""Bumped whenever a table schema, the HDF5 layout or the directory layout changes."""
