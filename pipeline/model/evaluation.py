"""One object, end to end: the unit of work the dataset job fans out.

load + validate -> stable poses -> per pose: candidate pushes, toppling model,
suction quality -> value iteration and policies.  Every random draw comes from a
stream of (seed, object id, pose), so the result does not depend on which worker
runs it.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Iterator, Protocol

import numpy as np

from schema.frames import transform_points
from schema.vocabulary import STATUS_NAMES

from .collision import collision_object
from .config import Config
from .contacts import explicit_actions, object_contacts, pose_actions
from .mdp import pose_values
from .mesh import ObjectModel, load_mesh
from .outcomes import Actions, ObjectResult, StablePose, SuctionResult, ToppleTable
from .poses import PoseSet, stable_poses
from .rng import stream
from .suction import suction_quality
from .topple import evaluate_pose


class Spec(Protocol):
    """What the job needs to know of a corpus entry (``pipeline.build.corpus.ObjectSpec``)."""

    object_id: str
    path: str
    scale: float
    mass: float


@contextmanager
def _stage(timings: dict[str, float], name: str) -> Iterator[None]:
    start = time.process_time()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.process_time() - start


def load_object(spec: Spec, config: Config) -> ObjectModel:
    """The spec's mesh, validated; raises ``MeshError`` with a one-line reason."""
    return load_mesh(spec.path, scale=spec.scale, mass=spec.mass, name=spec.object_id, config=config.mesh)


def pose_suction(obj: ObjectModel, pose: StablePose, config: Config) -> SuctionResult:
    """V_s and the best suction grasp of one pose (pose frame)."""
    mesh = obj.mesh.copy()
    mesh.apply_transform(pose.transform)
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    rng = stream(config.seed, obj.name, pose.index, "suction")
    return suction_quality(mesh, center_mass, obj.mass, config.suction, rng, config.topple.gravity)


def process_object(spec: Spec, config: Config) -> ObjectResult:
    """Evaluate every stable pose of one corpus object (CPU seconds per stage in ``timings``)."""
    timings: dict[str, float] = {}
    with _stage(timings, "load"):
        obj = load_object(spec, config)
    with _stage(timings, "poses"):
        pose_set = stable_poses(obj, config.poses)
    poses = pose_set.poses
    with _stage(timings, "contacts"):
        points, normals = object_contacts(obj, config.contacts, config.seed)
        mesh_collision = collision_object(obj.mesh)
        actions = [pose_actions(points, normals, obj.mesh, mesh_collision, p.transform, config.contacts) for p in poses]
    with _stage(timings, "topple"):
        tables = [
            evaluate_pose(obj, p, len(poses), a, config.topple, stream(config.seed, obj.name, p.index, "trials"))
            for p, a in zip(poses, actions)
        ]
    with _stage(timings, "suction"):
        suction = [pose_suction(obj, p, config) for p in poses]
    with _stage(timings, "mdp"):
        values = pose_values(
            [t.next_pose for t in tables],
            np.array([s.quality for s in suction]),
            [a.max_height for a in actions],
            config.mdp,
        )
    return ObjectResult(
        object_id=spec.object_id,
        mass=obj.mass,
        center_mass=obj.center_mass,
        hull_vertices=np.asarray(obj.hull.vertices),
        hull_faces=np.asarray(obj.hull.faces),
        repairs=obj.repairs,
        poses=poses,
        actions=actions,
        topple=tables,
        suction=suction,
        values=values,
        timings=timings,
    )


def select_info(spec: Spec, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """What the thesis 4.4.1 selection rule needs: V_s and COM height of every pose.

    returns : v_s (P,) float, com_heights (P,) float, m
    """
    obj = load_object(spec, config)
    poses = stable_poses(obj, config.poses).poses
    return (
        np.array([pose_suction(obj, p, config).quality for p in poses]),
        np.array([p.com_height for p in poses]),
    )


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
