"""A heap in pybullet: drop objects into the bin, push one with a finger, pick one out.

Every call builds its world from a ``HeapState`` in a fresh ``resetSimulation`` (so a result
depends only on its inputs, never on what the process simulated before) and returns the
``HeapState`` once every object is at rest (or the time cap is reached).

Simulation choices, and why (docs/HEAPS.md has more):

* Objects collide as their convex hulls (``GEOM_MESH`` without the concave flag): an
  approximation.  A mug's inside or a hook's gap is filled, so hulls stack and interlock
  less than the real meshes; the grasp checks (``pipeline.heaps.grasps``) use the full meshes.
* Mass properties from the model: uniform density scaled to the corpus mass, about the
  model's centre of mass (``pipeline.heaps.objects.heap_object``).
* One friction coefficient per heap (``SimConfig.object_friction``); Bullet multiplies the two
  bodies' coefficients, so the bin and the finger get 1 and each object mu.
* The finger is a dynamic vertical cylinder dragged along the push by a fixed constraint
  (``finger_max_force``), as the push player does; it does not collide with the floor.
* Objects that leave the bin (over a wall, or through it) are dropped from the state.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from clutter.state import Bin, HeapState, Push

from .config import GRAVITY, HeapConfig
from .objects import HeapObject, ObjectLibrary, default_library
from .seeds import heap_stream

OUTSIDE_TOLERANCE = 0.01
"""m, how far past a wall's inner face (or below the floor) an object's centre of mass may be
before it counts as out of the bin (a resting centre is never that close to a wall)."""
FINGER_MASS = 0.1
"""kg; the finger is dynamic but its constraint is far stronger than any object's resistance."""


def library_for(config: HeapConfig, library: ObjectLibrary | None) -> ObjectLibrary:
    return library if library is not None else default_library(config.sim.max_object_extent)


def heap_friction(seed: int, heap: int, config: HeapConfig) -> float:
    """The heap's friction coefficient, uniform in ``config.sim.object_friction``."""
    low, high = config.sim.object_friction
    return float(heap_stream(seed, heap, "friction").uniform(low, high))


# ---------------------------------------------------------------- frames


def link_pose(obj: HeapObject, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pybullet base (link frame at the centre of mass) for an object transform.

    transform : (4, 4) float, object -> world
    returns : position (3,) m; rotation (3, 3), link -> world
    """
    position = transform[:3, :3] @ obj.model.center_mass + transform[:3, 3]
    return position, transform[:3, :3] @ obj.link_from_object.T


def object_transform(obj: HeapObject, position: np.ndarray, world_from_link: np.ndarray) -> np.ndarray:
    """(4, 4) object -> world from pybullet's base position (m) and rotation (3, 3)."""
    rotation = world_from_link @ obj.link_from_object
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(position) - rotation @ obj.model.center_mass
    return transform


# ---------------------------------------------------------------- the pybullet world


_CLIENTS: dict[int, int] = {}


def _client():
    """pybullet and this process's DIRECT client (a forked worker gets its own)."""
    import pybullet as pb

    pid = os.getpid()
    if pid not in _CLIENTS or not pb.isConnected(_CLIENTS[pid]):
        _CLIENTS[pid] = pb.connect(pb.DIRECT)
    return pb, _CLIENTS[pid]


@dataclass
class World:
    """A built pybullet scene: the client, the bin's bodies and one body per object."""

    pb: object
    client: int
    floor: int
    bodies: list[int]
    objects: list[HeapObject]


def bin_boxes(bin: Bin) -> list[tuple[np.ndarray, np.ndarray]]:
    """The bin as five boxes: floor (top face at z = 0) and four walls around the inner floor.

    returns : [(centre (3,), half extents (3,))], m; the floor first
    """
    hx, hy = bin.half_extents
    w, h = bin.wall, bin.height
    return [
        (np.array([0.0, 0.0, -w / 2]), np.array([hx + w, hy + w, w / 2])),
        (np.array([hx + w / 2, 0.0, h / 2]), np.array([w / 2, hy + w, h / 2])),
        (np.array([-hx - w / 2, 0.0, h / 2]), np.array([w / 2, hy + w, h / 2])),
        (np.array([0.0, hy + w / 2, h / 2]), np.array([hx + w, w / 2, h / 2])),
        (np.array([0.0, -hy - w / 2, h / 2]), np.array([hx + w, w / 2, h / 2])),
    ]


def build_world(
    objects: list[HeapObject], transforms: np.ndarray, friction: float, config: HeapConfig
) -> World:
    """Empty the simulation and build the bin and the objects at ``transforms`` ((n, 4, 4), object -> world)."""
    pb, client = _client()
    sim = config.sim
    pb.resetSimulation(physicsClientId=client)
    pb.setGravity(0, 0, -GRAVITY, physicsClientId=client)
    pb.setPhysicsEngineParameter(
        fixedTimeStep=sim.time_step, numSolverIterations=sim.solver_iterations, physicsClientId=client
    )
    parts = bin_boxes(config.bin)
    floor = -1
    for k, (centre, half) in enumerate(parts):
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client)
        body = pb.createMultiBody(0, shape, basePosition=centre.tolist(), physicsClientId=client)
        pb.changeDynamics(body, -1, lateralFriction=1.0, physicsClientId=client)
        if k == 0:
            floor = body
    bodies = []
    for obj, transform in zip(objects, transforms):
        position, rotation = link_pose(obj, transform)
        shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=obj.hull_link.tolist(), physicsClientId=client)
        body = pb.createMultiBody(
            obj.model.mass, shape, basePosition=position.tolist(),
            baseOrientation=Rotation.from_matrix(rotation).as_quat().tolist(), physicsClientId=client,
        )
        pb.changeDynamics(
            body, -1, lateralFriction=friction, localInertiaDiagonal=obj.inertia.tolist(),
            collisionMargin=sim.collision_margin, physicsClientId=client,
        )
        bodies.append(body)
    return World(pb, client, floor, bodies, list(objects))


