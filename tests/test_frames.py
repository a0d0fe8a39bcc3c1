"""schema.frames on its own: the rotations and frames the pipeline builds poses with and the
service matches observed poses with, checked against their definitions (numpy only)."""

from __future__ import annotations

import numpy as np

from schema.frames import (
    DOWN,
    align_to_down,
    axis_angle_matrices,
    canonical_transform,
    match_pose,
    place_push,
    tangent_frames,
    transform_points,
    unit,
    z_to_axes,
)

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


def test_axis_angle_matrices_are_rodrigues_rotations_about_any_axis():
    # Rodrigues' vector form, v cos a + (k x v) sin a + k (k . v)(1 - cos a), computed without the matrix,
    # for axes with every component non-zero (align_to_down's axes all have z = 0).
    rng = np.random.default_rng(5)
    axes = np.concatenate([AXES, random_axes(100, 5)])
    angles = rng.uniform(-np.pi, np.pi, len(axes))
    vectors = rng.normal(size=(len(axes), 3))
    matrices = axis_angle_matrices(axes, angles)
    assert_rotations(matrices)
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    expected = vectors * c + np.cross(axes, vectors) * s + axes * np.einsum("ij,ij->i", axes, vectors)[:, None] * (1 - c)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", matrices, vectors), expected, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", matrices, axes), axes, atol=1e-12)  # the axis stays put
    # Right-handed: a quarter turn about z takes x to y, a third of a turn about the body diagonal
    # cycles the axes x -> y -> z -> x (the matrices' columns are the images of x, y and z).
    np.testing.assert_allclose(axis_angle_matrices(np.array([0.0, 0.0, 1.0]), np.array(np.pi / 2)),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(axis_angle_matrices(unit(np.ones(3)), np.array(2 * np.pi / 3)),
                               [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)


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


def test_place_push_puts_a_pose_frame_push_in_the_world_with_the_finger_line_along_its_normal():
    # Pose frame -> world: a quarter turn about z, (x, y, z) -> (-y, x, z), then a shift.
    pose_to_world = np.eye(4)
    pose_to_world[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    pose_to_world[:3, 3] = [0.5, -0.2, 0.01]
    point, normal, direction = np.array([0.03, 0.01, 0.05]), unit(np.array([1.0, 2.0, 2.0])), np.array([-0.6, 0.0, -0.8])
    world = place_push(pose_to_world, point, normal, direction, 0.015, 0.04)
    assert set(world) == {"point", "normal", "direction", "start", "end"}
    np.testing.assert_allclose(world["point"], [0.5 - 0.01, -0.2 + 0.03, 0.01 + 0.05], rtol=0, atol=1e-15)
    np.testing.assert_allclose(world["normal"], np.array([-2.0, 1.0, 2.0]) / 3, rtol=0, atol=1e-15)
    np.testing.assert_allclose(world["direction"], [0.0, -0.6, -0.8], rtol=0, atol=1e-15)
    # The finger starts approach_offset outside the surface along the outward normal and ends push_depth inside.
    np.testing.assert_allclose(world["start"], world["point"] + 0.015 * np.array([-2.0, 1.0, 2.0]) / 3, rtol=0, atol=1e-15)
    np.testing.assert_allclose(world["end"], world["point"] - 0.04 * np.array([-2.0, 1.0, 2.0]) / 3, rtol=0, atol=1e-15)


def test_place_push_round_trips_through_an_observed_pose():
    # A box observed in each stable pose, turned and shifted on the table and a little tilted: a surface
    # point and normal given in the object frame, taken to the pose frame and placed through O T^-1 (as the
    # service and plan place pushes), land where the observation puts them, and come back through its inverse.
    _, transforms = box_poses()
    rng = np.random.default_rng(9)
    point, normal = np.array([0.1, 0.02, -0.01]), np.array([1.0, 0.0, 0.0])  # on the +x face
    for pose, transform in enumerate(transforms):
        observed = np.eye(4)
        observed[:3, :3] = axis_angle_matrices(random_axes(1, pose)[0], np.array(0.01)) @ axis_angle_matrices(
            np.array([0.0, 0.0, 1.0]), np.array(rng.uniform(-np.pi, np.pi)))
        observed[:3, 3] = [*rng.uniform(-0.5, 0.5, 2), 0.002]
        observed = observed @ transform
        pose_to_world = observed @ np.linalg.inv(transform)
        pose_point, pose_normal = transform_points(transform, point[None])[0], transform[:3, :3] @ normal
        world = place_push(pose_to_world, pose_point, pose_normal, -pose_normal, 0.015, 0.04)
        np.testing.assert_allclose(world["point"], transform_points(observed, point[None])[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(world["normal"], observed[:3, :3] @ normal, rtol=0, atol=1e-12)
        np.testing.assert_allclose(world["direction"], -world["normal"], rtol=0, atol=1e-15)
        back = transform_points(np.linalg.inv(observed), np.array([world["start"], world["end"]]))
        np.testing.assert_allclose(back, [point + 0.015 * normal, point - 0.04 * normal], rtol=0, atol=1e-12)
