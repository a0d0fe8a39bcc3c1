"""Heap grasp confidence (pipeline.heaps.grasps) on boxes with known answers."""

from __future__ import annotations

import dataclasses

import fcl
import numpy as np
import pytest
import trimesh

from clutter.state import HeapState
from pipeline.heaps.config import HeapConfig
from pipeline.heaps.grasps import (
    best_first,
    build_scene,
    cast_first,
    force_closure,
    heap_confidence,
    jaw_approach,
    jaw_candidates,
    jaw_options,
    jaw_parts,
    part_hits,
    suction_blocked,
    suction_candidates,
    suction_options,
    tilt_within,
)
from pipeline.heaps.objects import ObjectLibrary, box_model
from pipeline.model.mesh import model_from_mesh

CONFIG = HeapConfig()


@pytest.fixture(scope="module")
def boxes() -> ObjectLibrary:
    library = ObjectLibrary()
    library.add("brick", box_model((0.06, 0.09, 0.04)))
    library.add("wide", box_model((0.16, 0.16, 0.05)))  # wider than the jaws open, every way
    library.add("slab", box_model((0.05, 0.16, 0.04)))  # graspable across x only
    library.add("tile", box_model((0.10, 0.10, 0.03)))
    library.add("lid", box_model((0.12, 0.12, 0.02)))
    return library


def on_floor(library, object_id, x=0.0, y=0.0, z=0.0) -> np.ndarray:
    """(4, 4) pose of a box lying flat with its bottom at height z, centred at (x, y)."""
    pose = np.eye(4)
    pose[:3, 3] = [x, y, z + library[object_id].model.mesh.extents[2] / 2]
    return pose


def heap(library, *placed) -> HeapState:
    ids = tuple(p[0] for p in placed)
    return HeapState(CONFIG.bin, ids, np.stack([on_floor(library, *p) for p in placed]))


def test_force_closure_is_the_antipodal_friction_cone_test():
    c1, c2 = np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0])
    facing = np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    mu = np.array(0.5)  # cone half-angle atan(0.5) = 26.6 degrees
    assert force_closure(c1, facing[0], c2, facing[1], mu, 0.002)
    tilted = np.array([-np.cos(np.radians(20)), np.sin(np.radians(20)), 0.0])
    assert force_closure(c1, tilted, c2, facing[1], mu, 0.002)
    too_tilted = np.array([-np.cos(np.radians(35)), np.sin(np.radians(35)), 0.0])
    assert not force_closure(c1, too_tilted, c2, facing[1], mu, 0.002)
    assert force_closure(c1, too_tilted, c2, facing[1], np.array(1.0), 0.002)  # 45-degree cone
    assert not force_closure(c1, facing[0], c1, facing[1], mu, 0.002)  # one point is no grasp
    assert not force_closure(c1, facing[0], np.full(3, np.nan), facing[1], mu, 0.002)  # a missed jaw


def test_a_box_alone_in_the_bin_is_graspable_by_both_grippers(boxes):
    confidence = heap_confidence(heap(boxes, ("brick",)), CONFIG, boxes)
    assert confidence.quality("suction") > 0.8
    assert confidence.quality("parallel_jaw") > 0.8
    jaw = confidence.parallel_jaw
    assert jaw.target == 0 and jaw.width in (pytest.approx(0.06, abs=0.005), pytest.approx(0.09, abs=0.005))
    assert abs(jaw.axis[2]) < 0.2 and jaw.approach[2] < -0.9  # across the brick, from above
    assert confidence.suction.axis[2] < -0.9 and confidence.suction.point[2] == pytest.approx(0.04, abs=0.002)


def test_a_box_wider_than_the_jaws_open_has_no_jaw_grasp(boxes):
    confidence = heap_confidence(heap(boxes, ("wide",)), CONFIG, boxes)
    assert confidence.parallel_jaw is None and confidence.quality("parallel_jaw") == 0.0
    assert confidence.quality("suction") > 0.8  # its top face is still there for the cup