def settle(world: World, max_time: float, config: HeapConfig) -> tuple[bool, int]:
    """Step until every object is at rest for ``rest_steps`` steps, or ``max_time`` s.

    returns : (came to rest, steps taken)
    """
    pb, client, sim = world.pb, world.client, config.sim
    still, steps = 0, 0
    for steps in range(1, round(max_time / sim.time_step) + 1):
        pb.stepSimulation(physicsClientId=client)
        moving = False
        for body in world.bodies:
            linear, angular = pb.getBaseVelocity(body, physicsClientId=client)
            if linear[0] ** 2 + linear[1] ** 2 + linear[2] ** 2 > sim.rest_speed**2 or (
                angular[0] ** 2 + angular[1] ** 2 + angular[2] ** 2 > sim.rest_spin**2
            ):
                moving = True
                break
        still = 0 if moving else still + 1
        if still >= sim.rest_steps:
            return True, steps
    return False, steps


def observe(world: World, ids: tuple[str, ...], bin: Bin) -> HeapState:
    """The heap as it is now, without the objects that left the bin."""
    pb, client = world.pb, world.client
    keep, poses = [], []
    limit = np.append(bin.half_extents + OUTSIDE_TOLERANCE, -OUTSIDE_TOLERANCE)
    for k, (body, obj) in enumerate(zip(world.bodies, world.objects)):
        position, quaternion = pb.getBasePositionAndOrientation(body, physicsClientId=client)
        if np.any(np.abs(position[:2]) > limit[:2]) or position[2] < limit[2]:
            continue
        rotation = np.array(pb.getMatrixFromQuaternion(quaternion)).reshape(3, 3)
        keep.append(k)
        poses.append(object_transform(obj, np.array(position), rotation))
    return HeapState(bin, tuple(ids[k] for k in keep), np.array(poses).reshape(len(keep), 4, 4))


# ---------------------------------------------------------------- drop


def drop_poses(
    objects: list[HeapObject], bin: Bin, clearance: float, spread: float, rng: np.random.Generator
) -> np.ndarray:
    """Random start poses above the bin: uniform rotation; centre of mass normal about a heap
    centre (uniform over the middle half of the floor) with std ``spread``, clipped to keep one
    bounding radius from the walls; stacked so that no two bounding spheres overlap.

    returns : (n, 4, 4) float, object -> world
    """
    n = len(objects)
    rotations = Rotation.random(n, random_state=rng).as_matrix().reshape(n, 3, 3)
    middle = (2 * rng.random(2) - 1) * bin.half_extents / 2
    offsets = rng.normal(0.0, spread, (n, 2))
    centres = np.zeros((n, 3))
    for k, obj in enumerate(objects):
        room = np.maximum(bin.half_extents - obj.radius, 0.0)
        centres[k, :2] = np.clip(middle + offsets[k], -room, room)
        z = bin.height + obj.radius + clearance
        for j in range(k):  # above every earlier sphere it would overlap in plan
            if np.linalg.norm(centres[j, :2] - centres[k, :2]) < objects[j].radius + obj.radius + clearance:
                z = max(z, centres[j, 2] + objects[j].radius + obj.radius + clearance)
        centres[k, 2] = z
    transforms = np.tile(np.eye(4), (n, 1, 1))
    for k, obj in enumerate(objects):
        # The centre of mass goes to the sampled centre.
        transforms[k, :3, :3] = rotations[k]
        transforms[k, :3, 3] = centres[k] - rotations[k] @ obj.model.center_mass
    return transforms


