"""Stable poses of an object and quasi-static settling (Goldberg et al. 1999).

The convex hull's faces form a "topples to" graph: a face whose plane holds the
projection of the centre of mass rests; any other face rolls over the edge that
the centre of mass projects beyond (the edge crossed on the way from the face's
centroid to that projection, trimesh's rule) onto the neighbouring face.  The
graph's sinks are the stable poses; a pose's probability is the solid angle, seen
from the centre of mass, of the faces that drain into it.

One graph serves the pose list, the topple outcomes and settling from an
arbitrary orientation, so every pose a topple can reach is a pose of the list.

Rotationally symmetric objects (a cylinder, a can, a prism) have many sinks that
are the same resting pose turned about the centre of mass: their hulls, seen in
their canonical pose frames, coincide after a yaw about the vertical.  With
``merge_symmetric`` such poses are merged into one (``congruent_yaw``;
docs/MODEL.md, "Symmetric objects"), so a 32-sided cylinder has two poses, not 34,
and ``PoseSet.equivalents`` keeps every merged orientation for matching.  A nearly
spherical object has no stable pose worth pushing (it rolls) and is rejected with
that reason.
``tests/test_poses.py`` holds it against ``trimesh.poses.compute_stable_poses``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from schema.api import rotation_problem
from schema.frames import canonical_transform, transform_points, unit

from .config import PoseConfig
from .edges import base_edges, base_polygon, edge_geometry, landing_angles, landing_down, rolled_down
from .mesh import MeshError, ObjectModel
from .momentum import inertia_per_mass, momentum_poses
from .outcomes import StablePose


def face_neighbors(hull: trimesh.Trimesh) -> np.ndarray:
    """Neighbouring face across each face's edges.

    returns : (F, 3) int, entry k is the face across the edge opposite vertex k
    """
    faces = hull.faces
    n = len(faces)
    # Edge opposite vertex k joins vertices k+1 and k+2.
    edges = np.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], axis=1).reshape(-1, 2)
    edges.sort(axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    if np.any(counts != 2):
        raise ValueError("convex hull is not a closed two-manifold")
    order = np.argsort(inverse.ravel(), kind="stable")
    first, second = order[0::2], order[1::2]
    neighbors = np.empty(3 * n, dtype=np.int64)
    neighbors[first] = second // 3
    neighbors[second] = first // 3
    return neighbors.reshape(n, 3)


def facet_ids(hull: trimesh.Trimesh) -> np.ndarray:
    """Coplanar group of each hull face; faces in no group are their own.

    returns : (F,) int
    """
    ids = np.arange(len(hull.faces))
    for facet in hull.facets:
        ids[facet] = facet.min()
    return ids


def topple_graph(hull: trimesh.Trimesh, center_mass: np.ndarray) -> np.ndarray:
    """The face each hull face rolls onto; a face in a stable facet maps to itself.

    hull : convex hull, object frame
    center_mass : (3,) float, m, object frame
    returns : (F,) int
    """
    triangles = hull.triangles
    normals = hull.face_normals
    depth = np.einsum("ij,ij->i", normals, center_mass - triangles[:, 0])
    projected = center_mass - depth[:, None] * normals
    # A hull of a finely faceted part can keep a zero-area sliver; its coordinates come out inf or nan,
    # which no test below passes, so the sliver is never a resting face and rolls on like any other.
    with np.errstate(divide="ignore", invalid="ignore"):
        bary = trimesh.triangles.points_to_barycentric(triangles, projected)
    inside = np.all(bary >= -1e-9, axis=1)
    facets = facet_ids(hull)
    stable = np.isin(facets, facets[inside])
    # Walking from the centroid (1/3, 1/3, 1/3) towards the projection, coordinate k
    # reaches zero first where t_k = (1/3) / (1/3 - b_k) is smallest.
    with np.errstate(divide="ignore"):
        exit_time = np.where(bary < 0, (1.0 / 3.0) / (1.0 / 3.0 - bary), np.inf)
    exit_edge = np.argmin(exit_time, axis=1)
    rows = np.arange(len(triangles))
    return np.where(stable, rows, face_neighbors(hull)[rows, exit_edge])


def sink_faces(next_face: np.ndarray) -> np.ndarray:
    """Follow the topple graph to its sinks by pointer jumping.

    next_face : (F,) int
    returns : (F,) int, the resting face reached from each face
    """
    sink = next_face.copy()
    for _ in range(int(np.ceil(np.log2(max(len(sink), 2)))) + 2):
        sink = sink[sink]
    if np.any(sink[sink] != sink):
        raise ValueError("the topple graph has a cycle")
    return sink


def face_solid_angles(hull: trimesh.Trimesh, center_mass: np.ndarray) -> np.ndarray:
    """Solid angle of each hull face seen from the centre of mass (Van Oosterom and Strackee).

    returns : (F,) float, sr; sums to 4 pi for a closed hull around the centre of mass
    """
    a, b, c = (hull.triangles - center_mass).transpose(1, 0, 2)
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    numerator = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    denominator = (
        la * lb * lc
        + np.einsum("ij,ij->i", a, b) * lc
        + np.einsum("ij,ij->i", a, c) * lb
        + np.einsum("ij,ij->i", b, c) * la
    )
    return 2.0 * np.arctan2(numerator, denominator)


def face_below(hull: trimesh.Trimesh, center_mass: np.ndarray, downs: np.ndarray) -> np.ndarray:
    """The hull face pierced by the ray from the centre of mass along each down vector.

    downs : (n, 3) float, unit, object frame
    returns : (n,) int
    """
    normals = hull.face_normals
    facing = downs @ normals.T
    height = np.einsum("ij,ij->i", normals, hull.triangles[:, 0] - center_mass)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.where(facing > 1e-12, height[None, :] / facing, np.inf)
    return np.argmin(distance, axis=1)


@dataclass
class PoseSet:
    """An object's stable poses and the graph that settles any orientation into one.

    poses : list[StablePose], sorted by probability (descending), then closed under toppling
    face_pose : (F,) int, pose each hull face drains into (-1: a pose left out of ``poses``)
    """

    poses: list[StablePose]
    face_pose: np.ndarray
    equivalents: list[np.ndarray] | None = None
    """With ``merge_symmetric``: per pose, (k, 4, 4) transforms object -> this pose's frame,
    one per merged orientation (its own ``transform`` first); None when nothing was merged."""

    def match_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(downs (M, 3), transforms (M, 4, 4), pose of each (M,)) over every orientation
        that is a pose, merged equivalents included: what ``match_pose`` searches."""
        if self.equivalents is None:
            return self.downs, self.transforms, np.arange(len(self.poses))
        transforms = np.concatenate(self.equivalents)
        downs = np.einsum("mji,j->mi", transforms[:, :3, :3], [0.0, 0.0, -1.0])
        owner = np.concatenate([np.full(len(e), i) for i, e in enumerate(self.equivalents)])
        return downs, transforms, owner

    @property
    def downs(self) -> np.ndarray:
        return np.array([p.down for p in self.poses])

    @property
    def transforms(self) -> np.ndarray:
        return np.array([p.transform for p in self.poses])

    @property
    def probabilities(self) -> np.ndarray:
        """(P,) float, each pose's drop probability."""
        return np.array([p.probability for p in self.poses], dtype=float)


