"""The push player: one push of one object, played in pybullet, and the pose it comes to rest in.

``play_push`` places the object at a given transform (object -> world, table z = 0),
lets it come to rest, then drives a small sphere finger along the push: the
fingertip runs along the push direction, through the contact point, from
``approach_offset`` before it to ``push_depth`` past it, at ``FINGER_SPEED``.  The
finger is then withdrawn and the object left to come to rest.  It returns the
observed start and final transforms (4x4, object -> world), what a robot's camera
would log.  ``settle`` (``pipeline.model.poses``) turns a final transform into a
stable pose index; ``simulate_push`` does both for a push given in a pose frame.

Simulation choices, and why:

* Collision shape: the convex hull for a convex object; for a concave one (a closed mesh
  with under ``CONVEX_VOLUME_SHARE`` of its hull's volume) its convex parts from Bullet's
  V-HACD (``convex_parts``). The model pushes points on the mesh, and most of the corpus's
  objects are concave: 64 % of the corpus log's pushes touch the mesh more than 1 mm inside
  the hull (22 % more than 1 cm), where a hull-shaped object is met by the finger
  earlier, elsewhere. The object rests on its hull either way (its lowest points).
* Collision margin ``COLLISION_MARGIN`` (0.1 mm) instead of Bullet's 1 mm: Bullet
  inflates a convex hull by its margin, so with the default a resting object floats
  about 1 mm above the table (measured: 0.99 mm for a box and random_042), which
  lowers every push contact by a millimetre and changes where it meets the object.
  A small non-zero margin keeps Bullet's convex contact generation robust.
* Mass properties from the model (``body_model``): trimesh's uniform-density inertia,
  scaled to the object's mass, about the model's centre of mass; the link frame is the
  principal frame so the inertia is diagonal.
* Friction: Bullet multiplies the two bodies' coefficients, so the plane has 1, the object
  mu_T and the finger mu_f / mu_T; the object-table pair then has mu_T, the finger-object pair mu_f.
* Finger strength: the constraint that drags the finger is limited to
  ``topple.max_finger_force``, the force the model allows a push (docs/MODEL.md C.1).
  With a 200 N finger, pushes from above onto a face the object cannot move away from
  pressed 0.25 kg objects with 100-150 N until they slipped out over an edge (traced on
  corpus-log pushes the model gives P = 0): a push no arm of the model's class makes,
  and one the model, bounded at the same force, calls a failure (docs/VALIDATION.md).
  The bound is on the force's norm, as the model's (``finger_row_limit``; up to player
  version 4 Bullet clamped each world axis at 20 N, so a push at 45 degrees could press
  with 28 N, and the finger's own weight added 0.5 N from above).
* Noise: friction coefficients, contact point and push direction, with ``config.topple``'s
  distributions.  The model's object-rotation noise is not applied: a rotated object
  is not at rest, and the engine observes its own pose exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schema.frames import transform_points, unit

from ..model.config import Config
from ..model.mesh import ObjectModel
from ..model.momentum import inertia_per_mass
from ..model.poses import PoseSet, settle

DEFAULT_CONFIG = Config()
"""The parameters a push is played with when none are given (frozen, safe to share)."""
TIME_STEP = 1.0 / 240.0
"""s, simulation step."""
SOLVER_ITERATIONS = 50
"""Bullet constraint solver iterations per step (its default, 10, lets stacked contacts sag)."""
COLLISION_MARGIN = 1e-4
"""m, Bullet collision margin of the object's hull and of the table (see the module docstring)."""
TABLE_HALF_SIZE = 1.0
"""m, half the side of the table box (objects are at most 0.5 m and pushes move them centimetres)."""
FINGER_SPEED = 0.05
"""m/s; slow enough to be close to quasi-static."""
FINGER_MASS = 0.05
"""kg; the finger is dynamic and weightless (its weight is cancelled every step), dragged along
its path by a constraint whose force is at most ``topple.max_finger_force`` in norm
(``finger_row_limit``)."""
REST_BEFORE = 0.2
"""s the object is left on the table before the finger appears, so that its contacts have formed."""
SETTLE_TIME = 1.5
"""s, most simulated time after the push for the object to come to rest."""
REST_SPEED = 5e-3
"""m/s, speed of the centre of mass below which the object may be at rest."""
REST_SPIN = 2e-2
"""rad/s, angular speed below which the object may be at rest (Bullet lets a small hull creep at
about 1e-3 rad/s on the table; a 0.1 s window at this speed turns it by 0.1 degree)."""
REST_WINDOW = 0.1
"""s in a row below both speeds that count as at rest."""
CONVEX_VOLUME_SHARE = 0.98
"""A closed mesh with less than this share of its hull's volume is concave: it collides as
its convex parts (``convex_parts``), not as its hull."""
MIN_PART_DEPTH = 1e-4
"""m; a convex part whose clipped body holds no ball this deep is dropped (a sliver)."""
VHACD_RESOLUTION = 100_000
"""Voxels of Bullet's V-HACD decomposition (its default): about 2 mm cells for a 10 cm object."""
MIN_FRICTION = 0.05
"""Noisy friction coefficients are clipped here: Bullet treats 0 as frictionless, a noisy draw below 0 as nonsense."""
PLAYER_VERSION = "5"
"""Bumped whenever the player's physics changes, so that push logs made before are not resumed into."""


