"""Stable poses, canonical frames, pose matching and quasi-static settling."""

import re
import warnings

import numpy as np
import pytest
import trimesh
from shapes import boot_object, box_object, pose_with_down, random_object

from pipeline.model.config import PoseConfig
from pipeline.model.mesh import MeshError, model_from_mesh
from pipeline.model.poses import (
    congruent_yaw,
    face_neighbors,
    face_solid_angles,
    settle,
    sink_faces,
    stability_margin,
    stable_poses,
    topple_graph,
)
from schema.frames import axis_angle_matrices, match_pose, transform_points


def test_box_has_six_poses_with_face_area_ordering():
    obj = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(obj, merge_symmetric=False)
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
    for pose in stable_poses(obj, merge_symmetric=False).poses:
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
        # An edge that does not leave the pose (blocked, or a topple back into it; most of these
        # objects have some) rolls on nowhere (C.8) and has nothing onward (C.18).  None of them
        # merges symmetric poses, where a topple into a merged twin would count here too.
        assert pose_set.equivalents is None
        stays = pose.edge_blocked | (pose.edge_final_pose == pose.index)
        assert np.all(pose.edge_momentum_pose[stays] == pose.index) and np.all(pose.edge_onward_pose[stays] == pose.index)


def test_box_edges_topple_onto_adjacent_faces():
    obj = box_object()
    pose_set = stable_poses(obj, merge_symmetric=False)
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
    pose_set = stable_poses(obj, merge_symmetric=False)
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
    pose_set = stable_poses(obj, merge_symmetric=False)
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
    pose_set = stable_poses(obj, merge_symmetric=False)
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
    pose_set = stable_poses(obj, merge_symmetric=False)
    standing = pose_with_down(pose_set, [0, 0, -1])
    # Apex over the 0.05-wide bottom edge is atan(0.025 / 0.075) = 18.4 degrees about y.
    for degrees, expected_down in ((10, [0, 0, -1]), (-10, [0, 0, -1]), (30, [1, 0, 0]), (-30, [-1, 0, 0])):
        rotation = axis_angle_matrices(np.array([0.0, 1, 0]), np.array(np.radians(degrees)))
        assert settle(pose_set, obj, rotation) == pose_with_down(pose_set, expected_down)
    assert settle(pose_set, obj, np.eye(3)) == standing


def test_settle_is_consistent_with_canonical_transforms():
    obj = random_object(8)
    pose_set = stable_poses(obj, merge_symmetric=False)
    for pose in pose_set.poses:
        assert settle(pose_set, obj, pose.transform[:3, :3]) == pose.index


def _cylinder(sections=32):
    return model_from_mesh(trimesh.creation.cylinder(radius=0.03, height=0.1, sections=sections), name="can")


def test_symmetric_cylinder_merges_into_two_poses_that_match_any_roll():
    import pipeline as toppledb

    obj = _cylinder()
    assert len(stable_poses(obj, merge_symmetric=False).poses) == 34, "one pose per hull face without merging"
    merged = stable_poses(obj, merge_symmetric=True)
    assert len(merged.poses) == 2
    side, end = merged.poses
    assert np.isclose(side.com_height, 0.03 * np.cos(np.pi / 32)) and np.isclose(end.com_height, 0.05)
    assert np.isclose(side.probability + end.probability, 1.0) and side.probability > end.probability
    assert [len(e) for e in merged.equivalents] == [32, 2]
    assert np.all((side.edge_final_pose >= 0) & (side.edge_final_pose < 2))
    assert set(end.edge_final_pose.tolist()) == {0}, "an end topples onto the side"
    # Every merged orientation puts the hull exactly where the pose's own transform does.
    reference = np.sort(transform_points(side.transform, obj.hull.vertices).round(9), axis=0)
    for transform in merged.equivalents[0]:
        np.testing.assert_allclose(np.sort(transform_points(transform, obj.hull.vertices).round(9), axis=0), reference, atol=1e-8)

    # Lying rolled by five facets and turned, upside down on its other end: both still match.
    roll = trimesh.transformations.rotation_matrix(5 * 2 * np.pi / 32, [0, 0, 1])  # about the cylinder's axis
    observed = trimesh.transformations.rotation_matrix(0.4, [0, 0, 1]) @ side.transform @ roll
    match = toppledb.match_pose(observed, merged)
    assert match.pose == 0 and match.angle_error < 1e-9 and abs(match.z_offset) < 1e-9
    flipped = end.transform @ trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0])
    assert toppledb.match_pose(flipped, merged).pose == 1
    assert toppledb.match_pose(observed, merged.poses).pose == -1, "without the equivalents it would not match"