def stability_margin(pose: StablePose, center_mass: np.ndarray) -> tuple[float, int]:
    """How close a pose is to falling over: the least horizontal distance (m) from the
    centre of mass's projection to a base edge line (negative when outside), and that edge.

    center_mass : (3,) float, m, object frame
    returns : (margin in m, index into ``pose.base_edges``)
    """
    geometry = edge_geometry(pose.base_edges, transform_points(pose.transform, center_mass[None])[0])
    edge = int(np.argmin(geometry.com_distance))
    return float(geometry.com_distance[edge]), edge


SYMMETRY_TOLERANCE = 1e-6
"""Relative to the hull's size: two poses are one when their hulls coincide, after a yaw,
to this fraction of the bounding-box diagonal (CAD-exact symmetry; scans rarely qualify)."""
SPHERE_RADIUS_RATIO = 0.95
"""Nearly a sphere: every hull face's plane at least this fraction of the farthest hull
vertex's distance from the centre of mass.  Such an object rolls on any push."""


def congruent_yaw(a: np.ndarray, b: np.ndarray, tolerance: float) -> float | None:
    """A yaw (rad) that turns point set ``a`` onto ``b`` about the z axis, or None.

    a, b : (n, 3) float, m, hull vertices in two pose frames (z up, centre of mass on the z axis)
    tolerance : m, largest distance from a turned point of ``a`` to its nearest in ``b``
    """
    if len(a) != len(b):
        return None
    tree = cKDTree(b)
    radius_a, radius_b = np.hypot(a[:, 0], a[:, 1]), np.hypot(b[:, 0], b[:, 1])
    anchor = int(np.argmax(radius_a))  # the farthest from the axis has a well-defined azimuth
    candidates = np.flatnonzero(
        (np.abs(radius_b - radius_a[anchor]) <= tolerance) & (np.abs(b[:, 2] - a[anchor, 2]) <= tolerance)
    )
    for k in candidates:
        yaw = np.arctan2(b[k, 1], b[k, 0]) - np.arctan2(a[anchor, 1], a[anchor, 0])
        c, s = np.cos(yaw), np.sin(yaw)
        turned = a @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        distance, _ = tree.query(turned, distance_upper_bound=2 * tolerance)
        if np.all(distance <= tolerance):
            return float(yaw)
    return None