@dataclass(frozen=True)
class PlayerSettings:
    """The player's numerical settings: how Bullet integrates a push, not what the push is.

    time_step : float, s, one simulation step;  solver_iterations : int, Bullet's constraint
    solver iterations per step;  finger_speed : float, m/s, along the stroke

    The defaults are the player's (``TIME_STEP``, ``SOLVER_ITERATIONS``, ``FINGER_SPEED``) and
    every log is played with them. Others play the same pushes with the same noise draws, to
    measure how much the judge itself depends on its numerics (``toppledb play --time-step``,
    docs/VALIDATION.md, "The judge's own numerics"): a quasi-static world would not depend on the
    finger's speed, an exact integrator not on the step or the iterations.
    """

    time_step: float = TIME_STEP
    solver_iterations: int = SOLVER_ITERATIONS
    finger_speed: float = FINGER_SPEED

    def __post_init__(self):
        for name in ("time_step", "finger_speed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"player {name} must be a positive number, got {value!r}")
        if isinstance(self.solver_iterations, bool) or not isinstance(self.solver_iterations, int) or self.solver_iterations < 1:
            raise ValueError(f"player solver_iterations must be a positive integer, got {self.solver_iterations!r}")
        if self.time_step > REST_WINDOW:
            raise ValueError(f"player time_step must be at most {REST_WINDOW} s (the rest window), got {self.time_step}")

    @property
    def rest_steps(self) -> int:
        """Steps in a row at rest that make ``REST_WINDOW`` (24 at the default step)."""
        return max(1, round(REST_WINDOW / self.time_step))


DEFAULT_PLAYER = PlayerSettings()
"""The settings every log is played with."""


def add_player_options(parser) -> None:
    """``--time-step``, ``--solver-iterations`` and ``--finger-speed`` on an argparse parser, defaulting
    to ``DEFAULT_PLAYER`` (read back with ``player_from_args``)."""
    parser.add_argument("--time-step", type=float, default=DEFAULT_PLAYER.time_step, metavar="S",
                        help="the player's simulation step, s (default: 1/240): with the two options below, to "
                             "measure how much physics depends on its own numerics (docs/VALIDATION.md)")
    parser.add_argument("--solver-iterations", type=int, default=DEFAULT_PLAYER.solver_iterations, metavar="N",
                        help="Bullet's constraint solver iterations per step (default: %(default)s)")
    parser.add_argument("--finger-speed", type=float, default=DEFAULT_PLAYER.finger_speed, metavar="V",
                        help="the finger's speed along its stroke, m/s (default: %(default)s)")


def player_from_args(args) -> PlayerSettings:
    """The settings ``add_player_options``'s options give; raises ValueError naming a bad one."""
    return PlayerSettings(args.time_step, args.solver_iterations, args.finger_speed)


def player_parameters(settings: PlayerSettings = DEFAULT_PLAYER) -> dict:
    """The player's constants and ``settings``, for the parameters recorded with a push log."""
    return {
        "player_version": PLAYER_VERSION,
        "time_step": settings.time_step,
        "solver_iterations": settings.solver_iterations,
        "collision_margin": COLLISION_MARGIN,
        "table_half_size": TABLE_HALF_SIZE,
        "finger_speed": settings.finger_speed,
        "finger_mass": FINGER_MASS,
        "rest_before": REST_BEFORE,
        "settle_time": SETTLE_TIME,
        "rest_speed": REST_SPEED,
        "rest_spin": REST_SPIN,
        "rest_steps": settings.rest_steps,
        "min_friction": MIN_FRICTION,
        "convex_volume_share": CONVEX_VOLUME_SHARE,
        "vhacd_resolution": VHACD_RESOLUTION,
    }


# ---------------------------------------------------------------- rigid body description


@dataclass
class BodyModel:
    """What pybullet needs of an object, computed once per object.

    vertices : (V, 3) float, m, hull vertices in the link frame (principal frame at the centre of mass)
    inertia : (3,) float, kg m^2, principal moments
    link_from_object : (3, 3) float, rotation object frame -> link frame
    center_mass : (3,) float, m, object frame
    mass : float, kg
    parts : Wavefront OBJ text of the object's convex parts in the link frame (``convex_parts``),
      its collision shape; empty for a convex object, whose shape is the hull
    """

    vertices: np.ndarray
    inertia: np.ndarray
    link_from_object: np.ndarray
    center_mass: np.ndarray
    mass: float
    parts: str = ""


def body_model(obj: ObjectModel) -> BodyModel:
    """Hull in the principal frame at the centre of mass, and the principal moments of inertia.

    Inertia is that of the uniform-density mesh (the hull if the mesh has no positive volume),
    scaled to ``obj.mass`` and moved to ``obj.center_mass`` by the parallel axis theorem.
    """
    inertia = inertia_per_mass(obj.mesh, obj.hull, obj.center_mass, obj.mass)
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:  # a proper rotation, so the link frame is right-handed
        axes[:, 2] *= -1
    link_from_object = axes.T
    vertices = (obj.hull.vertices - obj.center_mass) @ link_from_object.T
    parts = ""
    if obj.mesh.is_volume and obj.mesh.volume < CONVEX_VOLUME_SHARE * obj.hull.volume:
        parts = convex_parts((obj.mesh.vertices - obj.center_mass) @ link_from_object.T, obj.mesh.faces, vertices)
    return BodyModel(vertices, np.maximum(moments, 1e-12), link_from_object, obj.center_mass.copy(), float(obj.mass), parts)


def convex_parts(vertices: np.ndarray, faces: np.ndarray, hull_vertices: np.ndarray) -> str:
    """Approximate convex decomposition of a closed mesh, as OBJ text for pybullet.

    vertices : (V, 3) float, m;  faces : (F, 3) int;  hull_vertices : (H, 3) float, m, its convex hull's
    returns : one ``o`` group (a convex polyhedron) per part; pybullet loads them as one compound shape

    A finger pushing into a concavity must meet the surface the model pushes; the hull
    would meet it earlier, elsewhere, and push a different object.  Bullet's V-HACD gives the
    parts; they are voxel-made and bulge up to a voxel past the surface, so each is cut back
    to the mesh's hull (``clip_to_hull``): the object then rests on exactly its hull's base,
    as the model's stable poses assume.
    """
    import os
    import tempfile

    import trimesh

    pb, client = _client()
    with tempfile.TemporaryDirectory() as folder:
        source, target = os.path.join(folder, "mesh.obj"), os.path.join(folder, "parts.obj")
        trimesh.Trimesh(vertices, faces, process=False).export(source)
        # V-HACD prints its progress on the process's stdout (C level): send it to a file.
        stdout = os.dup(1)
        with open(os.path.join(folder, "progress.log"), "w") as progress:
            os.dup2(progress.fileno(), 1)
            try:
                pb.vhacd(source, target, os.path.join(folder, "vhacd.log"), resolution=VHACD_RESOLUTION, physicsClientId=client)
            finally:
                os.dup2(stdout, 1)
                os.close(stdout)
        with open(target) as f:
            parts = _obj_groups(f.read())
    clipped = [clip_to_hull(part, hull_vertices) for part in parts]
    return _obj_text([part for part in clipped if part is not None])


def clip_to_hull(points: np.ndarray, hull_points: np.ndarray) -> np.ndarray | None:
    """Vertices of conv(points) intersected with conv(hull_points), or None if that is (nearly) empty.

    points, hull_points : (n, 3), (m, 3) float, m
    """
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

    try:
        halfspaces = np.vstack([ConvexHull(points).equations, ConvexHull(hull_points).equations])  # a.x + b <= 0
    except QhullError:
        return None
    # The point deepest inside both (Chebyshev centre) seeds the intersection.
    norms = np.linalg.norm(halfspaces[:, :3], axis=1)
    result = linprog(np.r_[0.0, 0.0, 0.0, -1.0], A_ub=np.column_stack([halfspaces[:, :3], norms]), b_ub=-halfspaces[:, 3],
                     bounds=[(None, None)] * 3 + [(0.0, None)])
    if not result.success or result.x[3] < MIN_PART_DEPTH:
        return None
    return HalfspaceIntersection(halfspaces, result.x[:3]).intersections


def _obj_groups(text: str) -> list[np.ndarray]:
    """The vertices of each ``o`` group of OBJ text: [(n_i, 3) float, ...]."""
    groups: list[list[list[float]]] = []
    for line in text.splitlines():
        if line.startswith("o "):
            groups.append([])
        elif line.startswith("v ") and groups:
            groups[-1].append([float(v) for v in line.split()[1:4]])
    return [np.array(g) for g in groups if len(g) >= 4]


def _obj_text(parts: list[np.ndarray]) -> str:
    """OBJ text with one ``o`` group per convex part (its hull's vertices and triangles)."""
    import trimesh

    lines, offset = [], 1
    for i, points in enumerate(parts):
        part = trimesh.convex.convex_hull(points)
        lines.append(f"o part_{i}")
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in part.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in part.faces]
        offset += len(part.vertices)
    return "\n".join(lines) + "\n"


