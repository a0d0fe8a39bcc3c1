"""toppledb's public Python API, in one place: one object end to end, no dataset needed.

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)      # metres, kilograms
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0, n_contacts=200, n_trials=50)
    result.transitions()   # [(action, next_pose, probability), ...]

    everything = toppledb.evaluate_object(obj, config)   # every pose: tables, V_s, V_T, policies
    plan = toppledb.plan(everything, observed_4x4)        # the push for an observed pose, world frame
    match = toppledb.match_pose(observed_4x4, poses)      # 10 deg tolerance, z_offset from the table

This module only gathers names from the layers below; nothing inside the
package imports it.
"""

from __future__ import annotations

import numpy as np

from schema import frames

from . import _PUBLIC
from .model.config import Config
from .model.evaluation import (
    NotResting,
    ObservedPose,
    Plan,
    PoseEvaluation,
    evaluate,
    evaluate_object,
    grasp_quality,
    observe,
    plan,
    solve,
)
from .model.mesh import MeshError, ObjectModel, load_mesh
from .model.outcomes import ObjectResult
from .model.poses import PoseSet, settle, stable_poses


def match_pose(observed, poses, transforms=None, tolerance=None, *, table_height: float = 0.0, config: Config = Config()):
    """Match an observed 4x4 pose (object -> world, z up) to a stable pose.

    ``match_pose(observed, poses)`` with a ``PoseSet`` (or an ``ObjectResult``) returns an
    ``ObservedPose``: pose (-1 when none is within ``tolerance``, default
    ``config.poses.same_pose_angle`` = 10 deg), angle_error, yaw, translation, planar,
    pose_to_world and z_offset (m above ``table_height``).
    ``match_pose(observed, downs, transforms, tolerance)`` is the array form
    (``schema.frames.match_pose``).
    """
    if transforms is not None:
        tolerance = config.poses.same_pose_angle if tolerance is None else tolerance
        return frames.match_pose(np.asarray(observed, dtype=float), np.asarray(poses), np.asarray(transforms), tolerance)
    stable = poses.poses if isinstance(poses, ObjectResult) else poses
    return observe(observed, stable, tolerance, table_height, config)


__all__ = list(_PUBLIC)
