"""Frame arithmetic on plain numpy arrays: rotations, canonical pose frames and
matching an observed pose to a stable pose.

Imports nothing but numpy, so the HTTP service can match observed poses
without loading the geometry stack.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DOWN = np.array([0.0, 0.0, -1.0])


def unit(vectors: np.ndarray) -> np.ndarray:
    """Normalise along the last axis; zero vectors stay zero.

    vectors : (..., 3) float
    """
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, norm, out=np.zeros_like(vectors, dtype=float), where=norm > 0)


def tangent_frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (u, v) with (u, v, axis) right-handed and orthonormal.

    axes : (..., 3) float, unit
    returns : u, v, each (..., 3) float
    """
    # Crossing with x fails only for axes near x; fall back to y there.
    helper = np.where(np.abs(axes[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = unit(np.cross(axes, helper))
    return u, np.cross(axes, u)


def z_to_axes(axes: np.ndarray) -> np.ndarray:
    """Rotations taking +z onto each unit axis: (..., 3) -> (..., 3, 3), columns (u, v, axis)."""
    u, v = tangent_frames(axes)
    return np.stack([u, v, axes], axis=-1)


def axis_angle_matrices(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rotation matrices from unit axes and angles (Rodrigues).

    axes : (..., 3) float, unit
    angles : (...,) float, rad, right-handed about the axis
    returns : (..., 3, 3) float
    """
    axes = np.asarray(axes, dtype=float)
    angles = np.asarray(angles, dtype=float)
    x, y, z = axes[..., 0], axes[..., 1], axes[..., 2]
    c, s = np.cos(angles), np.sin(angles)
    t = 1.0 - c
    out = np.empty(axes.shape[:-1] + (3, 3))
    out[..., 0, 0] = c + x * x * t
    out[..., 0, 1] = x * y * t - z * s
    out[..., 0, 2] = x * z * t + y * s
    out[..., 1, 0] = y * x * t + z * s
    out[..., 1, 1] = c + y * y * t
    out[..., 1, 2] = y * z * t - x * s
    out[..., 2, 0] = z * x * t - y * s
    out[..., 2, 1] = z * y * t + x * s
    out[..., 2, 2] = c + z * z * t
    return out


def align_to_down(down: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``down`` to (0, 0, -1).

    down : (3,) float, unit, object frame
    returns : (3, 3) float
    """
    down = unit(np.asarray(down, dtype=float))
    axis = np.cross(down, DOWN)
    sin = np.linalg.norm(axis)
    cos = float(np.dot(down, DOWN))
    if sin < 1e-12:
        # Parallel: identity; antiparallel: half turn about x (a fixed, deterministic choice).
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    return axis_angle_matrices(axis / sin, np.arctan2(sin, cos))


def canonical_transform(down: np.ndarray, center_mass: np.ndarray, hull_vertices: np.ndarray) -> np.ndarray:
    """Object frame -> canonical frame of the stable pose with this down vector:
    resting on z = 0 with the centre of mass over the origin.

    down : (3,) float, unit, object frame
    center_mass : (3,) float, m, object frame
    hull_vertices : (n, 3) float, m, object frame
    returns : (4, 4) float
    """
    rotation = align_to_down(down)
    transform = np.eye(4)
    transform[:3, :3] = rotation
    com = rotation @ center_mass
    transform[:3, 3] = [-com[0], -com[1], -float((hull_vertices @ rotation.T)[:, 2].min())]
    return transform


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """points : (n, 3) float -> (n, 3) float under a (4, 4) transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def place_push(
    pose_to_world: np.ndarray,
    point: np.ndarray,
    normal: np.ndarray,
    direction: np.ndarray,
    approach_offset: float,
    push_depth: float,
) -> dict[str, np.ndarray]:
    """A push stored in the pose frame, placed in the world.

    pose_to_world : (4, 4) float, pose frame -> world (as observed)
    point, normal, direction : (3,) float, pose frame: contact point, outward unit normal, push direction
    approach_offset, push_depth : m, the finger's line starts this far out along the normal
      and ends this far in
    returns : world (3,) float arrays ``point``, ``normal``, ``direction``, ``start``, ``end``
    """
    rotation = pose_to_world[:3, :3]
    point = rotation @ point + pose_to_world[:3, 3]
    normal = rotation @ normal
    return {
        "point": point,
        "normal": normal,
        "direction": rotation @ direction,
        "start": point + approach_offset * normal,
        "end": point - push_depth * normal,
    }


@dataclass
class PoseMatch:
    """An observed orientation matched to a stable pose.

    pose : int, index of the nearest stable pose (-1 when none is within tolerance)
    angle_error : float, rad, angle between the observed and the stable down vectors
    yaw : float, rad, planar rotation about world z of the canonical pose
    translation : (2,) float, m, planar translation of the canonical pose
    planar : (4, 4) float, world <- canonical: rotation yaw about z and the translation
    """

    pose: int
    angle_error: float
    yaw: float
    translation: np.ndarray
    planar: np.ndarray

    @property
    def matched(self) -> bool:
        return self.pose >= 0


def match_pose(
    observed: np.ndarray, pose_downs: np.ndarray, pose_transforms: np.ndarray, tolerance: float,
    pose_inverses: np.ndarray | None = None,
) -> PoseMatch:
    """Match an observed object pose to the nearest stable pose.

    observed : (4, 4) float, object frame -> world frame (z up, table z = 0)
    pose_downs : (P, 3) float, unit down vectors of the stable poses, object frame
    pose_transforms : (P, 4, 4) float, object -> canonical frame of each pose
    tolerance : float, rad, largest angle between down vectors that still matches
    pose_inverses : (P, 4, 4) float, the transforms' inverses when the caller keeps them

    The observed pose is ``planar @ pose_transforms[pose]`` up to the angle error.
    """
    rotation = observed[:3, :3]
    down = rotation.T @ DOWN
    angles = np.arccos(np.clip(pose_downs @ down, -1.0, 1.0))
    best = int(np.argmin(angles))
    error = float(angles[best])
    inverse = np.linalg.inv(pose_transforms[best]) if pose_inverses is None else pose_inverses[best]
    relative = observed @ inverse
    r = relative[:3, :3]
    yaw = float(np.arctan2(r[1, 0] - r[0, 1], r[0, 0] + r[1, 1]))
    planar = np.eye(4)
    planar[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    planar[:2, 3] = relative[:2, 3]
    return PoseMatch(
        pose=best if error <= tolerance else -1,
        angle_error=error,
        yaw=yaw,
        translation=relative[:2, 3].copy(),
        planar=planar,
    )
