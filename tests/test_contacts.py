"""Candidate pushes: exactly N, evenly spread, statuses, Max-Height action."""

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from shapes import box_object, pose_with_down, random_object

from pipeline.model.collision import collision_object
from pipeline.model.config import ContactConfig
from pipeline.model.contacts import pose_actions, surface_points
from pipeline.model.mesh import model_from_mesh
from pipeline.model.poses import stable_poses
from schema.vocabulary import (
    STATUS_FINGER_COLLISION,
    STATUS_OK,
    STATUS_PUSHES_UP,
    STATUS_TOO_LOW,
)


def test_exactly_n_points_on_the_surface_evenly_spread():
    obj = random_object(5)
    for n in (1, 37, 1000):
        points, normals = surface_points(obj.mesh, n, np.random.default_rng(0))
        assert points.shape == (n, 3) and normals.shape == (n, 3)
    _, distance, _ = trimesh.proximity.closest_point(obj.mesh, points)
    assert distance.max() < 1e-9
    spacing = cKDTree(points).query(points, k=2)[0][:, 1]
    # Even: the closest pair is not much closer than the typical pair.
    assert spacing.min() > 0.5 * np.median(spacing)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def _box_actions(points_object, normals_object, config=ContactConfig()):
    obj = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(obj)
    pose = pose_set.poses[pose_with_down(pose_set, [0, 0, -1])]
    return pose_actions(points_object, normals_object, obj.mesh, collision_object(obj.mesh), pose.transform, config)


def test_statuses_on_a_box():
    points = np.array([
        [0.025, 0.0, 0.10],    # side face, high: ok
        [0.025, 0.0, 0.01],    # side face below 15% of 0.15 m: too low
        [0.0, 0.0, 0.15],      # top face: the push points straight down, which is allowed
        [0.024, 0.0, 0.0],     # bottom face: pushes up (and too low first)
        [0.025, 0.0, 0.0235],  # just above 15%: ok
    ])
    normals = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1], [1, 0, 0]], dtype=float)
    actions = _box_actions(points, normals)
    assert list(actions.status[:5]) == [STATUS_OK, STATUS_TOO_LOW, STATUS_OK, STATUS_TOO_LOW, STATUS_OK]
    assert np.allclose(actions.directions, -actions.normals)


def test_pushes_up_status():
    # A contact high up whose normal points 70 degrees below horizontal: the push points up.
    normal = np.array([np.cos(np.radians(70)), 0, -np.sin(np.radians(70))])
    actions = _box_actions(np.array([[0.025, 0.0, 0.1]]), normal[None])
    assert actions.status[0] == STATUS_PUSHES_UP


def test_finger_collision_in_a_narrow_slot():
    # Two slabs 4 mm apart: a 4 mm-radius finger cannot reach the inner faces.
    left = trimesh.creation.box([0.02, 0.06, 0.1])
    left.apply_translation([-0.012, 0, 0.05])
    right = trimesh.creation.box([0.02, 0.06, 0.1])
    right.apply_translation([0.012, 0, 0.05])
    base = trimesh.creation.box([0.044, 0.06, 0.01])
    base.apply_translation([0, 0, 0.005])
    obj = model_from_mesh(trimesh.util.concatenate([left, right, base]), name="slot")
    pose_set = stable_poses(obj)
    pose = pose_set.poses[pose_with_down(pose_set, [0, 0, -1])]
    points = np.array([[-0.002, 0.0, 0.08], [-0.022, 0.0, 0.08]])  # inner face of left slab; outer face
    normals = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    actions = pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), pose.transform, ContactConfig())
    assert actions.status[0] == STATUS_FINGER_COLLISION
    assert actions.status[1] == STATUS_OK


def test_max_height_action_is_highest_near_vertical_point():
    obj = random_object(2)
    pose_set = stable_poses(obj)
    config = ContactConfig(n_contacts=50)
    points, normals = surface_points(obj.mesh, 50, np.random.default_rng(0))
    for pose in pose_set.poses:
        actions = pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), pose.transform, config)
        assert len(actions.status) == 51 and actions.max_height == 50
        point, normal = actions.points[50], actions.normals[50]
        assert abs(normal[2]) <= np.sin(config.max_height_normal_angle) + 1e-9
        # No steep face reaches meaningfully higher than the chosen point.
        vertices = obj.mesh.vertices @ pose.transform[:3, :3].T + pose.transform[:3, 3]
        steep = np.abs(obj.mesh.face_normals @ pose.transform[:3, :3].T)[:, 2] <= np.sin(config.max_height_normal_angle)
        assert point[2] >= vertices[obj.mesh.faces[steep]][:, :, 2].max() - 1e-3
        assert np.allclose(actions.directions[50], -normal)