def test_box_merges_opposite_faces_only_when_asked():
    obj = box_object((0.05, 0.08, 0.15))
    merged = stable_poses(obj, merge_symmetric=True)
    assert len(merged.poses) == 3 and [len(e) for e in merged.equivalents] == [2, 2, 2]
    plain = stable_poses(obj, merge_symmetric=False)
    assert np.allclose(sorted(p.probability for p in merged.poses),
                       sorted(np.add.reduceat(sorted(p.probability for p in plain.poses), [0, 2, 4])))


def test_congruent_yaw_finds_the_turn_or_none():
    from pipeline.model.poses import congruent_yaw

    square = trimesh.creation.box([0.04, 0.04, 0.1]).vertices
    turned = square @ trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])[:3, :3].T
    yaw = congruent_yaw(square, turned, 1e-9)
    assert yaw is not None and np.isclose(np.mod(yaw - 0.3, np.pi / 2), 0, atol=1e-9) | np.isclose(np.mod(yaw - 0.3, np.pi / 2), np.pi / 2)
    oblong = trimesh.creation.box([0.04, 0.05, 0.1]).vertices
    assert congruent_yaw(square, oblong, 1e-6) is None


def test_a_sphere_has_no_stable_pose_worth_pushing():
    for mesh in (trimesh.creation.uv_sphere(radius=0.05), trimesh.creation.icosphere(subdivisions=2, radius=0.05)):
        with pytest.raises(MeshError, match="ball: no stable pose worth pushing: nearly a sphere"):
            stable_poses(model_from_mesh(mesh, name="ball"))
    assert len(stable_poses(_cylinder(12), merge_symmetric=False).poses) == 14, "a can is not a ball"
    assert len(stable_poses(box_object((0.1, 0.1, 0.1)), merge_symmetric=True).poses) == 1, "a cube is one pose"


@pytest.mark.parametrize("index", [0, 3])
def test_face_neighbours_share_the_edge_opposite_each_vertex(index):
    hull = random_object(index).hull
    neighbours = face_neighbors(hull)
    for f, face in enumerate(hull.faces):
        for k in range(3):
            edge = {face[(k + 1) % 3], face[(k + 2) % 3]}
            assert neighbours[f, k] != f and edge <= set(hull.faces[neighbours[f, k]])


def test_an_open_surface_has_no_face_neighbours():
    lid = trimesh.creation.box([0.1, 0.1, 0.1])
    lid.update_faces(np.arange(len(lid.faces)) != 0)  # one triangle gone: three edges with one face
    with pytest.raises(ValueError, match="^convex hull is not a closed two-manifold$"):
        face_neighbors(lid)


@pytest.mark.parametrize("index", [0, 1, 2, 5])
def test_a_face_topples_across_the_edge_its_centre_of_mass_path_leaves_it_by(index):
    # The path from the face's centroid to the centre of mass's projection on its plane, crossed
    # with each edge's segment in the plane: the edge it leaves the face by, and the face across
    # it is the next one.  Faces whose projection lies beyond a corner (two edges
    # crossed) are where the order matters.
    obj = random_object(index)
    hull, com = obj.hull, obj.center_mass
    following = topple_graph(hull, com)
    corners = 0
    for f, (triangle, normal) in enumerate(zip(hull.triangles, hull.face_normals)):
        if following[f] == f:
            continue
        start = triangle.mean(axis=0)
        target = com - np.dot(com - triangle[0], normal) * normal
        crossings = []
        for k in range(3):
            a, b = triangle[(k + 1) % 3], triangle[(k + 2) % 3]
            # start + t (target - start) = a + s (b - a), solved in the plane
            (t, s), *_ = np.linalg.lstsq(np.column_stack([target - start, a - b]), a - start, rcond=None)
            if t > 0 and -1e-9 <= s <= 1 + 1e-9:
                crossings.append((t, k))
        # Edge lines that separate the centroid from the target: two when it lies beyond a corner.
        separating = 0
        for k in range(3):
            a, b = triangle[(k + 1) % 3], triangle[(k + 2) % 3]
            side = [np.dot(np.cross(b - a, point - a), normal) for point in (start, target)]
            separating += side[0] * side[1] < 0
        corners += separating == 2
        _, k = min(crossings)
        shared = {hull.faces[f][(k + 1) % 3], hull.faces[f][(k + 2) % 3]}
        across = [g for g, face in enumerate(hull.faces) if g != f and shared <= set(face)]
        assert following[f] == across[0]
    assert corners > 0