def test_two_boxes_pressed_together_lose_the_jaw_grasp_between_them(boxes):
    apart = heap(boxes, ("slab", -0.06), ("slab", 0.06))
    pressed = heap(boxes, ("slab", -0.025), ("slab", 0.025))
    assert heap_confidence(apart, CONFIG, boxes).quality("parallel_jaw") > 0.8
    # Across x a finger must go between the slabs; across y they are wider than the opening.
    assert heap_confidence(pressed, CONFIG, boxes).parallel_jaw is None


def test_a_box_against_the_wall_loses_the_finger_side(boxes):
    x_wall = CONFIG.bin.half_extents[0]
    against = heap(boxes, ("slab", x_wall - 0.025))
    assert heap_confidence(against, CONFIG, boxes).parallel_jaw is None


def test_a_suction_grasp_under_a_neighbour_is_rejected(boxes):
    covered = heap(boxes, ("tile",), ("lid", 0.0, 0.0, 0.03))  # the lid lies on the tile
    scene = build_scene(covered, [boxes[k] for k in covered.object_ids])
    down = np.array([0.0, 0.0, -1.0])
    assert suction_blocked(scene, 0, np.array([0.0, 0.0, 0.03]), down, CONFIG.suction)
    assert not suction_blocked(scene, 1, np.array([0.0, 0.0, 0.05]), down, CONFIG.suction)
    assert heap_confidence(covered, CONFIG, boxes, objects=[0]).suction is None
    alone = heap(boxes, ("tile",))
    assert heap_confidence(alone, CONFIG, boxes).quality("suction") > 0.8
    best = heap_confidence(covered, CONFIG, boxes)
    assert best.suction.target == 1


def test_confidence_is_reproducible_and_per_object(boxes):
    state = heap(boxes, ("brick", -0.1), ("slab", 0.1))
    first, again = heap_confidence(state, CONFIG, boxes), heap_confidence(state, CONFIG, boxes)
    for gripper in ("suction", "parallel_jaw"):
        a, b = getattr(first, gripper), getattr(again, gripper)
        assert (a.target, a.quality) == (b.target, b.quality)
        np.testing.assert_array_equal(a.point, b.point)
    only_slab = heap_confidence(state, CONFIG, boxes, objects=[1])
    assert only_slab.parallel_jaw.target == 1 and only_slab.suction.target == 1
    assert first.overall >= only_slab.overall


# --- cases the mutation run (stop 71) found untested ------------------------------------------


def test_grasps_name_their_gripper_and_objects_limits_both_grippers(boxes):
    state = heap(boxes, ("brick", -0.1), ("slab", 0.1))
    for objects in ([0], [1]):
        confidence = heap_confidence(state, CONFIG, boxes, objects=objects)
        assert confidence.suction.gripper == "suction" and confidence.parallel_jaw.gripper == "parallel_jaw"
        assert confidence.suction.target == objects[0] and confidence.parallel_jaw.target == objects[0]
        jaw = confidence.parallel_jaw
        assert abs(jaw.point[0] - state.poses[objects[0], 0, 3]) < 0.05  # on the object grasped
        np.testing.assert_array_equal(confidence.suction.approach, confidence.suction.axis)


def test_objects_without_candidates_do_not_hide_the_next_ones(boxes):
    # A brick with a body diagonal up has no face within 45 degrees of straight down for the cup;
    # the wide box has no jaw grasp.  The next object is still scored.
    tilted = np.eye(4)
    d = np.ones(3) / np.sqrt(3.0)  # the rotation taking this diagonal onto +z
    axis = np.cross(d, [0.0, 0.0, 1.0])
    angle = np.arccos(d[2])
    k = axis / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    tilted[:3, :3] = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
    tilted[:3, 3] = [-0.12, 0.0, 0.08]
    state = HeapState(CONFIG.bin, ("brick", "brick"), np.stack([tilted, on_floor(boxes, "brick", 0.12)]))
    owner, *_ = suction_options(state, [boxes[k] for k in state.object_ids], CONFIG)
    assert len(owner) and set(owner.tolist()) == {1}
    assert heap_confidence(state, CONFIG, boxes).suction.target == 1
    library = ObjectLibrary()
    library.add("cube", box_model((0.16, 0.16, 0.16)))  # wider than the jaws open every way, no candidate at all
    library.add("brick", box_model((0.06, 0.09, 0.04)))
    assert not len(jaw_candidates(library["cube"], CONFIG.jaw, CONFIG.seed, "cube").quality)
    state = heap(library, ("cube", -0.12), ("brick", 0.13))
    owner, *_ = jaw_options(state, [library[k] for k in state.object_ids], CONFIG)
    assert len(owner) and set(owner.tolist()) == {1}
    assert heap_confidence(state, CONFIG, library).parallel_jaw.target == 1


