"""Candidate pushes (thesis 4.4.1) and whether a finger can execute them.

Contact points are drawn once per object, spread evenly over its surface, and
shared by all its poses (action i is the same surface point in every pose); each
pose then decides which of them a finger can push: ``ok``, or why not.
"""

from __future__ import annotations

import fcl
import numpy as np
import trimesh

from schema.frames import transform_points, unit
from schema.vocabulary import (
    STATUS_FINGER_COLLISION,
    STATUS_OK,
    STATUS_PUSHES_UP,
    STATUS_TOO_LOW,
)

from .collision import collides_each
from .config import ContactConfig
from .mesh import ObjectModel
from .outcomes import Actions
from .rng import stream
from .sampling import area_weighted_faces, points_in_triangles

CONTACT_CLEARANCE = 5e-4
"""m; gap left between the finger tip and the contact so that touching is not a collision."""


def farthest_point_subset(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` points chosen greedily to be far from each other.

    points : (n, 3) float
    returns : (count,) int, starting from point 0 (so the result is deterministic)
    """
    if count > len(points):
        raise ValueError(f"cannot choose {count} points from {len(points)}")
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = 0
    # Coordinate rows and squared distances keep each step to a few contiguous passes.
    x, y, z = np.ascontiguousarray(points.T, dtype=float)
    nearest = np.full(len(points), np.inf)
    step = np.empty(len(points))
    scratch = np.empty(len(points))
    for i in range(count):
        if i:
            chosen[i] = np.argmax(nearest)
        qx, qy, qz = points[chosen[i]]
        np.subtract(x, qx, out=step)
        np.multiply(step, step, out=step)
        np.subtract(y, qy, out=scratch)
        np.multiply(scratch, scratch, out=scratch)
        step += scratch
        np.subtract(z, qz, out=scratch)
        np.multiply(scratch, scratch, out=scratch)
        step += scratch
        np.minimum(nearest, step, out=nearest)
    return chosen


def surface_points(
    mesh: trimesh.Trimesh, count: int, rng: np.random.Generator, oversample: int
) -> tuple[np.ndarray, np.ndarray]:
    """Exactly ``count`` points spread evenly over the surface, with their face normals.

    Uniform area-weighted samples, then a farthest-point subset: even spacing
    without the shortfall of Poisson-disk rejection.

    returns : points (count, 3) float, m; normals (count, 3) float, unit, outward
    """
    pool = max(count * oversample, count)
    faces = area_weighted_faces(mesh.area_faces, pool, rng)
    points = points_in_triangles(mesh.triangles[faces], rng.random((pool, 2)))
    keep = farthest_point_subset(points, count)
    return points[keep], mesh.face_normals[faces[keep]]


def max_height_contact(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, max_angle: float):
    """The Max-Height baseline's contact: the highest surface point whose normal is
    within ``max_angle`` of horizontal (thesis 4.3.1).

    vertices : (n, 3) float, m, pose frame; faces : (F, 3) int; normals : (F, 3) float, pose frame
    returns : (point (3,), normal (3,)) or None when no face qualifies
    """
    steep = np.flatnonzero(np.abs(normals[:, 2]) <= np.sin(max_angle))
    if len(steep) == 0:
        return None
    corner_z = vertices[faces[steep], 2]
    best = steep[np.argmax(corner_z.max(axis=1))]
    triangle = vertices[faces[best]]
    top = triangle[np.argmax(triangle[:, 2])]
    # A hair inside the face, so rays and collision checks see the face, not its edge.
    point = top + 1e-3 * (triangle.mean(axis=0) - top)
    return point, normals[best]


def capsule_segments(points: np.ndarray, directions: np.ndarray, config: ContactConfig):
    """End points of the finger capsule's axis: the finger as it sweeps from
    ``approach_offset`` outside the contact to touching it.

    returns : tip (A, 3), back (A, 3), m; the tip end is nearest the contact
    """
    tip = points - (config.finger_radius + CONTACT_CLEARANCE) * directions
    back = points - (config.approach_offset + config.finger_length) * directions
    return tip, back


def finger_collisions(
    collision_mesh: fcl.CollisionObject,
    to_object: np.ndarray,
    points: np.ndarray,
    directions: np.ndarray,
    config: ContactConfig,
) -> np.ndarray:
    """Whether the finger capsule hits the object or the table on its approach.

    collision_mesh : fcl object of the mesh in the object frame (built once per object)
    to_object : (4, 4) float, pose frame -> object frame
    points, directions : (A, 3) float, pose frame
    returns : (A,) bool
    """
    tip, back = capsule_segments(points, directions, config)
    hits = np.minimum(tip[:, 2], back[:, 2]) - config.finger_radius < 0.0  # the table is z < 0
    length = float(np.linalg.norm(tip[0] - back[0])) if len(points) else 0.0
    capsule = fcl.Capsule(config.finger_radius, length)
    check = np.flatnonzero(~hits)
    centers = transform_points(to_object, 0.5 * (tip[check] + back[check]))
    axes = directions[check] @ to_object[:3, :3].T
    hits[check] = collides_each(capsule, centers, axes, collision_mesh)
    return hits


def pose_actions(
    points: np.ndarray,
    normals: np.ndarray,
    mesh: trimesh.Trimesh,
    collision_mesh: fcl.CollisionObject,
    transform: np.ndarray,
    config: ContactConfig,
) -> Actions:
    """Candidate pushes of one pose: the object's contact points plus the Max-Height action.

    points, normals : (N, 3) float, object frame, from ``surface_points``
    mesh : object surface, object frame
    transform : (4, 4) float, object frame -> pose frame
    """
    rotation = transform[:3, :3]
    vertices = transform_points(transform, mesh.vertices)
    face_normals = mesh.face_normals @ rotation.T
    pose_points = transform_points(transform, points)
    pose_normals = normals @ rotation.T
    best = max_height_contact(vertices, mesh.faces, face_normals, config.max_height_normal_angle)
    max_height = -1
    if best is not None:
        pose_points = np.vstack([pose_points, best[0]])
        pose_normals = np.vstack([pose_normals, best[1]])
        max_height = len(pose_points) - 1
    pose_normals = unit(pose_normals)
    directions = -pose_normals

    status = np.full(len(pose_points), STATUS_OK, dtype=np.int8)
    height = vertices[:, 2].max()
    status[pose_points[:, 2] < config.min_height_fraction * height] = STATUS_TOO_LOW
    pushes_up = (status == STATUS_OK) & (directions[:, 2] > np.sin(config.max_up_angle))
    status[pushes_up] = STATUS_PUSHES_UP
    candidates = np.flatnonzero(status == STATUS_OK)
    to_object = np.linalg.inv(transform)
    blocked = finger_collisions(collision_mesh, to_object, pose_points[candidates], directions[candidates], config)
    status[candidates[blocked]] = STATUS_FINGER_COLLISION
    return Actions(points=pose_points, normals=pose_normals, directions=directions, status=status, max_height=max_height)


def object_contacts(obj: ObjectModel, config: ContactConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The object's candidate contact points and normals (object frame), shared by its poses."""
    return surface_points(obj.mesh, config.n_contacts, stream(seed, obj.name, -1, "contacts"), config.oversample)


SNAP_TOLERANCE = 1e-3
"""m; farthest an explicit push's point may lie from the object's surface (``explicit_actions``).
A point is snapped to the closest surface point, so one further off would be evaluated as a push
somewhere the caller did not mean, with a confident answer.  The pybullet logs' pushes (data/logs/*,
6,291 pushes read by ``studies.logreader``) lie at most 2.2e-6 m off the surface, so this is some
450 times what logged pushes need; it also admits points rounded to 0.1 mm or stored as float32."""


def push_arrays(points, directions) -> tuple[np.ndarray, np.ndarray | None]:
    """Explicit pushes as arrays, or ValueError saying what is wrong with them.

    points : (k, 3) finite, m (a single (3,) point is one push);  directions : None or (k, 3)
      finite and non-zero (any length: they are normalised), one per point
    returns : points (k, 3) float, directions (k, 3) float or None
    """
    points = _rows(points, "points")
    if directions is None:
        return points, None
    directions = _rows(directions, "directions")
    if len(directions) != len(points):
        raise ValueError(f"explicit pushes need one direction per point (or none): {len(points)} points, "
                         f"{len(directions)} directions")
    largest = np.abs(directions).max(axis=1)
    zero = np.flatnonzero(~(largest > 0))
    if len(zero):  # ``unit`` would leave it zero: a push that goes nowhere, evaluated all the same
        raise ValueError(f"directions must be non-zero: direction {zero[0]} is {directions[zero[0]].tolist()}")
    # A length whose square leaves float64 ([1e200, 0, 0] overflows, [1e-170, 0, 0] underflows) would normalise to
    # zero or NaN: such rows are scaled by their largest component first. Every other row is kept bit for bit.
    with np.errstate(over="ignore", under="ignore"):
        length = np.linalg.norm(directions, axis=1)
    extreme = ~((length > 1e-100) & (length < 1e100))
    if extreme.any():
        directions = directions.copy()
        directions[extreme] /= largest[extreme, None]
    return points, directions


def _rows(values, name: str) -> np.ndarray:
    """``values`` as a (k, 3) float array of finite numbers, k >= 1 (a (3,) vector is one row)."""
    try:
        array = np.atleast_2d(np.asarray(values, dtype=float))
    except (TypeError, ValueError):  # ragged rows, text: numpy's own words say nothing of pushes
        raise ValueError(f"{name} must be a (k, 3) array of numbers (m, pose frame), got {values!r}") from None
    if array.ndim != 2 or array.shape[1] != 3 or len(array) == 0:
        raise ValueError(f"{name} must be a (k, 3) array (x, y, z per push, pose frame), got shape {np.shape(values)}")
    bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
    if len(bad):
        raise ValueError(f"{name} must be finite: row {bad[0]} is {array[bad[0]].tolist()}")
    return array


def snap_to_surface(obj: ObjectModel, transform: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest surface point to each of ``points``.

    transform : (4, 4) float, object frame -> pose frame;  points : (k, 3) float, m, pose frame
    returns : closest (k, 3) float, m, pose frame; faces (k,) int, the face each is on;
      distance (k,) float, m, how far each point was moved
    """
    closest, distance, faces = trimesh.proximity.closest_point(obj.mesh, transform_points(np.linalg.inv(transform), points))
    return transform_points(transform, closest), faces, distance


class OffSurface(ValueError):
    """An explicit push's point further from the surface than the tolerance; ``where`` names the point
    and how far it is, for a caller (the log scorer) that explains it in its own terms."""

    def __init__(self, where: str):
        super().__init__(f"{where}; points are in metres in the pose frame (z up, table at z = 0, centre of mass over the origin)")
        self.where = where


def explicit_actions(obj: ObjectModel, transform: np.ndarray, points: np.ndarray, directions: np.ndarray | None,
                     tolerance: float = SNAP_TOLERANCE) -> Actions:
    """Actions at caller-chosen contact points (pose frame); all are evaluated (status ``ok``).

    points : (A, 3) float, m, pose frame (z up, table at z = 0, centre of mass over the origin), on the
      surface within ``tolerance`` (m, default ``SNAP_TOLERANCE``); each is snapped to the closest surface point
    directions : (A, 3) float, pose frame, non-zero push directions; the inward normal when None
    Raises ValueError for malformed points or directions (``push_arrays``), ``OffSurface`` for a point further
    than ``tolerance`` from the surface.
    """
    points, directions = push_arrays(points, directions)
    closest, faces, distance = snap_to_surface(obj, transform, points)
    far = np.flatnonzero(~(distance <= tolerance))
    if len(far):
        i = far[np.argmax(distance[far])]
        raise OffSurface(f"point {i} {points[i].tolist()} is {distance[i] * 1000:.4g} mm from the object's surface, "
                         f"more than the {tolerance * 1000:g} mm tolerance")
    normals = obj.mesh.face_normals[faces] @ transform[:3, :3].T
    directions = -normals if directions is None else unit(directions)
    return Actions(closest, normals, directions, np.full(len(closest), STATUS_OK, dtype=np.int8), max_height=-1)


SAME_CANDIDATE_TOLERANCE = 1e-6
"""m (points) and unit-vector components (directions): a push this close to a candidate is that candidate
(as close as a log's repeats of one push must agree, ``logreader.SAME_PUSH_TOLERANCE``)."""


def with_probes(pool: Actions, pushes: Actions, points: np.ndarray, directions: np.ndarray,
                tolerance: float = SAME_CANDIDATE_TOLERANCE) -> tuple[Actions, int, np.ndarray]:
    """A pose's candidate pushes followed by the pushes asked about that are none of them (probes):
    what ``topple.evaluate_pose(..., candidates=n)`` takes to predict a push among the candidates, as
    the dataset's rows are (the smoothing and maps of docs/MODEL.md C.12-C.19 read them).

    pool : the pose's candidates (``pose_actions``);  pushes : (k,) the pushes as actions
    points, directions : (k, 3) float, pose frame, each push as given, matched to the ``ok`` candidates
      within ``tolerance`` (the first that matches)
    returns : the actions (candidates, then probes), n (how many lead as candidates), and (k,) int,
      the row of the actions that predicts each push
    """
    points, directions = np.asarray(points, dtype=float).reshape(-1, 3), np.asarray(directions, dtype=float).reshape(-1, 3)
    if not len(points) == len(directions) == len(pushes.status):
        raise ValueError(f"with_probes needs one point and one direction per push: {len(points)} points, "
                         f"{len(directions)} directions, {len(pushes.status)} pushes")
    ok = np.flatnonzero(pool.status == STATUS_OK)
    index = np.full(len(points), -1, dtype=np.int64)
    probes: list[int] = []
    for i, (point, direction) in enumerate(zip(points, directions, strict=True)):
        same = ok[np.all(np.abs(pool.points[ok] - point) <= tolerance, axis=1)
                  & np.all(np.abs(pool.directions[ok] - direction) <= tolerance, axis=1)]
        if len(same):
            index[i] = same[0]
        else:
            index[i] = len(pool.status) + len(probes)
            probes.append(i)
    actions = Actions(
        points=np.vstack([pool.points, pushes.points[probes]]),
        normals=np.vstack([pool.normals, pushes.normals[probes]]),
        directions=np.vstack([pool.directions, pushes.directions[probes]]),
        status=np.concatenate([pool.status, pushes.status[probes]]),
        max_height=pool.max_height,
    )
    return actions, len(pool.status), index
