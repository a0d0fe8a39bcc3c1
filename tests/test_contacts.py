"""Candidate pushes: exactly N, evenly spread, statuses, Max-Height action."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from shapes import box_object, pose_with_down, random_object

from pipeline.model.collision import collision_object
from pipeline.model.config import ContactConfig
from pipeline.model.contacts import (
    OffSurface,
    explicit_actions,
    farthest_point_subset,
    finger_collisions,
    max_height_contact,
    pose_actions,
    push_arrays,
    snap_to_surface,
    surface_points,
    with_probes,
)
from pipeline.model.mesh import model_from_mesh
from pipeline.model.outcomes import Actions
from pipeline.model.poses import stable_poses
from pipeline.model.sampling import points_in_triangles
from schema.frames import unit
from schema.vocabulary import (
    STATUS_FINGER_COLLISION,
    STATUS_OK,
    STATUS_PUSHES_UP,
    STATUS_TOO_LOW,
)


def test_exactly_n_points_on_the_surface_evenly_spread():
    obj = random_object(5)
    for n in (1, 37, 1000):
        points, normals = surface_points(obj.mesh, n, np.random.default_rng(0), ContactConfig().oversample)
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
    points, normals = surface_points(obj.mesh, 50, np.random.default_rng(0), config.oversample)
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


def test_points_fill_their_triangle_uniformly():
    # Uniform over a triangle: every point inside it, their mean at its centroid.
    triangle = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.01], [0.01, 0.03, 0.02]])
    n = 20000
    points = points_in_triangles(np.broadcast_to(triangle, (n, 3, 3)), np.random.default_rng(0).random((n, 2)))
    edges = np.stack([triangle[1] - triangle[0], triangle[2] - triangle[0]], axis=1)  # (3, 2)
    weights = np.linalg.lstsq(edges, (points - triangle[0]).T, rcond=None)[0]  # (2, n) barycentric u, v
    assert np.all(weights >= -1e-12) and np.all(weights.sum(axis=0) <= 1 + 1e-12)
    np.testing.assert_allclose(edges @ weights + triangle[0][:, None], points.T, atol=1e-15)  # in the plane
    np.testing.assert_allclose(points.mean(axis=0), triangle.mean(axis=0), atol=5 * 0.02 / np.sqrt(n))


def test_farthest_point_subset_starts_at_point_0_and_takes_the_farthest_next():
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 10.0], [0.0, 0.0, 4.0]])
    # From {0, 10} the nearest-neighbour distances are 1, 2 and 4: z = 4 is taken third.
    np.testing.assert_array_equal(farthest_point_subset(points, 3), [0, 3, 4])
    assert sorted(farthest_point_subset(points, 5)) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="cannot choose 6 points from 5"):
        farthest_point_subset(points, 6)


def test_max_height_contact_lies_on_its_face_a_hair_below_the_top():
    obj = box_object((0.05, 0.08, 0.15))
    mesh = obj.mesh
    point, normal = max_height_contact(mesh.vertices, mesh.faces, mesh.face_normals, ContactConfig().max_height_normal_angle)
    assert normal[2] == pytest.approx(0.0, abs=1e-12)
    assert 0.15 - 1.5e-3 < point[2] < 0.15
    # On the side face the normal names, inside its rectangle.
    side = np.abs(normal).argmax()
    assert abs(point[side]) == pytest.approx((0.025, 0.04)[side], abs=1e-12)
    assert abs(point[1 - side]) < (0.025, 0.04)[1 - side]


def test_max_height_contact_needs_one_steep_face_and_no_more():
    wall = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1]])  # one vertical triangle
    point, _ = max_height_contact(wall, np.array([[0, 1, 2]]), np.array([[0.0, -1.0, 0.0]]), np.radians(15))
    assert 0.098 < point[2] < 0.1
    assert max_height_contact(wall, np.array([[0, 1, 2]]), np.array([[0.0, 0.0, 1.0]]), np.radians(15)) is None


def test_a_pose_with_no_face_near_vertical_has_no_max_height_action():
    # A squat cone: its sides slope 45 degrees, its base faces down; no face within 15 degrees of vertical.
    cone = trimesh.creation.cone(radius=0.05, height=0.05, sections=32)
    points, normals = surface_points(cone, 20, np.random.default_rng(0), ContactConfig().oversample)
    actions = pose_actions(points, normals, cone, collision_object(cone), np.eye(4), ContactConfig())
    assert actions.max_height == -1 and len(actions.status) == 20
    assert actions.status.dtype == np.int8


def test_the_finger_hits_the_table_under_a_low_contact():
    # A horizontal push whose finger (radius 4 mm) would reach below the table; the object is far away.
    far = collision_object(trimesh.creation.box([0.01, 0.01, 0.01]))
    config = ContactConfig()
    heights = np.array([0.5, 1.0, 1.5]) * config.finger_radius
    points = np.column_stack([np.full(3, 1.0), np.zeros(3), heights])
    hits = finger_collisions(far, np.eye(4), points, np.tile([1.0, 0.0, 0.0], (3, 1)), config)
    np.testing.assert_array_equal(hits, [True, False, False])  # touching the table is no hit: the table is z < 0


def test_explicit_pushes_default_to_the_inward_normal():
    obj = box_object((0.05, 0.08, 0.15))
    points = np.array([[0.025, 0.0, 0.1], [0.0, 0.0, 0.15]])  # a side face, the top
    actions = explicit_actions(obj, np.eye(4), points, None)
    np.testing.assert_allclose(actions.normals, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(actions.directions, -actions.normals)
    assert actions.max_height == -1
    assert actions.status.dtype == np.int8 and np.all(actions.status == STATUS_OK)
    pushed = explicit_actions(obj, np.eye(4), points[:1], np.array([[-2.0, 0.0, -2.0]]))
    np.testing.assert_allclose(pushed.directions, [[-np.sqrt(0.5), 0.0, -np.sqrt(0.5)]])


def test_a_pose_with_no_pushable_candidate_checks_no_finger():
    far = collision_object(trimesh.creation.box([0.01, 0.01, 0.01]))
    hits = finger_collisions(far, np.eye(4), np.empty((0, 3)), np.empty((0, 3)), ContactConfig())
    assert hits.shape == (0,) and hits.dtype == bool
    # The squat cone has no Max-Height action; contacts all near its base are too low, so no finger is checked.
    cone = trimesh.creation.cone(radius=0.05, height=0.05, sections=32)
    points = np.array([[0.049, 0.0, 0.001], [0.0, -0.049, 0.001]])
    normals = unit(np.array([[1.0, 0.0, 1.0], [0.0, -1.0, 1.0]]))
    actions = pose_actions(points, normals, cone, collision_object(cone), np.eye(4), ContactConfig())
    assert actions.max_height == -1
    np.testing.assert_array_equal(actions.status, [STATUS_TOO_LOW, STATUS_TOO_LOW])


def test_the_status_limits_are_strict_and_the_max_height_angle_inclusive():
    # MODEL.md (6.4) and (6.5): too low strictly below the fraction of the height, pushing up strictly above
    # the angle. The standing box's pose is the identity, so the heights compared are the ones given here.
    obj = box_object((0.05, 0.08, 0.15))
    height = obj.mesh.vertices[:, 2].max()
    config = ContactConfig(max_up_angle=np.pi / 2)  # sin is exactly 1: a push straight up is at the limit
    points = np.array([[0.025, 0.0, config.min_height_fraction * height], [0.025, 0.0, 0.1]])
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    actions = pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), np.eye(4), config)
    assert actions.status[0] == STATUS_OK
    # Not pushing up; the finger, coming from below along the side face, hits the box instead.
    assert actions.status[1] == STATUS_FINGER_COLLISION
    # A face exactly max_angle off vertical still counts as steep.
    angle = np.radians(15)
    wall = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1]])
    tilted = np.array([[0.0, -np.cos(angle), np.sin(angle)]])
    assert max_height_contact(wall, np.array([[0, 1, 2]]), tilted, angle) is not None


def test_explicit_pushes_off_the_surface_are_refused_naming_the_farthest_and_the_tolerance_is_inclusive():
    obj = box_object((0.05, 0.08, 0.15))
    on, two, five = [0.025, 0.0, 0.1], [0.027, 0.0, 0.1], [0.030, 0.0, 0.1]  # on the +x face, 2 and 5 mm out
    with pytest.raises(OffSurface, match=r"^point 2 \[0.03, 0.0, 0.1\] is 5 mm from the object's surface, more than the 1 mm tolerance; "
                                         r"points are in metres in the pose frame") as refused:
        explicit_actions(obj, np.eye(4), np.array([on, two, five, on]), None)
    assert refused.value.where.startswith("point 2 ") and refused.value.where.endswith("the 1 mm tolerance")
    _, _, distance = snap_to_surface(obj, np.eye(4), np.array([[0.0255, 0.0, 0.1]]))
    assert distance[0] == pytest.approx(5e-4, abs=1e-12)
    np.testing.assert_allclose(explicit_actions(obj, np.eye(4), [0.0255, 0.0, 0.1], None, tolerance=distance[0]).points,
                               [[0.025, 0.0, 0.1]], atol=1e-12)
    with pytest.raises(OffSurface):
        explicit_actions(obj, np.eye(4), [0.0255, 0.0, 0.1], None, tolerance=np.nextafter(distance[0], 0.0))


def test_push_arrays_keep_ordinary_directions_bit_for_bit_and_rescale_extreme_ones_quietly():
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.05, 0.05, (6, 3))
    directions = np.concatenate([rng.normal(size=(3, 3)), 0.01 * rng.normal(size=(3, 3))])  # lengths above and below 1
    got_points, got_directions = push_arrays(points, directions)
    np.testing.assert_array_equal(got_points, points)
    np.testing.assert_array_equal(got_directions, directions)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a length that overflows or underflows float64 is no warning of the caller's
        _, extreme = push_arrays(points[:3], [[1e200, 0.0, 0.0], [0.0, -1e-170, 0.0], [3e-200, 4e-200, 0.0]])
    np.testing.assert_allclose(extreme, [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.75, 1.0, 0.0]], rtol=1e-15)
    # Numbers of any type are floats; text is refused in the pushes' own words.
    got_points, got_directions = push_arrays([[0, 0, 1]], [[1, 0, 0]])
    assert got_points.dtype == float and got_directions.dtype == float
    with pytest.raises(ValueError, match=r"points must be a \(k, 3\) array of numbers \(m, pose frame\), got \[\['a', 'b', 'c'\]\]"):
        push_arrays([["a", "b", "c"]], None)


def test_with_probes_matches_a_push_to_the_first_ok_candidate_within_the_tolerance():
    points = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.1], [0.02, 0.0, 0.1]])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    pool = Actions(points, -directions, directions, np.array([STATUS_TOO_LOW, STATUS_OK, STATUS_OK], dtype=np.int8), max_height=2)
    asked = np.array([[0.0, 0.0, 0.1], [0.02, 0.0, 0.1], [0.02, 0.0, 0.1 + 1e-9]])
    asked_directions = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    pushes = Actions(asked, -asked_directions, asked_directions, np.full(3, STATUS_OK, dtype=np.int8))
    # Tolerance 0 takes only the very candidate: the first push is candidate 1 (candidate 0 is not ok), the
    # second candidate 2, the third, a nanometre off, a probe after the pool.
    actions, n, rows = with_probes(pool, pushes, asked, asked_directions, tolerance=0.0)
    assert n == 3 and actions.max_height == 2
    np.testing.assert_array_equal(rows, [1, 2, 3])
    np.testing.assert_array_equal(actions.points, np.vstack([points, asked[2:]]))
    np.testing.assert_array_equal(actions.status, [STATUS_TOO_LOW, STATUS_OK, STATUS_OK, STATUS_OK])
    np.testing.assert_array_equal(with_probes(pool, pushes, asked, asked_directions)[2], [1, 2, 2])  # within 1e-6 m
    with pytest.raises(ValueError, match=r"^with_probes needs one point and one direction per push: 3 points, 2 directions, 3 pushes$"):
        with_probes(pool, pushes, asked, asked_directions[:2])
