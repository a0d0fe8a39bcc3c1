"""Stable poses, canonical frames, pose matching and quasi-static settling."""

import numpy as np
import pytest
import trimesh
from shapes import boot_object, box_object, pose_with_down, random_object

from pipeline.model.config import PoseConfig
from pipeline.model.poses import face_solid_angles, settle, stable_poses
from schema.frames import axis_angle_matrices, match_pose, transform_points


def test_box_has_six_poses_with_face_area_ordering():
    obj = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(obj)
    assert len(pose_set.poses) == 6
    probabilities = np.array([p.probability for p in pose_set.poses])
    assert np.isclose(probabilities.sum(), 1.0)
    assert np.all(np.diff(probabilities) <= 1e-12)
    # Largest faces (0.08 x 0.15, normal along x) are the most probable poses.
    assert np.allclose(np.abs(pose_set.poses[0].down), [1, 0, 0])
    heights = sorted(round(p.height, 6) for p in pose_set.poses)
    assert heights == [0.05, 0.05, 0.08, 0.08, 0.15, 0.15]


def test_solid_angles_cover_the_sphere():
    obj = random_object(3)
    assert np.isclose(face_solid_angles(obj.hull, obj.center_mass).sum(), 4 * np.pi)


@pytest.mark.parametrize("index", [0, 1, 4, 7])
def test_canonical_frames_rest_on_table_with_com_over_origin(index):
    obj = random_object(index)
    for pose in stable_poses(obj).poses:
        vertices = transform_points(pose.transform, obj.hull.vertices)
        com = transform_points(pose.transform, obj.center_mass[None])[0]
        assert np.isclose(vertices[:, 2].min(), 0.0, atol=1e-12)
        assert np.allclose(com[:2], 0.0, atol=1e-12)
        assert np.isclose(com[2], pose.com_height)
        assert np.allclose(pose.transform[:3, :3] @ pose.down, [0, 0, -1])
        # The centre of mass projects inside the base: the pose is stable.
        edges = pose.base_edges
        direction = edges[:, 1] - edges[:, 0]
        cross = direction[:, 0] * (0 - edges[:, 0, 1]) - direction[:, 1] * (0 - edges[:, 0, 0])
        assert np.all(cross >= -1e-9)


@pytest.mark.parametrize("index", [0, 2, 5, 6, 9])
def test_matches_trimesh_stable_poses(index):
    obj = random_object(index)
    ours = stable_poses(obj, PoseConfig(min_probability=0.0))
    transforms, probabilities = trimesh.poses.compute_stable_poses(obj.mesh, center_mass=obj.center_mass)
    theirs = np.array([np.linalg.inv(t)[:3, :3] @ [0, 0, -1] for t in transforms])
    tolerance = PoseConfig().same_pose_angle
    # Every trimesh pose lies within the merge tolerance of one of ours ...
    angles = np.arccos(np.clip(theirs @ ours.downs.T, -1, 1))
    assert np.all(angles.min(axis=1) <= tolerance + 1e-9)
    # ... and the probability mass agrees once trimesh's poses are merged into ours.
    merged = np.bincount(angles.argmin(axis=1), weights=probabilities, minlength=len(ours.poses))
    assert np.allclose(merged, [p.probability for p in ours.poses], atol=0.02)


@pytest.mark.parametrize("index", range(10))
def test_pose_set_is_closed_under_toppling(index):
    pose_set = stable_poses(random_object(index))
    n = len(pose_set.poses)
    for pose in pose_set.poses:
        assert np.all((pose.edge_final_pose >= 0) & (pose.edge_final_pose < n))
        assert np.all(pose.edge_final_pose[pose.edge_blocked] == pose.index)


def test_box_edges_topple_onto_adjacent_faces():
    obj = box_object()
    pose_set = stable_poses(obj)
    for pose in pose_set.poses:
        edges = pose.base_edges
        direction = edges[:, 1] - edges[:, 0]
        outward = np.column_stack([direction[:, 1], -direction[:, 0], np.zeros(len(edges))])
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        assert not pose.edge_blocked.any()
        for edge, target in enumerate(pose.edge_final_pose):
            # After rolling over an edge the box rests on the face that faced outward there.
            down_in_pose = pose.transform[:3, :3] @ pose_set.poses[target].down
            assert np.allclose(down_in_pose, outward[edge], atol=1e-9)


def test_overhang_blocks_topple_over_its_edge():
    obj = boot_object()
    pose_set = stable_poses(obj)
    standing = pose_with_down(pose_set, [0, 0, -1])
    pose = pose_set.poses[standing]
    toe_edge = np.flatnonzero(np.isclose(pose.base_edges[:, :, 0], pose.base_edges[:, :, 0].max()).all(axis=1))
    assert len(toe_edge) == 1
    assert pose.edge_blocked[toe_edge[0]]
    assert pose.edge_final_pose[toe_edge[0]] == standing
    assert pose.edge_blocked.sum() == 1


def _planar(yaw, xy):
    planar = np.eye(4)
    planar[:3, :3] = axis_angle_matrices(np.array([0.0, 0, 1]), np.array(yaw))
    planar[:2, 3] = xy
    return planar


def test_match_pose_recovers_planar_transform():
    obj = random_object(4)
    pose_set = stable_poses(obj)
    tolerance = PoseConfig().same_pose_angle
    rng = np.random.default_rng(1)
    for pose in pose_set.poses:
        yaw, xy = rng.uniform(-np.pi, np.pi), rng.uniform(-0.5, 0.5, 2)
        observed = _planar(yaw, xy) @ pose.transform
        match = match_pose(observed, pose_set.downs, pose_set.transforms, tolerance)
        assert match.pose == pose.index
        assert match.angle_error < 1e-7
        assert np.isclose(np.cos(match.yaw - yaw), 1.0) and np.allclose(match.translation, xy)
        assert np.allclose(match.planar @ pose.transform, observed, atol=1e-9)


def test_match_pose_tolerates_small_tilt_and_rejects_large():
    obj = box_object()
    pose_set = stable_poses(obj)
    pose = pose_set.poses[0]
    tolerance = PoseConfig().same_pose_angle
    tilt = np.eye(4)
    tilt[:3, :3] = axis_angle_matrices(np.array([0.0, 1, 0]), np.array(np.radians(5)))
    assert match_pose(tilt @ pose.transform, pose_set.downs, pose_set.transforms, tolerance).pose == pose.index
    tilt[:3, :3] = axis_angle_matrices(np.array([0.0, 1, 0]), np.array(np.radians(30)))
    far = match_pose(tilt @ pose.transform, pose_set.downs, pose_set.transforms, tolerance)
    assert far.pose == -1 and not far.matched and far.angle_error > tolerance


def test_settle_from_tilted_box():
    obj = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(obj)
    standing = pose_with_down(pose_set, [0, 0, -1])
    # Apex over the 0.05-wide bottom edge is atan(0.025 / 0.075) = 18.4 degrees about y.
    for degrees, expected_down in ((10, [0, 0, -1]), (-10, [0, 0, -1]), (30, [1, 0, 0]), (-30, [-1, 0, 0])):
        rotation = axis_angle_matrices(np.array([0.0, 1, 0]), np.array(np.radians(degrees)))
        assert settle(pose_set, obj, rotation) == pose_with_down(pose_set, expected_down)
    assert settle(pose_set, obj, np.eye(3)) == standing


def test_settle_is_consistent_with_canonical_transforms():
    obj = random_object(8)
    pose_set = stable_poses(obj)
    for pose in pose_set.poses:
        assert settle(pose_set, obj, pose.transform[:3, :3]) == pose.index
