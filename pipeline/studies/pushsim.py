"""A push player in pybullet: one candidate push of one stable pose, played in a
physics engine, and the stable pose the object comes to rest in.

The object's convex hull rests on a plane in the canonical transform of a stable
pose (pose frame == world frame, z up, table z = 0); a small sphere finger, held by
a stiff constraint, moves slowly along the action's line, then is withdrawn; once
the object has come to rest its orientation is settled into a stable pose with
``pipeline.model.poses.settle``.

Simulation choices, and why:

* Convex hull collision shape: the model is quasi-static on the hull, and pybullet's
  ``GEOM_MESH`` without the concave flag is a convex hull anyway.
* Mass properties from trimesh (uniform density), scaled to the object's mass, about the
  object's centre of mass; the link frame is the principal frame so the inertia is diagonal.
* Friction: Bullet multiplies the two bodies' coefficients, so the plane has 1, the object
  mu_T and the finger mu_f / mu_T; the object-table pair then has mu_T, the finger-object pair mu_f.
* Noise: friction coefficients, contact point and push direction, with ``config.topple``'s
  standard deviations.  The model's object-rotation noise is not applied: a rotated object
  is not at rest, and the engine's own pose is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schema.frames import transform_points, unit

from ..model.config import Config
from ..model.mesh import ObjectModel
from ..model.poses import PoseSet, settle

TIME_STEP = 1.0 / 240.0
"""s, simulation step."""
FINGER_SPEED = 0.05
"""m/s; slow enough to be close to quasi-static."""
FINGER_MASS = 0.05
"""kg; the finger is dynamic but held by a constraint far stronger than any push."""
FINGER_MAX_FORCE = 200.0
"""N, strength of the constraint that drags the finger along its path."""
SETTLE_TIME = 1.5
"""s, most simulated time after the push for the object to come to rest."""
REST_SPEED = 2e-3
"""m/s and rad/s; below both for REST_STEPS steps in a row counts as at rest."""
REST_STEPS = 24
MIN_FRICTION = 0.05
"""Noisy friction coefficients are clipped here: Bullet treats 0 as frictionless, a noisy draw below 0 as nonsense."""
OUTSIDE = -1
"""Next-pose bucket for a rest pose outside the pose set (``settle`` returned -1)."""


# ---------------------------------------------------------------- rigid body description


@dataclass
class BodyModel:
    """What pybullet needs of an object, computed once per object.

    vertices : (V, 3) float, m, hull vertices in the link frame (principal frame at the centre of mass)
    inertia : (3,) float, kg m^2, principal moments
    link_from_object : (3, 3) float, rotation object frame -> link frame
    center_mass : (3,) float, m, object frame
    mass : float, kg
    """

    vertices: np.ndarray
    inertia: np.ndarray
    link_from_object: np.ndarray
    center_mass: np.ndarray
    mass: float


def body_model(obj: ObjectModel) -> BodyModel:
    """Hull in the principal frame at the centre of mass, and the principal moments of inertia.

    Inertia is that of the uniform-density mesh (the hull if the mesh has no positive volume),
    scaled to ``obj.mass`` and moved to ``obj.center_mass`` by the parallel axis theorem.
    """
    solid = obj.mesh if obj.mesh.is_volume and obj.mesh.volume > 0 else obj.hull
    scale = obj.mass / solid.mass
    offset = obj.center_mass - solid.center_mass
    inertia = solid.moment_inertia * scale + obj.mass * (np.dot(offset, offset) * np.eye(3) - np.outer(offset, offset))
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:  # a proper rotation, so the link frame is right-handed
        axes[:, 2] *= -1
    link_from_object = axes.T
    vertices = (obj.hull.vertices - obj.center_mass) @ link_from_object.T
    return BodyModel(vertices, np.maximum(moments, 1e-12), link_from_object, obj.center_mass.copy(), float(obj.mass))


def _quaternion(rotation: np.ndarray) -> list[float]:
    """(3, 3) rotation -> pybullet quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat().tolist()


# ---------------------------------------------------------------- one simulated push


@dataclass
class PushNoise:
    """One push's perturbation (zeros and means when noise-free).

    mu_table, mu_finger : float;  contact_offset : (3,) float, m;  direction_offset : (3,) float
    """

    mu_table: float
    mu_finger: float
    contact_offset: np.ndarray
    direction_offset: np.ndarray


def draw_noise(config: Config, rng: np.random.Generator | None, noise: bool) -> PushNoise:
    """The same kinds of noise as the model's trials, from ``config.topple``'s distributions."""
    t = config.topple
    if not noise:
        return PushNoise(t.mu_table_mean, t.mu_finger_mean, np.zeros(3), np.zeros(3))
    if rng is None:
        raise ValueError("a noisy push needs an rng (or noise=False)")
    return PushNoise(
        mu_table=float(max(rng.normal(t.mu_table_mean, t.mu_table_std), MIN_FRICTION)),
        mu_finger=float(max(rng.normal(t.mu_finger_mean, t.mu_finger_std), MIN_FRICTION)),
        contact_offset=rng.normal(0.0, t.contact_std, 3),
        direction_offset=rng.normal(0.0, t.direction_std, 3),
    )