def _quaternion(rotation: np.ndarray) -> list[float]:
    """(3, 3) rotation -> pybullet quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat().tolist()


def link_pose(body: BodyModel, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where pybullet's base (the link frame at the centre of mass) is for an object transform.

    transform : (4, 4) float, object -> world
    returns : position (3,) float, m; rotation (3, 3) float, link -> world
    """
    return transform_points(transform, body.center_mass[None])[0], transform[:3, :3] @ body.link_from_object.T


def object_transform(body: BodyModel, position: np.ndarray, world_from_link: np.ndarray) -> np.ndarray:
    """The object's transform (object -> world, (4, 4)) from pybullet's base position and rotation.

    An object point p is at position + world_from_link @ link_from_object @ (p - center_mass).
    """
    rotation = world_from_link @ body.link_from_object
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(position) - rotation @ body.center_mass
    return transform


# ---------------------------------------------------------------- one simulated push


@dataclass
class PushNoise:
    """One push's perturbation (zeros and means when noise-free).

    mu_table, mu_finger : float;  contact_offset : (3,) float, m, world frame;
    direction_offset : (3,) float, world frame, added to the unit direction
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


def finger_row_limit(force: np.ndarray, limit: float) -> float:
    """The per-row force limit that keeps the finger's constraint force within ``limit`` in norm.

    force : (3,) float, N, the constraint's linear force at the last step (world x, y, z)
    limit : float, N, the finger force limit (``topple.max_finger_force``, MODEL.md C.1)
    returns : float, N, the ``maxForce`` for the next step

    Bullet clamps each row of a fixed constraint (world x, y and z) at ``maxForce`` on its
    own: the force may reach sqrt(3) ``limit`` along a diagonal (28 N for a push at 45
    degrees, up to player version 4).  The model bounds the force's norm, so the box is
    scaled to pass through the sphere of radius ``limit`` in the force's direction.  It
    follows the last step's direction: where that jumps (a rocking contact) a single step
    can still overshoot (docs/VALIDATION.md, "Push player").
    """
    norm = float(np.linalg.norm(force))
    if not np.isfinite(norm) or norm <= 1e-9:  # no force yet (free flight): no direction to scale by
        return float(limit)
    return float(limit) * float(np.max(np.abs(force))) / norm


def finger_steps(config: Config, settings: PlayerSettings = DEFAULT_PLAYER) -> int:
    """Simulation steps of the finger's stroke at ``settings.finger_speed``."""
    stroke = config.contacts.approach_offset + config.contacts.push_depth
    return max(2, round(stroke / settings.finger_speed / settings.time_step))


