"""Versions: of the data contract, and of the code that writes or serves it."""

from importlib.metadata import PackageNotFoundError, version

SCHEMA_VERSION = "1.0"
"""Changes whenever a table, the HDF5 layout or the dataset layout changes."""

try:
    CODE_VERSION = version("toppledb")
except PackageNotFoundError:  # running from a checkout that was never installed
    CODE_VERSION = "0+unknown"
