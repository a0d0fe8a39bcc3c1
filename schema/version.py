"""Versions: of the data contract, and of the code that writes or serves it."""

from importlib.metadata import PackageNotFoundError, version

SCHEMA_VERSION = "1.2"
"""Changes whenever a table, the HDF5 layout or the dataset layout changes.

1.1: objects.hull_vertices, poses.equivalent_transforms (symmetric poses merged), and
the served tables (``served/*.arrow``, memory-mapped by the service).
1.2: the HDF5 arrays' ``edge_landed_pose``, ``edge_onward_pose`` and ``edge_onward_share``: where the
build's variant lands each edge's topples (``edge_final_pose`` is the thesis's landing); ``poses.v_failed``,
the value an action's ``q`` gives the pose when the push leaves the object in it."""

try:
    CODE_VERSION = version("toppledb")
except PackageNotFoundError:  # running from a checkout that was never installed
    CODE_VERSION = "0+unknown"