@dataclass
class PlayedPush:
    """What a played push observed.

    start_transform : (4, 4) float, object -> world once at rest, before the finger came
    final_transform : (4, 4) float, object -> world after the push, once at rest (or at the time cap)
    at_rest : bool, the object came to rest before ``SETTLE_TIME`` ran out
    point, direction : (3,) float, world frame, the push as executed (noise included)
    noise : the draws it was played with
    peak_force : float, N, the largest normal force the finger pressed on the object with
      (summed over its contact points, per simulation step)
    """

    start_transform: np.ndarray
    final_transform: np.ndarray
    at_rest: bool
    point: np.ndarray
    direction: np.ndarray
    noise: PushNoise
    peak_force: float = 0.0


def play_push(
    body: BodyModel,
    transform: np.ndarray,
    point: np.ndarray,
    direction: np.ndarray,
    config: Config = DEFAULT_CONFIG,
    noise: PushNoise | None = None,
    observe=None,
    settings: PlayerSettings = DEFAULT_PLAYER,
) -> PlayedPush:
    """Play one push of an object placed at ``transform`` on the table.

    body : ``body_model(obj)``
    transform : (4, 4) float, object -> world where the object is placed (resting on z = 0)
    point : (3,) float, m, contact point, object frame
    direction : (3,) float, push direction, object frame (normalised here)
    noise : the push's perturbation (``draw_noise``); noise-free at the config's means when None
    observe : called after every step of the finger's stroke as ``observe(pb, client, pushed, pressing)``
      (the object's body id, and the normal force in N the finger pressed it with at that step), to trace
      the push (``push_course``); it must only read
    settings : the player's numerics (``PlayerSettings``; every log is played with the default)

    The push is mapped to the world through the object's transform observed once it
    has come to rest, as a robot maps a planned push through the pose it sees.
    """
    noise = noise or draw_noise(config, None, noise=False)
    pb, client = _client()
    table, obj_id = _place(pb, client, body, transform, noise.mu_table, config, settings=settings)
    start = _observe(pb, client, obj_id, body)

    world_point = transform_points(start, np.asarray(point, dtype=float)[None])[0] + noise.contact_offset
    world_direction = unit(start[:3, :3] @ unit(np.asarray(direction, dtype=float)) + noise.direction_offset)
    path = finger_path(world_point, world_direction, config, finger_steps(config, settings))
    sphere = pb.createCollisionShape(pb.GEOM_SPHERE, radius=config.contacts.finger_radius, physicsClientId=client)
    finger = pb.createMultiBody(FINGER_MASS, sphere, basePosition=path[0].tolist(), physicsClientId=client)
    pb.changeDynamics(finger, -1, lateralFriction=noise.mu_finger / noise.mu_table, physicsClientId=client)
    pb.setCollisionFilterPair(finger, table, -1, -1, 0, physicsClientId=client)
    peak_force = drive_finger(pb, client, finger, path, obj_id, config.topple.max_finger_force, config.topple.gravity, observe)
    # Withdraw the finger so it neither props the object up nor pushes it further.
    pb.removeBody(finger, physicsClientId=client)
    still, rest_steps = 0, settings.rest_steps
    for _ in range(int(SETTLE_TIME / settings.time_step)):
        pb.stepSimulation(physicsClientId=client)
        linear, angular = pb.getBaseVelocity(obj_id, physicsClientId=client)
        still = still + 1 if np.linalg.norm(linear) < REST_SPEED and np.linalg.norm(angular) < REST_SPIN else 0
        if still >= rest_steps:
            break
    final = _observe(pb, client, obj_id, body)
    return PlayedPush(start, final, still >= rest_steps, world_point, world_direction, noise, peak_force)