def test_sinks_are_found_at_the_end_of_long_chains_and_cycles_are_refused():
    chain = np.append(np.arange(1, 100), 99)  # face i rolls onto i + 1; the last rests
    np.testing.assert_array_equal(sink_faces(chain), np.full(100, 99))
    with pytest.raises(ValueError, match="^the topple graph has a cycle$"):
        sink_faces(np.array([1, 2, 0, 3]))


@pytest.mark.parametrize("min_probability", [0.3, 0.99])
def test_improbable_poses_are_kept_when_a_kept_pose_topples_onto_them(min_probability):
    # A 5 x 8 x 15 cm box, each face its own pose: none reaches 0.3, so the most probable is kept,
    # and with it every pose its topples reach, however improbable.
    pose_set = stable_poses(box_object((0.05, 0.08, 0.15)), PoseConfig(min_probability=min_probability), merge_symmetric=False)
    n = len(pose_set.poses)
    assert n > 1 and all(p.probability < min_probability for p in pose_set.poses)
    assert pose_set.poses[0].probability == max(p.probability for p in pose_set.poses)
    for pose in pose_set.poses:
        assert np.all((pose.edge_final_pose >= 0) & (pose.edge_final_pose < n))


@pytest.mark.parametrize("index", [0, 8, 16])
def test_faces_draining_into_a_left_out_pose_have_none(index):
    obj = random_object(index)
    pose_set = stable_poses(obj)
    sink = sink_faces(topple_graph(obj.hull, obj.center_mass))
    assert np.any(pose_set.face_pose < 0) and pose_set.face_pose.min() == -1
    for f, pose in enumerate(pose_set.face_pose):
        resting = obj.hull.face_normals[sink[f]]  # the down vector of the face it comes to rest on
        angles = [np.arccos(np.clip(np.dot(p.down, resting), -1, 1)) for p in pose_set.poses]
        if pose >= 0:
            assert angles[pose] <= PoseConfig().same_pose_angle + 1e-9
        else:
            assert min(angles) > PoseConfig().same_pose_angle


def test_symmetry_is_to_a_millionth_of_the_size():
    # A 5 x 8 x 15 cm box (diagonal 17.7 cm) with one corner moved 0.35 um, twice a millionth of
    # the diagonal: not symmetric any more, while a move of half a millionth still is.
    def nudged(by):
        mesh = trimesh.creation.box([0.05, 0.08, 0.15])
        corner = np.flatnonzero(np.all(mesh.vertices > 0, axis=1))[0]
        vertices = mesh.vertices.copy()
        vertices[corner, 0] += by
        mesh = trimesh.Trimesh(vertices, mesh.faces)
        mesh.apply_translation([0, 0, 0.075])
        return model_from_mesh(mesh, mass=0.25, name="nudged")

    millionth = 1e-6 * np.linalg.norm([0.05, 0.08, 0.15])
    assert len(stable_poses(nudged(0.5 * millionth), merge_symmetric=True).poses) == 3
    assert len(stable_poses(nudged(2.0 * millionth), merge_symmetric=True).poses) > 3


