"""toppledb's compute side, in three layers that depend only downwards:

- ``pipeline.model``: one object at a time (config, meshes, stable poses, candidate
  pushes, the toppling model and its scalar reference, suction quality, value
  iteration, one-object evaluation);
- ``pipeline.build``: the dataset job (corpus, selection, rows, shards, manifest,
  fan-out, verify);
- ``pipeline.studies``: what is measured on top (bench, physics validation,
  policy experiment).

The public API (``pipeline.api``) is loaded lazily, so that ``import pipeline``
does not pull in the geometry stack::

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0)
"""

from importlib import import_module

# Before anything loads numpy: one BLAS kernel on every machine, so a build's numbers do not
# depend on the processor it ran on (pipeline.numerics).
from pipeline.numerics import pin_blas_kernel

pin_blas_kernel()

from schema.version import CODE_VERSION as __version__

_PUBLIC = ("Config", "MeshError", "NotResting", "ObjectModel", "ObjectResult", "ObservedPose", "Plan", "PoseEvaluation",
           "PoseSet", "evaluate", "evaluate_object", "grasp_quality", "load_mesh", "match_pose", "plan", "plan_heap", "settle",
           "solve", "stable_poses")
"""The names of ``pipeline.api`` (its ``__all__``), listed here so that they resolve without importing it."""

__all__ = sorted(_PUBLIC) + ["__version__"]


def __getattr__(name):
    if name in _PUBLIC:
        return getattr(import_module("pipeline.api"), name)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