def symmetric_groups(vertices: list[np.ndarray], com_heights: np.ndarray, order: np.ndarray, tolerance: float) -> np.ndarray:
    """Representative of each candidate pose: the first in ``order`` whose hull it matches.

    vertices : per candidate (n, 3) float, hull vertices in its pose frame
    com_heights : (C,) float, m;  order : candidates, most probable first
    returns : (C,) int, index of each candidate's representative (itself when unique)
    """
    representative = np.arange(len(vertices))
    representatives: list[int] = []
    for i in order.tolist():
        for r in representatives:
            if abs(com_heights[i] - com_heights[r]) <= tolerance and congruent_yaw(vertices[i], vertices[r], tolerance) is not None:
                representative[i] = r
                break
        else:
            representatives.append(i)
    return representative


def check_not_spherical(obj: ObjectModel) -> None:
    """Reject an object that rolls in every pose (``SPHERE_RADIUS_RATIO``): the centre of
    mass is nearly as far from every hull face's plane (its height resting on that face)
    as from the farthest hull vertex."""
    hull = obj.hull
    heights = np.einsum("ij,ij->i", hull.triangles[:, 0] - obj.center_mass, hull.face_normals)
    radius = float(np.linalg.norm(np.asarray(hull.vertices) - obj.center_mass, axis=1).max())
    if heights.min() >= SPHERE_RADIUS_RATIO * radius:
        raise MeshError(
            f"{obj.name}: no stable pose worth pushing: nearly a sphere (resting on any face, its centre of "
            f"mass is within {100 * (1 - SPHERE_RADIUS_RATIO):.0f}% of its farthest point's distance), so it rolls"
        )