def finger_path(point: np.ndarray, direction: np.ndarray, config: Config, n_steps: int) -> np.ndarray:
    """Centres of the finger sphere along the push, world frame.

    The fingertip (the sphere's leading point) runs from ``approach_offset`` before the
    contact to ``push_depth`` past it along the push direction, the line of the action.

    point : (3,) float, m;  direction : (3,) float, unit
    returns : (n_steps, 3) float, m
    """
    c = config.contacts
    s = np.linspace(-c.approach_offset, c.push_depth, n_steps)
    return point + s[:, None] * direction - c.finger_radius * direction


def simulate_push(
    obj: ObjectModel,
    pose_set: PoseSet,
    pose_index: int,
    point: np.ndarray,
    direction: np.ndarray,
    config: Config = Config(),
    rng: np.random.Generator | None = None,
    noise: bool = True,
    body: BodyModel | None = None,
) -> int:
    """Push the object in one of its stable poses in pybullet; the pose it comes to rest in.

    point : (3,) float, m, contact point, pose frame (== world frame: the object starts in
      the pose's canonical transform)
    direction : (3,) float, push direction, pose frame (normalised here)
    rng : draws the noise when ``noise`` is True
    body : ``body_model(obj)``, to reuse across pushes of one object
    returns : int, index into ``pose_set.poses``, or ``OUTSIDE`` (-1) for a rest pose left
      out of the set
    """
    import pybullet as pb

    body = body or body_model(obj)
    draws = draw_noise(config, rng, noise)
    point = np.asarray(point, dtype=float) + draws.contact_offset
    direction = unit(np.asarray(direction, dtype=float) + draws.direction_offset)

    client = pb.connect(pb.DIRECT)
    try:
        rotation = _run(pb, client, body, pose_set.poses[pose_index].transform, point, direction, draws, config)
    finally:
        pb.disconnect(client)
    return settle(pose_set, obj, rotation)


def _run(pb, client, body: BodyModel, transform, point, direction, draws: PushNoise, config: Config) -> np.ndarray:
    """Build the scene, push, withdraw, wait for rest; the object's final rotation (object -> world)."""
    pb.setGravity(0, 0, -config.topple.gravity, physicsClientId=client)
    pb.setPhysicsEngineParameter(fixedTimeStep=TIME_STEP, numSolverIterations=50, physicsClientId=client)

    plane = pb.createMultiBody(0, pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client), physicsClientId=client)
    pb.changeDynamics(plane, -1, lateralFriction=1.0, physicsClientId=client)

    world_from_link = transform[:3, :3] @ body.link_from_object.T
    start = transform_points(transform, body.center_mass[None])[0]
    shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=body.vertices.tolist(), physicsClientId=client)
    obj_id = pb.createMultiBody(
        body.mass, shape, basePosition=start.tolist(), baseOrientation=_quaternion(world_from_link), physicsClientId=client
    )
    pb.changeDynamics(
        obj_id,
        -1,
        lateralFriction=draws.mu_table,
        localInertiaDiagonal=body.inertia.tolist(),
        rollingFriction=0.0,
        spinningFriction=0.0,
        physicsClientId=client,
    )
    # Bullet's collision margin lifts a convex hull slightly; let it find its rest first.
    for _ in range(48):
        pb.stepSimulation(physicsClientId=client)

    path = finger_path(point, direction, config, max(2, int(round((config.contacts.approach_offset + config.contacts.push_depth) / FINGER_SPEED / TIME_STEP))))
    sphere = pb.createCollisionShape(pb.GEOM_SPHERE, radius=config.contacts.finger_radius, physicsClientId=client)
    finger = pb.createMultiBody(FINGER_MASS, sphere, basePosition=path[0].tolist(), physicsClientId=client)
    pb.changeDynamics(finger, -1, lateralFriction=draws.mu_finger / draws.mu_table, physicsClientId=client)
    pb.setCollisionFilterPair(finger, plane, -1, -1, 0, physicsClientId=client)
    grip = pb.createConstraint(finger, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], path[0].tolist(), physicsClientId=client)
    for target in path:
        pb.changeConstraint(grip, target.tolist(), maxForce=FINGER_MAX_FORCE, physicsClientId=client)
        pb.stepSimulation(physicsClientId=client)

    # Withdraw the finger so it neither props the object up nor pushes it further.
    pb.removeConstraint(grip, physicsClientId=client)
    pb.removeBody(finger, physicsClientId=client)
    still = 0
    for _ in range(int(SETTLE_TIME / TIME_STEP)):
        pb.stepSimulation(physicsClientId=client)
        linear, angular = pb.getBaseVelocity(obj_id, physicsClientId=client)
        still = still + 1 if max(np.linalg.norm(linear), np.linalg.norm(angular)) < REST_SPEED else 0
        if still >= REST_STEPS:
            break
    _, quaternion = pb.getBasePositionAndOrientation(obj_id, physicsClientId=client)
    world_from_link = np.array(pb.getMatrixFromQuaternion(quaternion)).reshape(3, 3)
    # Still moving at the time cap: ``settle`` follows the hull's topple graph from here.
    return world_from_link @ body.link_from_object


def empirical_distribution(outcomes: np.ndarray, n_poses: int) -> np.ndarray:
    """Next-pose frequencies from simulated outcomes.

    outcomes : (R,) int, pose indices or ``OUTSIDE``
    returns : (n_poses + 1,) float, the last bucket is ``OUTSIDE``; sums to 1
    """
    buckets = np.where(np.asarray(outcomes) < 0, n_poses, outcomes)
    return np.bincount(buckets, minlength=n_poses + 1) / len(outcomes)