def test_a_ball_anywhere_is_refused_with_its_margin():
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    ball.apply_translation([1.0, 2.0, 3.0])
    with pytest.raises(MeshError, match="within 5% of its farthest point"):
        stable_poses(model_from_mesh(ball, name="ball"))


def test_match_arrays_list_every_orientation_that_is_a_pose():
    obj = box_object((0.05, 0.08, 0.15))
    plain = stable_poses(obj, merge_symmetric=False)
    assert plain.equivalents is None
    downs, transforms, owner = plain.match_arrays()
    np.testing.assert_array_equal(owner, np.arange(6))
    merged = stable_poses(obj, merge_symmetric=True)
    downs, transforms, owner = merged.match_arrays()
    np.testing.assert_array_equal(owner, [0, 0, 1, 1, 2, 2])
    # Each orientation's transform turns its down vector straight down.
    np.testing.assert_allclose(np.einsum("mij,mj->mi", transforms[:, :3, :3], downs), np.tile([0.0, 0.0, -1.0], (6, 1)), atol=1e-12)


def test_congruent_yaw_anchors_on_a_point_off_the_axis():
    # A square pyramid listed apex first: the apex is on the axis, where azimuth means nothing.
    pyramid = np.array([[0.0, 0.0, 0.05], [0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.03, 0.0, 0.0], [0.0, -0.03, 0.0]])
    turned = pyramid @ trimesh.transformations.rotation_matrix(0.4, [0, 0, 1])[:3, :3].T
    yaw = congruent_yaw(pyramid, turned, 1e-9)
    assert yaw is not None and np.isclose(np.mod(yaw - 0.4 + 1e-12, np.pi / 2), 0, atol=1e-9)


def test_a_zero_area_sliver_on_the_hull_rolls_on_without_a_warning():
    """The xArm 6 base's hull (pybullet_data, scaled as the parts set has it) keeps a sliver of 1.6e-13 m^2,
    whose barycentric coordinates divide by zero: it is never a resting face, and no RuntimeWarning reaches
    the dataset job's output."""
    import warnings

    import pybullet_data

    mesh = trimesh.load(f"{pybullet_data.getDataPath()}/xarm/xarm_description/meshes/xarm6/visual/base.stl", force="mesh")
    mesh.apply_scale(0.773003)
    hull = mesh.convex_hull
    sliver = np.flatnonzero(hull.area_faces < 1e-12)
    assert len(sliver) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rolls_onto = topple_graph(hull, hull.center_mass)
    assert rolls_onto[sliver[0]] != sliver[0]
    rests_on = sink_faces(rolls_onto)[sliver[0]]
    assert rests_on != sliver[0] and rolls_onto[rests_on] == rests_on


def _rectangle_solid_angle(a, b, d):
    """Solid angle (sr) of an a x b rectangle seen from distance d above its centre."""
    return 4.0 * np.arctan(a * b / (2.0 * d * np.sqrt(4.0 * d**2 + a**2 + b**2)))


@pytest.mark.parametrize("merge_symmetric", [False, True])
def test_a_box_pose_is_as_probable_as_its_face_looks_from_the_centre_of_mass(merge_symmetric):
    # Each face drains only into itself: a pose's probability is its face's solid angle over 4 pi
    # (twice that when the opposite face, its turned twin, is merged into it).
    size = np.array([0.05, 0.08, 0.15])
    pose_set = stable_poses(box_object(tuple(size)), merge_symmetric=merge_symmetric)
    assert np.isclose(pose_set.probabilities.sum(), 1.0)
    for pose in pose_set.poses:
        axis = int(np.argmax(np.abs(pose.down)))
        a, b = np.delete(size, axis)
        faces = 2 if merge_symmetric else 1
        assert pose.probability == pytest.approx(faces * _rectangle_solid_angle(a, b, size[axis] / 2) / (4 * np.pi), rel=1e-12)