def drive_finger(pb, client: int, finger: int, path: np.ndarray, pushed: int, limit: float, gravity: float, observe=None) -> float:
    """Drag the finger body through ``path``, one simulation step per point, pressing with
    ``limit`` in norm once it presses steadily (``finger_row_limit``); the constraint is
    removed at the end, the finger body left to the caller.

    pb : the pybullet module;  client : its physics client;  finger : the finger's body id
    path : (n_steps, 3) float, m, world frame;  pushed : body id of what the finger pushes
    limit : float, N (``topple.max_finger_force``);  gravity : float, m/s^2, cancelled on the finger
    observe : ``play_push``'s, called after each step
    returns : float, N, the largest normal force the finger pressed ``pushed`` with (summed
      over its contact points, per step)
    """
    grip = pb.createConstraint(finger, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], path[0].tolist(), physicsClientId=client)
    # The model's finger has no weight: cancelled, so what the constraint pulls with is what
    # the finger presses with once it moves steadily.
    lift = [0.0, 0.0, FINGER_MASS * gravity]
    row_limit, peak_force = limit, 0.0
    for target in path:
        pb.changeConstraint(grip, target.tolist(), maxForce=row_limit, physicsClientId=client)
        position, _ = pb.getBasePositionAndOrientation(finger, physicsClientId=client)
        pb.applyExternalForce(finger, -1, lift, position, pb.WORLD_FRAME, physicsClientId=client)
        pb.stepSimulation(physicsClientId=client)
        applied = np.asarray(pb.getConstraintState(grip, physicsClientId=client)[:3], dtype=float)
        row_limit = finger_row_limit(applied, limit)
        pressing = sum(c[9] for c in pb.getContactPoints(finger, pushed, physicsClientId=client))
        peak_force = max(peak_force, pressing)
        if observe is not None:
            observe(pb, client, pushed, pressing)
    pb.removeConstraint(grip, physicsClientId=client)
    return peak_force


