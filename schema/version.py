"""Versions: of the data contract, and of the code that writes or serves it."""

from importlib.metadata import PackageNotFoundError, version

SCHEMA_VERSION = "1.1"
"""Changes whenever a table, the HDF5 layout or the dataset layout changes.

1.1: objects.hull_vertices, poses.equivalent_transforms (symmetric poses merged), and
the served tables (``served/*.arrow``, memory-mapped by the service)."""

try:
    CODE_VERSION = version("toppledb")
except PackageNotFoundError:  # running from a checkout that was never installed
    CODE_VERSION = "0+unknown"
