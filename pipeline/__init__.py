"""toppledb's compute side: meshes, stable poses, the toppling model, suction
quality, value iteration, and the dataset job.

The public API is loaded lazily so that light modules (``pipeline.frames``,
``pipeline.results``) import without the geometry stack::

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0)
"""

from importlib import import_module

__version__ = "0.1.0"

_EXPORTS = {
    "Config": "pipeline.config",
    "load_mesh": "pipeline.mesh",
    "MeshError": "pipeline.mesh",
    "stable_poses": "pipeline.poses",
    "settle": "pipeline.poses",
    "match_pose": "pipeline.frames",
    "evaluate": "pipeline.api",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
