"""toppledb's public Python API, in one place: one object end to end, no dataset needed.

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)      # metres, kilograms
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0, n_contacts=200, n_trials=50)
    result.transitions()   # [(action, next_pose, probability), ...]

    everything = toppledb.evaluate_object(obj, config)   # every pose: tables, V_s, V_T, policies
    plan = toppledb.plan(everything, observed_4x4)        # the push for an observed pose, world frame
    match = toppledb.match_pose(observed_4x4, poses)      # 10 deg tolerance, z_offset from the table
    push = toppledb.plan_heap(["duck", "mug"], [pose_a, pose_b], "data/dataset", "boundary_shear")  # chapter 3

This module only gathers names from the layers below; nothing inside the
package imports it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from clutter.policies import PushConfig, outside_bin, plan_push
from clutter.state import Bin, HeapState, Push
from schema import frames
from schema.api import BIN_TOLERANCE, MAX_SEED
from schema.reader import Dataset

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


def plan_heap(object_ids: Sequence[str], poses, objects: Mapping[str, ObjectModel] | str | Path,
              policy: str = "boundary_shear", *, bin: Bin | None = None, seed: int = 0,
              config: PushConfig | None = None) -> Push | None:
    """The push a planar push policy of thesis 3.2 chooses for a heap in a bin, as POST /heaps/plan.

    object_ids : n dataset or mesh ids (an id may repeat)
    poses : (n, 4, 4) object -> world (the bin's frame: origin at the centre of its floor, z up)
    objects : {object_id: ObjectModel} (``load_mesh``: hull and centre of mass), or a dataset
        directory (hull vertices and centre of mass from its objects table, as the service serves them)
    policy : one of ``clutter.policies.POLICIES``
    bin : default ``Bin()``, the tote the service assumes too; seed : quasi_random's draws (the
        same seed gives the service's push); config : the planner's numbers (``PushConfig()``)

    Returns a ``clutter.state.Push`` (world start and end of the finger's line, target index),
    or None when the policy finds no collision-free push.  ValueError for an unknown id or
    policy, malformed poses, a seed that is no integer in [0, ``schema.api.MAX_SEED``] (the
    service's range), or an object more than ``schema.api.BIN_TOLERANCE`` past a wall or below
    the floor.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be an integer from 0 to {MAX_SEED}, got {seed!r}")
    ids = tuple(object_ids)
    state = HeapState(bin or Bin(), ids, np.asarray(poses, dtype=np.float64))
    if isinstance(objects, Mapping):
        missing = sorted(set(ids) - set(objects))
        if missing:
            raise ValueError(f"no mesh given for {', '.join(map(repr, missing))}")
        hulls = [np.asarray(objects[i].hull.vertices, dtype=np.float64) for i in ids]
        centres = np.array([objects[i].center_mass for i in ids], dtype=np.float64)
    else:
        hulls, centres = _dataset_geometry(Path(objects), ids)
    found = outside_bin(state, hulls, BIN_TOLERANCE)
    if found is not None:
        index, reason, distance = found
        where = "past a wall of the bin" if reason == "outside_bin" else "below the bin's floor"
        raise ValueError(f"object {index} ('{ids[index]}') reaches {distance * 1000:.1f} mm {where} "
                         f"(tolerance {BIN_TOLERANCE * 1000:g} mm)")
    return plan_push(policy, state, hulls, centres, rng=np.random.default_rng(seed), config=config or PushConfig())


def _dataset_geometry(root: Path, ids: tuple[str, ...]) -> tuple[list[np.ndarray], np.ndarray]:
    """Hull vertices (V_i, 3) and centres of mass (n, 3), object frame, m, of ``ids`` from a
    dataset's objects table (the rows the service's served hulls are made of)."""
    table = Dataset.open(root).table("objects", ["object_id", "com_x", "com_y", "com_z", "hull_vertices"]).to_pylist()
    rows = {r["object_id"]: r for r in table}
    missing = sorted(set(ids) - set(rows))
    if missing:
        raise ValueError(f"{root}: no object {', '.join(map(repr, missing))} in the dataset")
    hulls = {i: np.asarray(rows[i]["hull_vertices"], dtype=np.float64).reshape(-1, 3) for i in set(ids)}
    centres = [[rows[i]["com_x"], rows[i]["com_y"], rows[i]["com_z"]] for i in ids]
    return [hulls[i] for i in ids], np.array(centres, dtype=np.float64)


__all__ = list(_PUBLIC)
