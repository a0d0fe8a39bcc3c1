"""One object, end to end: the unit of work the dataset job fans out.

load + validate -> stable poses -> per pose: candidate pushes, toppling model,
suction quality -> value iteration and policies.  Every random draw comes from a
stream of (seed, object id, pose), so the result does not depend on which worker
runs it.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator, Protocol

import numpy as np

from .api import object_contacts
from .config import Config
from .contacts import collision_object, pose_actions
from .frames import transform_points
from .mdp import pose_values
from .mesh import ObjectModel, load_mesh
from .poses import stable_poses
from .results import ObjectResult, StablePose, SuctionResult
from .rng import stream
from .suction import suction_quality
from .topple import evaluate_pose


class Spec(Protocol):
    """What the job needs to know of a corpus entry (``pipeline.corpus.ObjectSpec``)."""

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