def test_candidates_are_cached_per_configuration_and_drawn_per_object_id():
    library = ObjectLibrary()
    model = box_model((0.06, 0.09, 0.04))
    a, b = library.add("a", model), library.add("b", model)
    few = dataclasses.replace(CONFIG.suction, n_candidates=7)
    assert len(suction_candidates(a, CONFIG.suction, 0, "a").points) == CONFIG.suction.n_candidates
    assert len(suction_candidates(a, few, 0, "a").points) == 7
    # Two ids of one model draw their own candidates (the stream is keyed by the object id).
    assert not np.array_equal(suction_candidates(b, CONFIG.suction, 0, "b").points, suction_candidates(a, CONFIG.suction, 0, "a").points)
    first = jaw_candidates(a, CONFIG.jaw, 0, "a")
    small = jaw_candidates(a, dataclasses.replace(CONFIG.jaw, n_candidates=10), 0, "a")
    assert len(first.quality) > 10 >= len(small.quality)
    assert not np.array_equal(jaw_candidates(b, CONFIG.jaw, 0, "b").centres, first.centres)
    # And through the heap (fresh caches): the same box at the same pose, under two ids, is scored on its own draws.
    fresh = ObjectLibrary()
    a, b = fresh.add("a", model), fresh.add("b", model)
    state = HeapState(CONFIG.bin, ("a", "b"), np.stack([on_floor(fresh, "a")] * 2))
    for options in (suction_options, jaw_options):
        owner, _, points, *_ = options(state, [a, b], CONFIG)
        assert not np.array_equal(points[owner == 0], points[owner == 1])


def test_jaw_candidates_are_nominally_in_force_closure_within_the_sampling_cone():
    library = ObjectLibrary()
    obj = library.add("brick", box_model((0.06, 0.09, 0.04)))
    cand = jaw_candidates(obj, CONFIG.jaw, 0, "brick")
    assert len(cand.quality) > 20 and np.all(cand.quality > 0) and np.all(cand.widths <= CONFIG.jaw.max_opening)
    # Each axis is a box face's normal tilted by at most cone_spread * atan(mu).
    limit = CONFIG.jaw.cone_spread * np.arctan(CONFIG.jaw.friction)
    tilt = np.arccos(np.clip(np.abs(cand.axes).max(axis=1), -1, 1))
    assert tilt.max() <= limit + 1e-9 and tilt.max() > limit / 2
    # The contacts along each axis through its centre are in force closure and that wide.
    reach = 1.0
    mesh = obj.model.mesh
    o1, n1 = cast_first(mesh, cand.centres - reach * cand.axes, cand.axes)
    o2, n2 = cast_first(mesh, cand.centres + reach * cand.axes, -cand.axes)
    assert np.allclose(np.linalg.norm(o2 - o1, axis=1), cand.widths)
    assert force_closure(o1, n1, o2, n2, np.full(len(o1), CONFIG.jaw.friction), CONFIG.jaw.min_width).all()


def test_cast_first_hits_every_triangle_on_its_plane():
    mesh = box_model((0.06, 0.09, 0.04)).mesh
    centres = mesh.triangles.mean(axis=1)
    normals = mesh.face_normals
    origins = centres + 0.05 * normals
    points, hit_normals = cast_first(mesh, origins, -normals)
    assert np.allclose(points, centres, atol=1e-9) and np.allclose(hit_normals, normals)
    miss, miss_normals = cast_first(mesh, origins, normals)  # away from the box
    assert np.isnan(miss).all() and np.isnan(miss_normals).all()