def test_a_box_pose_tips_at_its_apex_over_each_base_edge_and_its_margin_is_the_nearest_edge():
    # Resting on a face of half sides (h1, h2) with the centre of mass at height z above its
    # centre: the centre of mass passes over an edge after turning atan(h / z), and the nearest
    # edges, h_min away, give the margin.
    size = np.array([0.05, 0.08, 0.15])
    obj = box_object(tuple(size))
    for pose in stable_poses(obj, merge_symmetric=False).poses:
        axis = int(np.argmax(np.abs(pose.down)))
        half, height = np.delete(size, axis) / 2, size[axis] / 2
        np.testing.assert_allclose(np.sort(pose.apex_angle), np.sort(np.repeat(np.arctan2(half, height), 2)), atol=1e-12)
        margin, edge = stability_margin(pose, obj.center_mass)
        assert margin == pytest.approx(half.min(), abs=1e-12)
        assert pose.apex_angle[edge] == pytest.approx(np.arctan2(half.min(), height), abs=1e-12)


def test_the_margin_is_negative_when_the_centre_of_mass_lies_beyond_an_edge():
    box = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(box, merge_symmetric=False)
    standing = pose_set.poses[pose_with_down(pose_set, [0, 0, -1])]
    beyond = box.center_mass + np.array([0.0, 0.043, 0.0])  # 3 mm past the +y edge, 0.04 m out
    margin, edge = stability_margin(standing, beyond)
    assert margin == pytest.approx(-0.003, abs=1e-12)
    outward = np.cross(standing.base_edges[edge, 1] - standing.base_edges[edge, 0], [0, 0, 1])
    np.testing.assert_allclose(outward / np.linalg.norm(outward), standing.transform[:3, :3] @ [0, 1, 0], atol=1e-12)


def _keel(left_degrees=2.0, right_degrees=3.0):
    """A 6 cm wide, 8 cm long, 6 cm high block whose bottom is a shallow keel: two faces rising
    ``left_degrees`` and ``right_degrees`` from a ridge along y.  It rests on either face, their
    down vectors 5 degrees apart, within ``same_pose_angle`` (10 degrees)."""
    w, height = 0.03, 0.06
    section = [(0.0, 0.0), (w, w * np.tan(np.radians(right_degrees))), (w, height), (-w, height),
               (-w, w * np.tan(np.radians(left_degrees)))]
    points = np.array([(x, y, z) for x, z in section for y in (-0.04, 0.04)])
    return model_from_mesh(trimesh.convex.convex_hull(points), mass=0.2, name="keel")


def test_sinks_within_the_same_pose_angle_merge_into_the_more_probable_ones_pose():
    obj = _keel()
    fine = stable_poses(obj, PoseConfig(min_probability=0.0, same_pose_angle=np.radians(1.0)), merge_symmetric=False)
    coarse = stable_poses(obj, PoseConfig(min_probability=0.0), merge_symmetric=False)
    keel = [p for p in fine.poses if p.down[2] < -0.99]
    assert len(keel) == 2 and len(coarse.poses) == len(fine.poses) - 1
    assert np.degrees(np.arccos(np.dot(keel[0].down, keel[1].down))) == pytest.approx(5.0, abs=1e-9)
    likely, unlikely = sorted(keel, key=lambda p: -p.probability)
    assert likely.probability > unlikely.probability
    # One pose with both faces' probability and the more probable face's down vector; the rest as they were.
    merged = coarse.poses[pose_with_down(coarse, likely.down, atol=1e-12)]
    assert merged.probability == pytest.approx(likely.probability + unlikely.probability, rel=1e-12)
    assert np.isclose(fine.probabilities.sum(), 1.0) and np.isclose(coarse.probabilities.sum(), 1.0)
    for pose in fine.poses:
        if pose.index not in (likely.index, unlikely.index):
            assert coarse.poses[pose_with_down(coarse, pose.down, atol=1e-12)].probability == pose.probability
    # Released resting on the less probable face, it settles into the merged pose.
    assert settle(coarse, obj, unlikely.transform[:3, :3]) == merged.index
    assert settle(fine, obj, unlikely.transform[:3, :3]) == unlikely.index