def rest_on_table(body: BodyModel, transform: np.ndarray, config: Config = DEFAULT_CONFIG, duration: float = REST_BEFORE,
                  settings: PlayerSettings = DEFAULT_PLAYER) -> np.ndarray:
    """Place the object at ``transform`` (object -> world), leave it ``duration`` s, and observe it.

    What ``play_push`` does before the finger comes; the object's transform then, (4, 4).
    """
    pb, client = _client()
    _, obj_id = _place(pb, client, body, transform, config.topple.mu_table_mean, config, duration, settings)
    return _observe(pb, client, obj_id, body)


_CLIENTS: dict[int, int] = {}
"""This process's pybullet client (connecting costs ~60 ms, resetting it ~3 ms), by process id."""


def _client():
    """pybullet and this process's DIRECT client, connected on first use."""
    import os

    import pybullet as pb

    pid = os.getpid()  # a forked worker must not share its parent's client
    if pid not in _CLIENTS or not pb.isConnected(_CLIENTS[pid]):
        _CLIENTS[pid] = pb.connect(pb.DIRECT)
    return pb, _CLIENTS[pid]


def _place(pb, client, body: BodyModel, transform: np.ndarray, mu_table: float, config: Config, duration: float = REST_BEFORE,
           settings: PlayerSettings = DEFAULT_PLAYER) -> tuple[int, int]:
    """Empty the world, build the table and the object at ``transform``, let it rest ``duration`` s.

    ``resetSimulation`` first, so that a push does not depend on what this process
    played before it (results are the same whatever the number of workers).
    settings : the step and solver iterations the world is integrated with (``PlayerSettings``)
    returns : (table body id, object body id)
    """
    pb.resetSimulation(physicsClientId=client)
    pb.setGravity(0, 0, -config.topple.gravity, physicsClientId=client)
    pb.setPhysicsEngineParameter(fixedTimeStep=settings.time_step, numSolverIterations=settings.solver_iterations,
                                 physicsClientId=client)

    # The table is a thick box with its top face at z = 0 (a GEOM_PLANE costs ~15 ms to create).
    half = [TABLE_HALF_SIZE] * 3
    table = pb.createMultiBody(
        0, pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=client),
        basePosition=[0.0, 0.0, -TABLE_HALF_SIZE], physicsClientId=client,
    )
    pb.changeDynamics(table, -1, lateralFriction=1.0, collisionMargin=COLLISION_MARGIN, physicsClientId=client)

    position, world_from_link = link_pose(body, transform)
    if body.parts:
        shape = _parts_shape(pb, client, body.parts)
    else:
        shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=body.vertices.tolist(), physicsClientId=client)
    obj_id = pb.createMultiBody(
        body.mass, shape, basePosition=position.tolist(), baseOrientation=_quaternion(world_from_link), physicsClientId=client
    )
    pb.changeDynamics(
        obj_id,
        -1,
        lateralFriction=mu_table,
        localInertiaDiagonal=body.inertia.tolist(),
        rollingFriction=0.0,
        spinningFriction=0.0,
        collisionMargin=COLLISION_MARGIN,
        physicsClientId=client,
    )
    for _ in range(round(duration / settings.time_step)):
        pb.stepSimulation(physicsClientId=client)
    return table, obj_id