def test_tilted_axes_stay_in_the_cone_and_spread_around_it():
    rng = np.random.default_rng(0)
    axes = np.tile([0.0, 0.0, 1.0], (4000, 1))
    tilted = tilt_within(axes, 0.3, rng)
    assert np.allclose(np.linalg.norm(tilted, axis=1), 1.0)
    angle = np.arccos(np.clip(tilted[:, 2], -1, 1))
    assert angle.max() <= 0.3 + 1e-12 and abs(angle.mean() - 0.15) < 0.01  # uniform in [0, 0.3]
    azimuth = np.arctan2(tilted[:, 1], tilted[:, 0]) % (2 * np.pi)
    octants = np.bincount((azimuth // (np.pi / 4)).astype(int), minlength=8)
    assert octants.min() > 0.8 * 500 and octants.max() < 1.2 * 500


def test_the_jaws_approach_is_the_steepest_direction_across_the_axis():
    rng = np.random.default_rng(1)
    axes = rng.normal(size=(50, 3)) * [1.0, 1.0, 0.3]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    approach = jaw_approach(axes)
    assert np.allclose(np.linalg.norm(approach, axis=1), 1.0) and np.allclose(np.sum(approach * axes, axis=1), 0.0)
    assert np.allclose(approach[:, 2], -np.sqrt(1.0 - axes[:, 2] ** 2))


@pytest.mark.parametrize("width", [0.05, 0.135])
def test_the_open_jaws_fingers_and_palm_in_the_grasp_frame(width):
    config = CONFIG.jaw
    axis = np.array([1.0, 0.5, 0.2]) / np.linalg.norm([1.0, 0.5, 0.2])
    approach = jaw_approach(axis[None])[0]
    centre = np.array([0.01, -0.02, 0.03])
    parts, rotation = jaw_parts(centre, axis, approach, width, config)
    side = np.cross(approach, axis)
    np.testing.assert_allclose(rotation, np.stack([axis, side, approach], axis=1))
    opening = min(width + 2 * config.clearance, config.max_opening)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    ranges = []
    for half, part_centre in parts:
        corners = part_centre + (signs * half) @ rotation.T - centre
        local = corners @ np.stack([axis, side, approach], axis=1)  # (axis, side, approach) coordinates
        ranges.append(np.stack([local.min(axis=0), local.max(axis=0)], axis=1))
    tip, top = config.tip_depth, config.tip_depth - config.finger_length
    finger = [[-config.finger_width / 2, config.finger_width / 2], [top, tip]]
    np.testing.assert_allclose(ranges[0], [[opening / 2, opening / 2 + config.finger_thickness], *finger], atol=1e-12)
    np.testing.assert_allclose(ranges[1], [[-opening / 2 - config.finger_thickness, -opening / 2], *finger], atol=1e-12)
    outer = opening / 2 + config.finger_thickness
    np.testing.assert_allclose(ranges[2], [[-outer, outer], finger[0], [top - config.palm_thickness, top]], atol=1e-12)


def test_the_cup_may_touch_only_its_own_object_and_the_body_not_even_that(boxes):
    # A brick beside the tile's contact, 14 mm from the approach axis: inside the cup's radius
    # (15 mm), outside the body's (12.5 mm).
    down = np.array([0.0, 0.0, -1.0])
    for gap, blocked in ((0.014, True), (0.016, False)):
        state = HeapState(CONFIG.bin, ("tile", "brick"), np.stack([on_floor(boxes, "tile"), on_floor(boxes, "brick", gap + 0.03, 0.0, 0.03)]))
        scene = build_scene(state, [boxes[k] for k in state.object_ids])
        assert suction_blocked(scene, 0, np.array([0.0, 0.0, 0.03]), down, CONFIG.suction) == blocked
    # The bin is no object the cup may touch: a contact 14 mm from a wall is blocked, whichever object it is on.
    x = CONFIG.bin.half_extents[0] - 0.014
    state = heap(boxes, ("tile", -0.1), ("brick", x - 0.02))
    scene = build_scene(state, [boxes[k] for k in state.object_ids])
    assert suction_blocked(scene, 1, np.array([x, 0.0, 0.04]), down, CONFIG.suction)
    assert not suction_blocked(scene, 1, np.array([x - 0.004, 0.0, 0.04]), down, CONFIG.suction)
    # A contact sunk into its own object deeper than max_deflection (4 mm): the rigid body hits it.
    scene = build_scene(heap(boxes, ("tile",)), [boxes["tile"]])
    assert not suction_blocked(scene, 0, np.array([0.0, 0.0, 0.0275]), down, CONFIG.suction)
    assert suction_blocked(scene, 0, np.array([0.0, 0.0, 0.025]), down, CONFIG.suction)
    assert not suction_blocked(scene, 0, np.array([0.0, 0.0, 0.03]), down, CONFIG.suction)


def test_parts_and_objects_collide_as_rotated_not_by_their_bounding_boxes(boxes):
    yaw = np.eye(4)
    c = s = np.sqrt(0.5)
    yaw[:2, :2] = [[c, -s], [s, c]]
    yaw[:3, 3] = [0.0, 0.0, 0.02]
    state = HeapState(CONFIG.bin, ("brick",), yaw[None])
    scene = build_scene(state, [boxes["brick"]])
    probe = fcl.Box(0.01, 0.01, 0.01)
    # Inside the brick as if unrotated and inside its world bounding box, but 13 mm outside it.
    p = np.array([0.028, 0.040, 0.02])
    assert not part_hits(scene, probe, p, np.eye(3), p - 0.005, p + 0.005, None)
    top = np.array([0.0, 0.0, 0.04])  # across the brick's top face
    assert part_hits(scene, probe, top, np.eye(3), top - 0.005, top + 0.005, None)
    # A long thin part turned a quarter about z: along y it reaches the (unrotated) brick, along x it would not.
    flat = build_scene(heap(boxes, ("brick",)), [boxes["brick"]])
    rod = fcl.Box(0.1, 0.004, 0.004)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([0.0, 0.09, 0.02])
    lower, upper = centre - [0.002, 0.05, 0.002], centre + [0.002, 0.05, 0.002]
    assert part_hits(flat, rod, centre, turn, lower, upper, None)
    assert not part_hits(flat, rod, centre, turn, lower, upper, 0)  # the object itself skipped


def test_best_first_drops_zero_quality_and_other_objects_and_keeps_ties_in_order():
    owner = np.array([0, 0, 1, 1, 2])
    quality = np.array([0.5, 0.0, 0.5, 0.9, 0.5])
    assert best_first(owner, quality, None).tolist() == [3, 0, 2, 4]
    assert best_first(owner, quality, [0]).tolist() == [0]
    assert best_first(owner, quality, [1, 2]).tolist() == [3, 2, 4]
    rng = np.random.default_rng(2)
    many = rng.choice([0.2, 0.4, 0.6], size=200)
    expected = [i for q in (0.6, 0.4, 0.2) for i in range(200) if many[i] == q]
    assert best_first(np.zeros(200, int), many, None).tolist() == expected


def test_a_post_narrower_than_the_cup_has_no_suction_grasp():
    # Its only face within 45 degrees of straight down is 1 cm square: the 15 mm cup seals nowhere.
    library = ObjectLibrary()
    library.add("post", box_model((0.01, 0.01, 0.1)))
    state = heap(library, ("post",))
    owner, quality, *_ = suction_options(state, [library["post"]], CONFIG)
    assert len(owner) and np.all(quality == 0.0)
    assert heap_confidence(state, CONFIG, library).suction is None


def test_a_balls_jaw_quality_counts_only_samples_in_force_closure():
    # Across a ball of radius r every chord at distance d from the centre meets both normals at
    # asin(d / r): in the friction cone while d <= r sin(atan mu) = 13.4 mm (mu 0.5, r 3 cm).  The
    # samples move the grasp by N(0, 5 mm) + N(0, 10 mm) per axis, about sigma = 11.2 mm across the
    # axis, so a fraction 1 - exp(-13.4^2 / (2 sigma^2)) = 0.51 close; the widths all fit the jaws.
    library = ObjectLibrary()
    ball = library.add("ball", model_from_mesh(trimesh.creation.icosphere(subdivisions=3, radius=0.03), mass=0.2, name="ball"))
    cand = jaw_candidates(ball, CONFIG.jaw, 0, "ball")
    assert len(cand.quality) > 100 and 0.3 < cand.quality.mean() < 0.65