def stable_poses(obj: ObjectModel, config: PoseConfig = PoseConfig(), merge_symmetric: bool | None = None) -> PoseSet:
    """Stable poses of ``obj`` with probability >= ``config.min_probability``, plus
    every pose reachable from them by toppling over a base edge.

    Sink facets whose down vectors lie within ``config.same_pose_angle`` merge into
    one pose (the more probable facet gives the down vector).  ``merge_symmetric``
    also merges poses that are the same resting pose turned (``symmetric_groups``);
    None takes ``config.merge_symmetric``.
    Raises ``MeshError`` for a nearly spherical object (``check_not_spherical``).
    """
    hull, com = obj.hull, obj.center_mass
    check_not_spherical(obj)
    try:
        sink = sink_faces(topple_graph(hull, com))
    except ValueError as err:
        raise MeshError(f"{obj.name}: {err}") from None
    probability = face_solid_angles(hull, com) / (4.0 * np.pi)

    sinks, drain = np.unique(facet_ids(hull)[sink], return_inverse=True)
    sink_probability = np.bincount(drain, weights=probability, minlength=len(sinks))
    sink_down = hull.face_normals[sinks]

    # Merge sinks into poses, most probable first.
    order = np.argsort(-sink_probability, kind="stable")
    pose_of_sink = np.full(len(sinks), -1)
    downs: list[np.ndarray] = []
    for s in order:
        if downs:
            angles = np.arccos(np.clip(np.array(downs) @ sink_down[s], -1.0, 1.0))
            if angles.min() <= config.same_pose_angle:
                pose_of_sink[s] = int(np.argmin(angles))
                continue
        pose_of_sink[s] = len(downs)
        downs.append(sink_down[s])
    candidate_probability = np.bincount(pose_of_sink, weights=sink_probability, minlength=len(downs))
    face_candidate = pose_of_sink[drain]

    geometry = [_pose_geometry(obj, down, face_candidate, i, config) for i, down in enumerate(downs)]
    # C.8 (``momentum``) on every candidate, before symmetric ones merge: a roll-on chain needs
    # each landing orientation's own frame.
    rolled_on, onward = momentum_poses(
        np.array([g["transform"] for g in geometry]),
        [g["base_edges"] for g in geometry],
        [g["edge_final_pose"] for g in geometry],
        [g["edge_blocked"] for g in geometry],
        com,
        inertia_per_mass(obj.mesh, hull, com),
    )
    for g, poses_after, poses_onward in zip(geometry, rolled_on, onward):
        g["edge_momentum_pose"] = poses_after
        g["edge_onward_pose"] = poses_onward

    # Symmetric objects: candidates whose hulls coincide after a yaw are one pose.
    representative = np.arange(len(downs))
    if config.merge_symmetric if merge_symmetric is None else merge_symmetric:
        tolerance = SYMMETRY_TOLERANCE * float(np.linalg.norm(hull.extents))
        representative = symmetric_groups(
            [transform_points(g["transform"], hull.vertices) for g in geometry],
            np.array([g["com_height"] for g in geometry]),
            np.argsort(-candidate_probability, kind="stable"),
            tolerance,
        )
    merged = bool(np.any(representative != np.arange(len(downs))))
    if merged:
        candidate_probability = np.bincount(representative, weights=candidate_probability, minlength=len(downs))
        face_candidate = representative[face_candidate]
        for g in geometry:
            g["edge_final_pose"] = representative[g["edge_final_pose"]]
            g["edge_rolled_pose"] = representative[g["edge_rolled_pose"]]
            g["edge_momentum_pose"] = representative[g["edge_momentum_pose"]]
            g["edge_onward_pose"] = representative[g["edge_onward_pose"]]
        candidate_probability[representative != np.arange(len(downs))] = -1.0  # never kept

    # Keep probable poses and close the set under toppling.
    keep = set(np.flatnonzero(candidate_probability >= config.min_probability).tolist()) or {
        int(np.argmax(candidate_probability))
    }
    frontier = list(keep)
    while frontier:
        for target in geometry[frontier.pop()]["edge_final_pose"].tolist():
            if target not in keep:
                keep.add(target)
                frontier.append(target)
    kept = sorted(keep, key=lambda i: (-candidate_probability[i], i))
    new_index = np.full(len(downs), -1)
    new_index[kept] = np.arange(len(kept))

    poses = []
    for i, old in enumerate(kept):
        g = geometry[old]
        # A pose the fall rolls on into (C.8) but the set left out: the thesis's outcome.
        rolled_on_to, onward_to = new_index[g["edge_momentum_pose"]], new_index[g["edge_onward_pose"]]  # -1: left out
        momentum_pose = np.where(rolled_on_to >= 0, rolled_on_to, new_index[g["edge_final_pose"]])
        poses.append(
            StablePose(
                index=i,
                down=downs[old],
                probability=float(candidate_probability[old]),
                transform=g["transform"],
                height=g["height"],
                com_height=g["com_height"],
                base_edges=g["base_edges"],
                edge_final_pose=new_index[g["edge_final_pose"]],
                edge_blocked=g["edge_blocked"],
                apex_angle=g["apex_angle"],
                # A rolled-into pose outside the kept set (the set is closed under the thesis's
                # topples only, so C.6 never changes it) falls back to the thesis's outcome.
                edge_rolled_pose=np.where(
                    new_index[g["edge_rolled_pose"]] >= 0, new_index[g["edge_rolled_pose"]], new_index[g["edge_final_pose"]]
                ),
                edge_momentum_pose=momentum_pose,
                # C.18: an onward pose the set left out, or one beyond a momentum pose it left out (the
                # trial then lands where the thesis says), carries nothing on: the landing itself.
                edge_onward_pose=np.where((onward_to >= 0) & (rolled_on_to >= 0), onward_to, momentum_pose),
            )
        )
    equivalents = None
    if merged:
        equivalents = []
        for old in kept:
            members = [old] + [j for j in np.flatnonzero(representative == old).tolist() if j != old]
            equivalents.append(np.array([_aligned(obj, geometry[j]["transform"], geometry[old]["transform"], tolerance)
                                         for j in members]))
    return PoseSet(poses=poses, face_pose=new_index[face_candidate], equivalents=equivalents)


