"""schema.frames on its own: the rotations and frames the pipeline builds poses with and the
service matches observed poses with, checked against their definitions (numpy only)."""

from __future__ import annotations

import numpy as np

from schema.frames import DOWN, align_to_down, axis_angle_matrices, canonical_transform, match_pose, tangent_frames, unit, z_to_axes

# Axes where a fixed helper vector can be parallel to the axis: the coordinate axes, both signs,
# the face and body diagonals, and both sides of tangent_frames' switch at |x| = 0.9.
AXES = unit(np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
     [1, 1, 0], [1, 0, 1], [0, 1, 1], [-1, 1, 0], [1, 0, -1], [1, 1, 1], [-1, -1, 1],
     [0.9, np.sqrt(1 - 0.81), 0], [0.9 + 1e-9, np.sqrt(1 - (0.9 + 1e-9) ** 2), 0], [-0.95, 0, 0.3]],
    dtype=float,
))


def random_axes(n: int, seed: int) -> np.ndarray:
    return unit(np.random.default_rng(seed).normal(size=(n, 3)))


def assert_rotations(matrices: np.ndarray) -> None:
    """Each (3, 3) is orthonormal with determinant +1 (a rotation, not a reflection)."""
    identity = np.broadcast_to(np.eye(3), matrices.shape)
    np.testing.assert_allclose(np.swapaxes(matrices, -1, -2) @ matrices, identity, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(matrices), 1.0, atol=1e-12)


def test_unit_normalises_and_leaves_zero_vectors_zero():
    vectors = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, -2.0, 0.0], [0.0, 0.0, 0.0]])
    with np.errstate(all="raise"):  # a zero vector is not divided by its zero norm
        result = unit(vectors)
    np.testing.assert_array_equal(result[[1, 3]], 0.0)
    np.testing.assert_allclose(result[[0, 2]], [[0.6, 0.8, 0.0], [0.0, -1.0, 0.0]], rtol=0, atol=1e-15)
    # Zeros must be written, not inherited: at this size a fresh output buffer is seldom the
    # norm's scratch (zero where the vectors are), so garbage would show.
    many = np.random.default_rng(2).normal(size=(100, 3))
    many[::2] = 0.0
    result = unit(many)
    np.testing.assert_array_equal(result[::2], 0.0)
    np.testing.assert_allclose(np.linalg.norm(result[1::2], axis=-1), 1.0, atol=1e-12)


def test_unit_of_integer_vectors_is_float():
    result = unit(np.array([[3, 4, 0], [0, 0, 0]]))
    assert result.dtype == float
    np.testing.assert_allclose(result, [[0.6, 0.8, 0.0], [0.0, 0.0, 0.0]], rtol=0, atol=1e-15)


def test_tangent_frames_are_orthonormal_and_right_handed_for_every_axis():
    axes = np.concatenate([AXES, random_axes(200, 3)])
    u, v = tangent_frames(axes)
    np.testing.assert_allclose(np.linalg.norm(u, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(v, axis=-1), 1.0, atol=1e-12)
    for a, b in [(u, v), (u, axes), (v, axes)]:
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(u, v), axes, atol=1e-12)  # (u, v, axis) right-handed


def test_z_to_axes_takes_z_onto_each_axis_batched_or_alone():
    axes = np.concatenate([AXES, random_axes(50, 4)])
    rotations = z_to_axes(axes)
    assert rotations.shape == (len(axes), 3, 3)
    assert_rotations(rotations)
    np.testing.assert_allclose(rotations @ [0.0, 0.0, 1.0], axes, atol=1e-12)
    for axis, rotation in zip(axes, rotations):
        np.testing.assert_allclose(z_to_axes(axis), rotation, atol=1e-15)  # one axis is the batch of one
    grid = z_to_axes(axes.reshape(2, -1, 3))  # any leading shape
    np.testing.assert_allclose(grid @ [0.0, 0.0, 1.0], axes.reshape(2, -1, 3), atol=1e-12)


def test_align_to_down_is_a_rotation_onto_down_even_from_straight_up():
    # Straight up (antiparallel to DOWN) and straight down are the special cases; the others
    # lean a hair off them, then anywhere.
    downs = np.concatenate([[[0, 0, 1], [0, 0, -1], [1e-13, 0, 1], [0, 1e-13, -1], [1e-6, 0, 1]], AXES, random_axes(100, 7)])
    for down in downs:
        rotation = align_to_down(down)
        assert_rotations(rotation)
        np.testing.assert_allclose(rotation @ unit(down), DOWN, atol=1e-12)
    np.testing.assert_array_equal(align_to_down([0.0, 0.0, -2.0]), np.eye(3))  # already down: no turn at all


def box_poses() -> tuple[np.ndarray, np.ndarray]:
    """The six stable poses of a 0.2 x 0.1 x 0.06 m box with its centre of mass at the origin:
    down vectors (6, 3) and object -> canonical transforms (6, 4, 4)."""
    hull = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.05, 0.05) for z in (-0.03, 0.03)])
    downs = np.concatenate([np.eye(3), -np.eye(3)])
    return downs, np.array([canonical_transform(d, np.zeros(3), hull) for d in downs])


def test_match_pose_tolerance_is_the_largest_angle_that_still_matches():
    downs, transforms = box_poses()
    tilt = np.eye(4)
    tilt[:3, :3] = axis_angle_matrices(np.array([1.0, 0.0, 0.0]), np.array(0.05))
    for pose in range(len(downs)):
        observed = tilt @ transforms[pose]
        error = match_pose(observed, downs, transforms, np.inf).angle_error
        assert abs(error - 0.05) < 1e-9
        assert match_pose(observed, downs, transforms, error).pose == pose
        assert not match_pose(observed, downs, transforms, np.nextafter(error, 0.0)).matched
