"""The small public Python API: load a mesh, list its stable poses, evaluate a pose.

    import pipeline as toppledb
    obj = toppledb.load_mesh("duck.obj", scale=0.01, mass=0.1)
    poses = toppledb.stable_poses(obj)
    result = toppledb.evaluate(obj, poses, pose=0, n_contacts=200, n_trials=50)
    result.transitions()   # [(action, next_pose, probability), ...]
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import trimesh

from .config import Config, ContactConfig
from .contacts import collision_object, pose_actions, surface_points
from .frames import transform_points, unit
from .mesh import ObjectModel
from .poses import PoseSet
from .results import STATUS_NAMES, STATUS_OK, Actions, ToppleTable
from .rng import stream
from .topple import evaluate_pose


@dataclass
class PoseEvaluation:
    """Candidate pushes of one pose and what the toppling model says of them."""

    pose: int
    actions: Actions
    table: ToppleTable

    def transitions(self) -> list[tuple[int, int, float]]:
        """Long form (action, next_pose, probability) over ``ok`` actions, nonzero probabilities only."""
        rows, cols = np.nonzero(np.nan_to_num(self.table.next_pose) > 0)
        return [(int(a), int(x), float(self.table.next_pose[a, x])) for a, x in zip(rows, cols)]

    def status_names(self) -> list[str]:
        return [STATUS_NAMES[s] for s in self.actions.status]


def object_contacts(obj: ObjectModel, config: ContactConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The object's candidate contact points and normals (object frame), shared by its poses."""
    return surface_points(obj.mesh, config.n_contacts, stream(seed, obj.name, -1, "contacts"), config.oversample)


def explicit_actions(obj: ObjectModel, transform: np.ndarray, points: np.ndarray, directions: np.ndarray | None) -> Actions:
    """Actions at caller-chosen contact points (pose frame); all are evaluated (status ``ok``).

    points : (A, 3) float, m, pose frame, on or near the surface (snapped to the closest surface point)
    directions : (A, 3) float, pose frame, push directions; the inward normal when None
    """
    to_object = np.linalg.inv(transform)
    closest, _, faces = trimesh.proximity.closest_point(obj.mesh, transform_points(to_object, np.atleast_2d(points)))
    normals = obj.mesh.face_normals[faces] @ transform[:3, :3].T
    points = transform_points(transform, closest)
    directions = -normals if directions is None else unit(np.atleast_2d(np.asarray(directions, dtype=float)))
    return Actions(points, normals, directions, np.full(len(points), STATUS_OK, dtype=np.int8), max_height=-1)


def evaluate(
    obj: ObjectModel,
    poses: PoseSet,
    pose: int,
    *,
    points: np.ndarray | None = None,
    directions: np.ndarray | None = None,
    n_contacts: int | None = None,
    n_trials: int | None = None,
    variant: str | None = None,
    seed: int = 0,
    config: Config = Config(),
) -> PoseEvaluation:
    """Evaluate the toppling model on one stable pose.

    points, directions : optional explicit pushes, (A, 3) pose frame; otherwise the
      pose's ``n_contacts`` candidates plus the Max-Height action
    n_contacts, n_trials, variant : override ``config.contacts`` / ``config.topple``
    seed : root of the random streams (same seed, same result)
    """
    contact_config = config.contacts if n_contacts is None else replace(config.contacts, n_contacts=n_contacts)
    topple_config = config.topple
    if n_trials is not None or variant is not None:
        topple_config = replace(
            topple_config,
            n_trials=topple_config.n_trials if n_trials is None else n_trials,
            variant=topple_config.variant if variant is None else variant,
        )
    stable = poses.poses[pose]
    if points is not None:
        actions = explicit_actions(obj, stable.transform, points, directions)
    else:
        contacts, normals = object_contacts(obj, contact_config, seed)
        actions = pose_actions(contacts, normals, obj.mesh, collision_object(obj.mesh), stable.transform, contact_config)
    table = evaluate_pose(obj, stable, len(poses.poses), actions, topple_config, stream(seed, obj.name, pose, "trials"))
    return PoseEvaluation(pose=pose, actions=actions, table=table)