def _aligned(obj: ObjectModel, transform: np.ndarray, reference: np.ndarray, tolerance: float) -> np.ndarray:
    """``transform`` turned about z so that the hull lands where ``reference`` puts it."""
    yaw = congruent_yaw(
        transform_points(transform, obj.hull.vertices), transform_points(reference, obj.hull.vertices), tolerance
    )
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    return turn @ transform


def _pose_geometry(obj: ObjectModel, down: np.ndarray, face_pose: np.ndarray, index: int, config: PoseConfig) -> dict:
    """Canonical transform, base edges and per-edge outcomes of the pose with this down vector."""
    hull, com = obj.hull, obj.center_mass
    transform = canonical_transform(down, com, hull.vertices)
    vertices = transform_points(transform, hull.vertices)
    com_pose = transform_points(transform, com[None])[0]
    try:
        edges = base_edges(base_polygon(vertices, config.base_tolerance))
    except ValueError as err:
        raise MeshError(f"{obj.name}: pose {index}: {err}") from None
    geometry = edge_geometry(edges, com_pose)
    landing = landing_angles(geometry, vertices, config.base_tolerance)
    blocked = landing < geometry.apex_angle
    # The face the object lands on is the hull face most aligned with the new down direction.
    downs_object = landing_down(geometry, landing) @ transform[:3, :3]
    landing_face = np.argmax(unit(downs_object) @ hull.face_normals.T, axis=1)
    final = np.where(blocked, index, face_pose[landing_face])
    # C.6 (``rolling``): a blocked topple rolls on while the finger pushes (the thesis's outcome where it cannot).
    rolled = final.copy()
    for e in np.flatnonzero(blocked):
        down = rolled_down(vertices, com_pose, geometry.start[e], geometry.direction[e], config.base_tolerance)
        if down is not None:
            face = int(np.argmax(hull.face_normals @ unit(down @ transform[:3, :3])))
            rolled[e] = face_pose[face]
    return {
        "transform": transform,
        "height": float(vertices[:, 2].max()),
        "com_height": float(com_pose[2]),
        "base_edges": edges,
        "edge_final_pose": final,
        "edge_blocked": blocked,
        "edge_rolled_pose": rolled,
        "apex_angle": geometry.apex_angle,
    }


def settle(pose_set: PoseSet, obj: ObjectModel, rotation: np.ndarray) -> int:
    """Stable pose an object comes to rest in when released in an orientation.

    rotation : (3, 3) float, object frame -> world frame (z up): a proper rotation (orthonormal,
      det +1, within ``schema.api.ROTATION_TOLERANCE``); of a 4x4 transform, its ``[:3, :3]``
    returns : int, pose index, or -1 when it rests in a pose left out of ``pose_set``
    Raises ValueError for anything else (``check_rotation``).
    """
    down = check_rotation(rotation, "settle's rotation").T @ np.array([0.0, 0.0, -1.0])
    face = face_below(obj.hull, obj.center_mass, down[None])[0]
    return int(pose_set.face_pose[face])


def check_rotation(rotation, name: str) -> np.ndarray:
    """``rotation`` as a (3, 3) float array when it is a finite proper rotation, else ValueError
    naming ``name`` and what was given.  A scaled or reflected matrix would still give a down
    vector, and so a confident wrong pose, so it is refused rather than normalised."""
    try:
        given = np.asarray(rotation, dtype=float)
    except (TypeError, ValueError):  # ragged rows, text: numpy's own words say nothing of rotations
        raise ValueError(f"{name} must be a finite (3, 3) rotation, got {rotation!r}") from None
    if given.shape == (4, 4):
        raise ValueError(f"{name} must be a (3, 3) rotation, got a (4, 4) matrix: pass its upper-left 3x3 (transform[:3, :3])")
    if given.shape != (3, 3) or not np.all(np.isfinite(given)):
        raise ValueError(f"{name} must be a finite (3, 3) rotation, got {_shown(given)}")
    problem = rotation_problem(given.tolist())
    if problem is not None:
        raise ValueError(f"{name} is not a rotation: {problem}; got {_shown(given)}")
    return given


def _shown(array: np.ndarray) -> str:
    """A given array for an error message: its values when small, else its shape."""
    if array.size <= 16:
        return np.array2string(array, precision=4, separator=", ").replace("\n", "")
    return f"an array of shape {array.shape}"