def drop_heap(
    seed: int, config: HeapConfig, heap: int = 0, library: ObjectLibrary | None = None
) -> HeapState:
    """Drop 2-10 random corpus objects into the bin and let them settle.

    seed : experiment seed;  heap : heap number.  The same (seed, heap, config, library) gives
    the same heap: every draw comes from ``heap_stream(seed, heap, "drop")``.
    returns : the heap at rest (objects that bounced out of the bin are not in it)
    """
    library = library_for(config, library)
    rng = heap_stream(seed, heap, "drop")
    ids = library.ids()
    if not ids:
        raise ValueError("the object library offers no objects small enough for the bin")
    n = int(rng.integers(config.min_objects, config.max_objects + 1))
    chosen = tuple(ids[i] for i in rng.integers(0, len(ids), n))
    objects = [library[k] for k in chosen]
    transforms = drop_poses(objects, config.bin, config.sim.drop_clearance, config.sim.drop_spread, rng)
    world = build_world(objects, transforms, heap_friction(seed, heap, config), config)
    settle(world, config.sim.settle_time, config)
    return observe(world, chosen, config.bin)


def settle_state(
    state: HeapState, config: HeapConfig, friction: float, library: ObjectLibrary | None = None,
    max_time: float | None = None,
) -> HeapState:
    """Place the heap as it is and let it come to rest (``resettle_time`` s at most)."""
    library = library_for(config, library)
    world = build_world([library[k] for k in state.object_ids], state.poses, friction, config)
    settle(world, config.sim.resettle_time if max_time is None else max_time, config)
    return observe(world, state.object_ids, state.bin)


def remove_object(
    state: HeapState, index: int, config: HeapConfig, friction: float, library: ObjectLibrary | None = None
) -> HeapState:
    """The heap after object ``index`` is picked out and the rest have settled."""
    if not 0 <= index < len(state):
        raise IndexError(f"object index {index} out of range for a heap of {len(state)}")
    return settle_state(state.without(index), config, friction, library)


# ---------------------------------------------------------------- push


def finger_path(push: Push, config: HeapConfig) -> np.ndarray:
    """Centres of the finger cylinder along the push at ``finger_speed`` (its tip on the push line).

    returns : (steps, 3) float, m, world frame
    """
    sim = config.sim
    start, end = np.asarray(push.start, dtype=float), np.asarray(push.end, dtype=float)
    steps = max(2, int(np.ceil(push.length / sim.finger_speed / sim.time_step)))
    s = np.linspace(0.0, 1.0, steps)[:, None]
    return start + s * (end - start) + np.array([0.0, 0.0, sim.finger_height / 2])


def execute_push(
    state: HeapState, push: Push, config: HeapConfig, friction: float | None = None,
    library: ObjectLibrary | None = None,
) -> HeapState:
    """Drive the finger from ``push.start`` to ``push.end``, withdraw it, and let the heap settle.

    friction : the heap's coefficient (``heap_friction``); the middle of the range when None
    returns : the heap at rest after the push
    """
    library = library_for(config, library)
    sim = config.sim
    start, end = np.asarray(push.start, dtype=float), np.asarray(push.end, dtype=float)
    if start.shape != (3,) or end.shape != (3,) or not (np.all(np.isfinite(start)) and np.all(np.isfinite(end))):
        raise ValueError("push start and end must be finite (3,) points")
    if friction is None:
        friction = float(np.mean(sim.object_friction))
    world = build_world([library[k] for k in state.object_ids], state.poses, friction, config)
    pb, client = world.pb, world.client
    path = finger_path(push, config)
    shape = pb.createCollisionShape(
        pb.GEOM_CYLINDER, radius=sim.finger_radius, height=sim.finger_height, physicsClientId=client
    )
    finger = pb.createMultiBody(FINGER_MASS, shape, basePosition=path[0].tolist(), physicsClientId=client)
    pb.changeDynamics(finger, -1, lateralFriction=1.0, physicsClientId=client)
    pb.setCollisionFilterPair(finger, world.floor, -1, -1, 0, physicsClientId=client)
    grip = pb.createConstraint(
        finger, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], path[0].tolist(), physicsClientId=client
    )
    for target in path:
        pb.changeConstraint(grip, target.tolist(), maxForce=sim.finger_max_force, physicsClientId=client)
        pb.stepSimulation(physicsClientId=client)
    pb.removeConstraint(grip, physicsClientId=client)
    pb.removeBody(finger, physicsClientId=client)
    settle(world, sim.resettle_time, config)
    return observe(world, state.object_ids, state.bin)