def test_settling_a_merged_object_names_the_merged_pose_without_a_warning():
    obj = box_object((0.05, 0.08, 0.15))
    merged = stable_poses(obj, merge_symmetric=True)
    _, transforms, owner = merged.match_arrays()
    assert merged.face_pose.shape == (len(obj.hull.faces),) and set(merged.face_pose.tolist()) == {0, 1, 2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the box's side faces meet a straight down vector edge on: n . down = 0
        for transform, pose in zip(transforms, owner):
            assert settle(merged, obj, transform[:3, :3]) == pose


def test_merged_poses_alone_are_kept_when_none_is_probable_enough():
    # No pair of a 5 x 8 x 15 cm box's faces reaches 0.99: the most probable pair is kept, and its
    # topples reach the other two; a merged twin is never a pose of its own.
    obj = box_object((0.05, 0.08, 0.15))
    merged = stable_poses(obj, PoseConfig(min_probability=0.99), merge_symmetric=True)
    assert len(merged.poses) == 3 and [len(e) for e in merged.equivalents] == [2, 2, 2]
    assert np.isclose(merged.probabilities.sum(), 1.0) and np.all(merged.probabilities < 0.99)


def test_a_topple_graph_with_a_cycle_refuses_the_object(monkeypatch):
    import pipeline.model.poses as poses_module

    obj = box_object()
    monkeypatch.setattr(poses_module, "topple_graph", lambda hull, com: np.roll(np.arange(len(hull.faces)), 1))
    with pytest.raises(MeshError, match=r"^box: the topple graph has a cycle$"):
        stable_poses(obj)


def test_settle_names_what_it_was_given_when_it_is_no_rotation():
    obj = box_object()
    pose_set = stable_poses(obj, merge_symmetric=False)
    name = "settle's rotation"
    text = [["a", "b", "c"]] * 3
    cases = [
        (np.eye(4), f"{name} must be a (3, 3) rotation, got a (4, 4) matrix: pass its upper-left 3x3 (transform[:3, :3])"),
        ([[1, 0, 0], [0, 1]], f"{name} must be a finite (3, 3) rotation, got [[1, 0, 0], [0, 1]]"),
        (text, f"{name} must be a finite (3, 3) rotation, got {text!r}"),
        (np.eye(2), f"{name} must be a finite (3, 3) rotation, got [[1., 0.], [0., 1.]]"),
        (np.full((3, 3), np.nan), f"{name} must be a finite (3, 3) rotation, got [[nan, nan, nan], [nan, nan, nan], [nan, nan, nan]]"),
        (np.ones((2, 8)), f"{name} must be a finite (3, 3) rotation, got [{', '.join(['[' + ', '.join(['1.'] * 8) + ']'] * 2)}]"),
        (np.ones(17), f"{name} must be a finite (3, 3) rotation, got an array of shape (17,)"),  # past 16 values, the shape
        (np.eye(5), f"{name} must be a finite (3, 3) rotation, got an array of shape (5, 5)"),
    ]
    for given, message in cases:
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            settle(pose_set, obj, given)
    # A scaled matrix would give a down vector all the same: refused, its values shown.
    with pytest.raises(ValueError, match=r"^settle's rotation is not a rotation: its columns are not orthonormal .*; "
                                         r"got \[\[2\., 0\., 0\.\], \[0\., 2\., 0\.\], \[0\., 0\., 2\.\]\]$"):
        settle(pose_set, obj, 2 * np.eye(3))
    with pytest.raises(ValueError, match=r"^settle's rotation is not a rotation: .*; got \[\[0\.3333, 0\.3333, 0\.3333\], "):
        settle(pose_set, obj, np.full((3, 3), 1 / 3))  # values to four decimals
    assert settle(pose_set, obj, np.eye(3, dtype=int)) == settle(pose_set, obj, np.eye(3))


def test_an_open_surface_rests_as_its_convex_hull_does():
    # A can without its lids encloses no volume: its poses, their probabilities and where each
    # topple and roll lands are those of the closed can, whose hull it shares.
    can = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=12)
    tube = model_from_mesh(trimesh.Trimesh(can.vertices, can.faces[np.abs(can.face_normals[:, 2]) < 0.5]), name="tube")
    closed = model_from_mesh(can, name="can")
    assert not tube.mesh.is_volume and np.allclose(tube.center_mass, closed.center_mass, atol=1e-12)
    ours, theirs = (stable_poses(obj, merge_symmetric=False) for obj in (tube, closed))
    assert len(ours.poses) == len(theirs.poses) == 14
    # The hulls' faces, and so the poses and their base edges, may be listed in other orders: poses
    # are matched by down vector, and a pose's landings compared as the set of their down vectors.
    def landings(pose_set, pose, name):
        return np.unique(pose_set.downs[getattr(pose, name)].round(9), axis=0)

    for mine in ours.poses:
        other = theirs.poses[pose_with_down(theirs, mine.down, atol=1e-12)]
        assert mine.probability == pytest.approx(other.probability, abs=1e-12)
        for name in ("edge_final_pose", "edge_rolled_pose", "edge_momentum_pose", "edge_onward_pose"):
            np.testing.assert_allclose(landings(ours, mine, name), landings(theirs, other, name), atol=1e-9)


