"""toppledb's public Python API, in one place.

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0, n_contacts=200, n_trials=50)
    result.transitions()   # [(action, next_pose, probability), ...]

This module only gathers names from the layers below; nothing inside the
package imports it.
"""

from __future__ import annotations

from schema.frames import match_pose

from .model.config import Config
from .model.evaluation import PoseEvaluation, evaluate
from .model.mesh import MeshError, ObjectModel, load_mesh
from .model.poses import PoseSet, settle, stable_poses

__all__ = [
    "Config",
    "MeshError",
    "ObjectModel",
    "PoseEvaluation",
    "PoseSet",
    "evaluate",
    "load_mesh",
    "match_pose",
    "settle",
    "stable_poses",
]