def _parts_shape(pb, client, parts: str) -> int:
    """pybullet's compound collision shape of ``parts`` (OBJ text; ``convex_parts``).

    pybullet loads a compound only from a file: it is written, loaded and removed again, so
    that no file outlives the call whatever ends the process later.
    """
    import os
    import tempfile

    handle, path = tempfile.mkstemp(suffix=".obj", prefix="toppledb-parts-")
    try:
        with os.fdopen(handle, "w") as f:
            f.write(parts)
        return pb.createCollisionShape(pb.GEOM_MESH, fileName=path, physicsClientId=client)
    finally:
        os.unlink(path)


def _observe(pb, client, obj_id: int, body: BodyModel) -> np.ndarray:
    """The object's current transform, object -> world, (4, 4)."""
    position, quaternion = pb.getBasePositionAndOrientation(obj_id, physicsClientId=client)
    world_from_link = np.array(pb.getMatrixFromQuaternion(quaternion)).reshape(3, 3)
    return object_transform(body, np.array(position), world_from_link)


def simulate_push(
    obj: ObjectModel,
    pose_set: PoseSet,
    pose_index: int,
    point: np.ndarray,
    direction: np.ndarray,
    config: Config = DEFAULT_CONFIG,
    rng: np.random.Generator | None = None,
    noise: bool = True,
    body: BodyModel | None = None,
) -> int:
    """Push the object standing in one of its stable poses; the stable pose it comes to rest in.

    point : (3,) float, m, contact point, pose frame (the object starts in the pose's
      canonical transform, so pose frame == world frame)
    direction : (3,) float, push direction, pose frame (normalised here)
    rng : draws the noise when ``noise`` is True
    body : ``body_model(obj)``, to reuse across pushes of one object
    returns : int, index into ``pose_set.poses``, or ``logreader.OUTSIDE`` (-1) for a rest pose left
      out of the set (settled with the hull's topple graph if still moving at the time cap)
    """
    transform = pose_set.poses[pose_index].transform
    to_object = np.linalg.inv(transform)
    played = play_push(
        body or body_model(obj),
        transform,
        transform_points(to_object, np.asarray(point, dtype=float)[None])[0],
        to_object[:3, :3] @ np.asarray(direction, dtype=float),
        config,
        draw_noise(config, rng, noise),
    )
    return settle(pose_set, obj, played.final_transform[:3, :3])