def _resting_facet(obj, pose):
    """Facet (its lowest hull face) the pose rests on."""
    from pipeline.model.poses import facet_ids

    return int(facet_ids(obj.hull)[np.argmax(obj.hull.face_normals @ pose.down)])


def test_poses_of_equal_probability_are_listed_in_the_order_of_their_facets():
    # The 32-sided can's sides tie in probability (to the last bit, many of them): their order,
    # and so every pose's index, follows the hull's facets, not the sort algorithm.
    obj = _cylinder()
    plain = stable_poses(obj, PoseConfig(min_probability=0.0), merge_symmetric=False)
    ties = 0
    for before, after in zip(plain.poses, plain.poses[1:]):
        assert before.probability >= after.probability
        if before.probability == after.probability:
            ties += 1
            assert _resting_facet(obj, before) < _resting_facet(obj, after)
    assert ties >= 10
    # Merged, a pose is represented by the orientation the unmerged list puts first.
    merged = stable_poses(obj, PoseConfig(min_probability=0.0), merge_symmetric=True)
    for pose in merged.poses:
        first = next(p for p in plain.poses if any(np.allclose(e[:3, :3] @ p.down, [0, 0, -1], atol=1e-9)
                                                 for e in merged.equivalents[pose.index]))
        np.testing.assert_allclose(pose.down, first.down, atol=1e-12)


@pytest.mark.parametrize("index", [0, 23, 33, 35])
def test_a_landing_in_a_pose_left_out_falls_back_to_the_thesis_s_and_one_kept_stays(index):
    # Leaving improbable poses out renumbers the rest and sends a roll (C.6), a roll-on (C.8) or an
    # onward fall (C.18) into a left-out pose back to the quasi-static landing; every other landing
    # is the same pose, pose 0 (the most probable, in both sets) included.
    obj = random_object(index)
    every = stable_poses(obj, PoseConfig(min_probability=0.0), merge_symmetric=False)
    kept = stable_poses(obj, merge_symmetric=False)
    assert len(kept.poses) < len(every.poses)
    renumber = np.full(len(every.poses), -1)
    for pose in every.poses:
        match = [p.index for p in kept.poses if np.allclose(p.down, pose.down, atol=1e-12)]
        renumber[pose.index] = match[0] if match else -1
    zero = 0
    for pose in kept.poses:
        full = every.poses[np.flatnonzero(renumber == pose.index)[0]]
        np.testing.assert_array_equal(renumber[full.edge_final_pose], pose.edge_final_pose)
        rolled, momentum, onward = (renumber[getattr(full, name)] for name in ("edge_rolled_pose", "edge_momentum_pose", "edge_onward_pose"))
        np.testing.assert_array_equal(pose.edge_rolled_pose, np.where(rolled >= 0, rolled, pose.edge_final_pose))
        landing = np.where(momentum >= 0, momentum, pose.edge_final_pose)
        np.testing.assert_array_equal(pose.edge_momentum_pose, landing)
        np.testing.assert_array_equal(pose.edge_onward_pose, np.where((onward >= 0) & (momentum >= 0), onward, landing))
        zero += np.sum(((rolled == 0) | (momentum == 0)) & (pose.edge_final_pose != 0))
    assert zero > 0, "some roll or roll-on lands in pose 0, away from the quasi-static landing"
