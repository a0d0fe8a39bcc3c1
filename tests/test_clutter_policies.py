"""clutter.policies: the five push policies of thesis 3.2 on hand-made heaps whose answer is
known (two boxes side by side, an object with one neighbour, an object by a wall, a full
bin), the invariants every push keeps (inside the bin, a free start, a collision-free
approach), reproducibility, and the errors of bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clutter import footprints as fp
from clutter.policies import (
    POLICIES,
    PushConfig,
    best_stroke,
    clearance_ratios,
    closest_pair,
    clusters,
    cosine,
    floor_grid,
    free_space_points,
    outside_bin,
    plan_push,
    room,
    scene,
    strokes,
    unit,
)
from clutter.state import Bin, HeapState

CONFIG = PushConfig()
CENTRE = np.array([0.0, 0.0, 0.02])
"""Centre of mass of ``box``, object frame."""


def box(a: float = 0.03, b: float = 0.03, c: float = 0.04) -> np.ndarray:
    """(8, 3) hull of a box 2a x 2b x c standing on z = 0, object frame."""
    return np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (0.0, c)])


def placed(x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    pose[:2, 3] = [x, y]
    return pose


DEFAULT_BIN = Bin()


def heap(places, hulls=None, bin=DEFAULT_BIN):
    """(state, hulls, centers_mass) for boxes at ``places`` [(x, y[, yaw]), ...]."""
    hulls = hulls or [box() for _ in places]
    state = HeapState(bin, tuple(f"box{i}" for i in range(len(places))), np.stack([placed(*p) for p in places]))
    return state, hulls, np.tile(CENTRE, (len(places), 1))


def random_heap(rng, n: int):
    """n boxes of random sizes at random places and yaws inside the default bin (they may overlap)."""
    hulls = [box(*rng.uniform([0.01, 0.01, 0.02], [0.05, 0.03, 0.06])) for _ in range(n)]
    places = [(*rng.uniform([-0.18, -0.13], [0.18, 0.13]), rng.uniform(0, 2 * np.pi)) for _ in range(n)]
    return heap(places, hulls)


def direction(push) -> np.ndarray:
    d = (push.end - push.start)[:2]
    return d / np.linalg.norm(d)


def check_push(push, state, hulls, centers_mass, config=CONFIG):
    """The invariants of every push: in the bin a finger radius from the walls, level, through
    the target's centre of mass, a start a finger radius clear of every footprint."""
    sc = scene(state, hulls, centers_mass, config)
    box_half = state.bin.half_extents - config.finger_radius
    assert np.all(np.abs(push.start[:2]) <= box_half + 1e-9) and np.all(np.abs(push.end[:2]) <= box_half + 1e-9)
    assert push.start[2] == push.end[2] >= config.finger_radius
    assert push.length >= config.min_push
    line, com = push.end[:2] - push.start[:2], sc.centers[push.target] - push.start[:2]
    assert abs(line[0] * com[1] - line[1] * com[0]) / np.linalg.norm(line) < 1e-9  # the line passes through the COM
    clear = fp.point_polygon_distance(push.start[None, :2], sc.polygons)
    assert np.all(clear >= config.finger_radius - 1e-9), clear


# --- the policies' geometry ----------------------------------------------------------------


@pytest.mark.parametrize("y", [0.0, -0.1])
def test_boundary_shear_pushes_along_the_boundary_of_two_boxes_side_by_side(y):
    state, hulls, com = heap([(-0.031, y), (0.031, y)])
    push = plan_push("boundary_shear", state, hulls, com)
    assert push is not None and push.target in (0, 1)
    d = direction(push)
    assert abs(d[0]) < 1e-9  # perpendicular to the line between the centres
    check_push(push, state, hulls, com)
    if y < 0:  # by the near wall the free space is towards the bin's middle
        assert d[1] == pytest.approx(1.0)


def test_free_space_pushes_an_object_away_from_its_one_neighbour_towards_its_free_space_point():
    state, hulls, com = heap([(0.0, 0.0), (0.08, 0.0)])
    push = plan_push("free_space", state, hulls, com)
    assert push is not None
    other = 1 - push.target
    away = state.poses[push.target, :2, 3] - state.poses[other, :2, 3]
    assert direction(push) @ away > 0
    # Nothing stands in the way here, so it is the ideal direction c -> p itself.
    _, free = free_space_points(scene(state, hulls, com, CONFIG), np.array([push.target]))
    assert np.allclose(direction(push), free[0], atol=1e-9)
    check_push(push, state, hulls, com)


def test_the_free_space_point_of_a_lone_object_is_the_bins_middle():
    state, hulls, com = heap([(-0.15, 0.05)])
    sc = scene(state, hulls, com, CONFIG)
    points, free = free_space_points(sc, np.array([0]))
    # Alone, the room is the distance to the walls: largest on the bin's midline |x| <= 0.05 (0.5 x 0.4 m).
    assert points[0, 1] == pytest.approx(0.0, abs=CONFIG.grid_resolution) and points[0, 0] == pytest.approx(-0.05, abs=CONFIG.grid_resolution)
    assert free[0] @ [1.0, -1.0] > 0


def test_the_free_space_search_finds_the_best_grid_cell():
    rng = np.random.default_rng(8)
    for n in (2, 5, 9):
        state, hulls, com = random_heap(rng, n)
        sc = scene(state, hulls, com, CONFIG)
        size, counts = floor_grid(sc.half_extents, CONFIG)
        cells = np.stack([a.ravel() for a in np.meshgrid(np.arange(counts[0]), np.arange(counts[1]), indexing="ij")], axis=1)
        centres = (cells + 0.5) * size - sc.half_extents
        value = room(centres, sc)  # every cell, every object
        points, _ = free_space_points(sc, np.arange(n))
        for i in range(n):
            at = np.flatnonzero(np.all(np.abs(centres - points[i]) < 1e-12, axis=1))
            assert len(at) == 1 and value[at[0], i] == pytest.approx(value[:, i].max(), abs=1e-12)
            # Among the best cells, the one nearest the object's centre of mass.
            best = value[:, i] >= value[:, i].max() - 1e-9
            assert np.linalg.norm(points[i] - sc.centers[i]) == pytest.approx(np.linalg.norm(centres[best] - sc.centers[i], axis=1).min())


def test_max_clearance_pushes_towards_the_room():
    # A box 3 cm from the left wall with a neighbour above it: the room is to the right.
    state, hulls, com = heap([(-0.19, 0.0), (-0.19, 0.075)])
    push = plan_push("max_clearance", state, hulls, com)
    assert push is not None and direction(push)[0] > 0.9
    check_push(push, state, hulls, com)


def test_max_clearance_takes_the_best_ratio_the_finger_can_reach():
    # Two boxes touching: the best ratios push one away from the other, but the finger would
    # have to come down where the other one is.
    state, hulls, com = heap([(-0.1, 0.0), (-0.16, 0.0)])
    push = plan_push("max_clearance", state, hulls, com)
    assert push is not None
    check_push(push, state, hulls, com)
    sc = scene(state, hulls, com, CONFIG)
    ratios, directions = clearance_ratios(sc)
    k = int(np.argmin(np.linalg.norm(directions - direction(push), axis=1)))
    assert np.allclose(directions[k], direction(push), atol=1e-9)
    better = np.argwhere(ratios > ratios[push.target, k])
    assert len(better) >= 2 and not strokes(sc, better[:, 0], directions[better[:, 1]]).feasible.any()


def test_the_clearance_ratio_is_forward_over_backward_room():
    state, hulls, com = heap([(-0.19, 0.0)])
    ratios, directions = clearance_ratios(scene(state, hulls, com, CONFIG))
    plus_x, minus_x = (int(np.argmin(np.linalg.norm(directions - d, axis=1))) for d in ([1, 0], [-1, 0]))
    # 0.25 - 0.19 - 0.03 = 0.03 m to the left wall, 0.25 + 0.19 - 0.03 = 0.41 m to the right one.
    assert ratios[0, plus_x] == pytest.approx(0.41 / 0.03) and ratios[0, minus_x] == pytest.approx(0.03 / 0.41)


def test_cluster_diffusion_pushes_away_from_the_cluster_centre():
    places = [(-0.06, 0.0), (0.06, 0.0), (0.0, 0.1), (0.2, -0.15)]  # a cluster of three and a loner
    state, hulls, com = heap(places)
    push = plan_push("cluster_diffusion", state, hulls, com)
    assert push is not None and push.target != 3
    centre = np.mean(places[:3], axis=0)
    away = np.array(places[push.target]) - centre
    assert direction(push) @ (away / np.linalg.norm(away)) == pytest.approx(1.0)
    check_push(push, state, hulls, com)


def test_clusters_hold_one_to_three_near_objects():
    # A chain 1, 1.5 and 2 cm apart: the nearest links first, the fourth would make four.
    centres = np.array([[0, 0], [0.01, 0], [0.025, 0], [0.045, 0], [1, 1], [1.01, 1], [5, 5]], dtype=float)
    label = clusters(centres, 3, reach=0.5)
    sizes = np.bincount(label)[label]
    assert list(sizes) == [3, 3, 3, 1, 2, 2, 1] and label[0] == label[1] == label[2] and label[4] == label[5]
    assert np.array_equal(clusters(centres, 3, reach=0.001), np.arange(7))


# --- every push, every policy --------------------------------------------------------------


@pytest.mark.parametrize("policy", POLICIES)
def test_every_push_stays_in_the_bin_with_a_free_start(policy):
    rng = np.random.default_rng(11)
    found = 0
    for _ in range(12):
        state, hulls, com = random_heap(rng, int(rng.integers(2, 9)))
        push = plan_push(policy, state, hulls, com, rng=np.random.default_rng(int(rng.integers(1 << 30))))
        if push is None:
            continue
        check_push(push, state, hulls, com)
        assert push.policy == policy and 0 <= push.target < len(state)
        if policy != "quasi_random":  # the baseline is only clipped to the bin (thesis 3.2.1)
            sc = scene(state, hulls, com, CONFIG)
            contact = push.start[:2] + direction(push) * (CONFIG.approach_offset - CONFIG.finger_radius)
            others = np.delete(sc.polygons, push.target, axis=0)
            assert not fp.capsule_hits(push.start[None, :2], contact[None], CONFIG.finger_radius, others).any()
        found += 1
    assert found >= 6


def test_quasi_random_is_reproducible_from_the_seed_and_differs_across_seeds():
    state, hulls, com = random_heap(np.random.default_rng(5), 6)
    pushes = [plan_push("quasi_random", state, hulls, com, rng=np.random.default_rng(seed)) for seed in (1, 1, 2, 3)]
    assert np.array_equal(pushes[0].start, pushes[1].start) and np.array_equal(pushes[0].end, pushes[1].end)
    assert len({(p.target, *np.round(p.end, 9)) for p in pushes}) == 3


@pytest.mark.parametrize("policy", POLICIES)
def test_a_full_bin_has_no_push(policy):
    # Four boxes tile a 0.2 x 0.2 m bin: nowhere for the finger to come down.
    state, hulls, com = heap([(-0.05, -0.05), (0.05, -0.05), (-0.05, 0.05), (0.05, 0.05)],
                             hulls=[box(0.05, 0.05) for _ in range(4)], bin=Bin(length=0.2, width=0.2))
    assert plan_push(policy, state, hulls, com, rng=np.random.default_rng(0)) is None


def test_one_object_has_no_pair_to_separate_but_can_be_cleared():
    state, hulls, com = heap([(-0.1, 0.0)])
    assert plan_push("boundary_shear", state, hulls, com) is None
    assert plan_push("free_space", state, hulls, com) is None
    assert plan_push("cluster_diffusion", state, hulls, com) is None
    assert plan_push("max_clearance", state, hulls, com) is not None


def test_an_empty_heap_has_no_push():
    state = HeapState(Bin(), (), np.zeros((0, 4, 4)))
    assert plan_push("boundary_shear", state, [], np.zeros((0, 3))) is None


def test_outside_bin_names_the_first_object_past_a_wall_or_below_the_floor():
    state, hulls, _ = heap([(0.0, 0.0), (0.23, 0.0), (0.0, 0.19)])
    # The second box reaches 0.23 + 0.03 - 0.25 = 1 cm past the right wall, the third 2 cm past the top.
    assert outside_bin(state, hulls, tolerance=0.011) == (2, "outside_bin", pytest.approx(0.02))
    assert outside_bin(state, hulls, tolerance=0.005) == (1, "outside_bin", pytest.approx(0.01))
    assert outside_bin(state, hulls, tolerance=0.03) is None
    poses = state.poses.copy()
    poses[0, 2, 3] = -0.004
    sunk = HeapState(state.bin, state.object_ids, poses)
    assert outside_bin(sunk, hulls, tolerance=0.003) == (0, "below_floor", pytest.approx(0.004))


# --- errors ------------------------------------------------------------------------


def test_bad_input_is_a_one_line_value_error():
    state, hulls, com = heap([(0.0, 0.0), (0.1, 0.0)])
    with pytest.raises(ValueError, match="unknown push policy 'shove'"):
        plan_push("shove", state, hulls, com)
    with pytest.raises(ValueError, match="got 1 hulls for a heap of 2 objects"):
        plan_push("free_space", state, hulls[:1], com)
    with pytest.raises(ValueError, match=r"centers_mass must be \(2, 3\)"):
        plan_push("free_space", state, hulls, com[:, :2])
    with pytest.raises(ValueError, match=r"object 1 \('box1'\): hull vertices must be"):
        plan_push("free_space", state, [hulls[0], hulls[1][:, :2]], com)
    with pytest.raises(ValueError, match="needs rng"):
        plan_push("quasi_random", state, hulls, com)
    poses = state.poses.copy()
    poses[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"object 1 \('box1'\): its pose holds a NaN"):
        plan_push("max_clearance", HeapState(state.bin, state.object_ids, poses), hulls, com)
    bad_com = com.copy()
    bad_com[0, 2] = np.inf
    with pytest.raises(ValueError, match="object 0 .* centre of mass is not finite"):
        plan_push("max_clearance", state, hulls, bad_com)
    flat = hulls[0].copy()
    flat[:, 1] = 0.0  # a hull in the plane y = 0, seen edge-on from above
    with pytest.raises(ValueError, match="footprint has no area"):
        plan_push("max_clearance", state, [flat, hulls[1]], com)


@pytest.mark.parametrize("change, message", [
    ({"approach_offset": 0.005}, "at least finger_radius"),
    ({"directions": 15}, "even"),
    ({"push_length": -0.1}, "positive"),
    ({"grid_resolution": float("nan")}, "positive"),
])
def test_a_bad_config_says_which_field(change, message):
    with pytest.raises(ValueError, match=message):
        PushConfig(**change)


def test_plan_heap_takes_meshes():
    shapes = pytest.importorskip("tests.shapes")  # the geometry stack (pipeline extra)
    import pipeline as toppledb

    box_model = shapes.box_object(size=(0.06, 0.06, 0.04))
    state, hulls, _ = heap([(-0.031, -0.1), (0.031, -0.1)], hulls=[np.asarray(box_model.hull.vertices)] * 2)
    push = toppledb.plan_heap(state.object_ids, state.poses, {"box0": box_model, "box1": box_model}, "boundary_shear")
    expected = plan_push("boundary_shear", state, hulls, np.tile(box_model.center_mass, (2, 1)))
    assert push.target == expected.target and np.allclose(push.end, expected.end) and direction(push)[1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no mesh given for 'box1'"):
        toppledb.plan_heap(state.object_ids, state.poses, {"box0": box_model})


# --- cases the mutation run (stop 71) found untested ------------------------------------------


def test_config_limits_are_inclusive_where_documented_and_errors_name_the_field():
    assert PushConfig(approach_offset=0.01, finger_radius=0.01).approach_offset == 0.01  # "at least finger_radius"
    assert PushConfig(directions=4).directions == 4  # "even and at least 4"
    with pytest.raises(ValueError, match="PushConfig.min_push must be a positive number, got 0"):
        PushConfig(min_push=0)
    with pytest.raises(TypeError, match=r"PushConfig.directions must be an integer, got 16.0"):
        PushConfig(directions=16.0)


def test_bad_input_names_the_object_it_is_about():
    state, hulls, com = heap([(0.0, 0.0), (0.1, 0.0), (-0.1, 0.0)])
    bad_com = com.copy()
    bad_com[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"object 2 \('box2'\): its centre of mass is not finite"):
        plan_push("max_clearance", state, hulls, bad_com)
    bad_hull = hulls[1].copy()
    bad_hull[3, 2] = np.inf
    with pytest.raises(ValueError, match=r"object 1 \('box1'\): its hull vertices are not all finite"):
        plan_push("max_clearance", state, [hulls[0], bad_hull, hulls[2]], com)
    with pytest.raises(ValueError, match="known: quasi_random, boundary_shear, free_space, max_clearance, cluster_diffusion$"):
        plan_push("shove", state, hulls, com)
    with pytest.raises(ValueError, match=r"^the quasi_random policy needs rng \(a numpy Generator\)$"):
        plan_push("quasi_random", state, hulls, com)
    with pytest.raises(ValueError, match="^got 2 hulls for an empty heap$"):
        plan_push("free_space", HeapState(Bin(), (), np.zeros((0, 4, 4))), hulls[:2], np.zeros((0, 3)))
    # Three vertices are enough (V >= 3): a triangle lying on the floor.
    triangle = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.0, 0.04, 0.0]])
    assert scene(state, [triangle, hulls[1], hulls[2]], com, CONFIG).polygons.shape[0] == 3


@pytest.mark.parametrize("half", [[0.25, 0.2], [0.4, 0.1], [0.003, 0.2]])
@pytest.mark.parametrize("max_points", [20_000, 16])
def test_the_floor_grid_has_the_fewest_cells_no_larger_than_its_resolution(half, max_points):
    half = np.array(half)
    config = PushConfig(max_grid_points=max_points)
    size, counts = floor_grid(half, config)
    extent = 2 * half
    # The cell is the configured one unless that would make more than max_grid_points cells.
    resolution = max(config.grid_resolution, math.sqrt(extent[0] * extent[1] / max_points))
    assert counts.dtype.kind == "i" and np.allclose(size * counts, extent)
    assert np.all((counts - 1) * resolution < extent) and np.all(extent <= counts * resolution * (1 + 1e-12))
    assert counts.prod() <= max_points + counts.sum() + 1  # the budget, but for rounding up per side


def test_the_closest_pair_is_by_centre_distance():
    state, hulls, com = heap([(-0.15, 0.0), (0.05, 0.0), (0.12, 0.0)])
    assert closest_pair(scene(state, hulls, com, CONFIG)) == (1, 2)


def test_cosine_of_any_vectors():
    a = np.array([[3.0, 4.0], [1.0, 0.0], [0.0, 0.0], [2.0, 2.0], [0.0, 5.0]])
    b = np.array([[6.0, 8.0], [-2.0, 0.0], [1.0, 1.0], [0.0, 0.0], [3.0, 0.0]])
    assert np.allclose(cosine(a, b), [1.0, -1.0, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(18)
    a, b = rng.normal(size=(20, 2)) * 3, rng.normal(size=(20, 2)) * 0.2
    angle = np.arctan2(a[:, 1], a[:, 0]) - np.arctan2(b[:, 1], b[:, 0])
    assert np.allclose(cosine(a, b), np.cos(angle))


def test_free_space_points_in_a_bin_two_cells_wide():
    # Alone, every cell at |x| <= 0.245 ties on room (5 mm to a long wall): the point is the
    # object's own cell, and an object there has no direction of most free space.
    narrow = Bin(length=0.5, width=0.02)
    for y in (-0.005, 0.005):
        state, hulls, com = heap([(0.005, y)], hulls=[box(0.004, 0.004)], bin=narrow)
        points, free = free_space_points(scene(state, hulls, com, CONFIG), np.array([0]))
        assert np.allclose(points[0], [0.005, y], atol=1e-12) and np.array_equal(free[0], [0.0, 0.0])


def test_the_direction_of_most_free_space_is_unit_beyond_half_a_cell_and_zero_within():
    # In the default bin the best cells of a lone object tie around the middle (room 0.195 m).
    for place, unit_length in (((0.0, 0.0), True), ((0.009, 0.005), False)):
        state, hulls, com = heap([place])
        points, free = free_space_points(scene(state, hulls, com, CONFIG), np.array([0]))
        offset = points[0] - place
        if unit_length:  # 7.1 mm from the nearest best cells
            assert np.linalg.norm(offset) > CONFIG.grid_resolution / 2 and np.allclose(free[0], offset / np.linalg.norm(offset))
        else:  # 4 mm from it
            assert np.linalg.norm(offset) < CONFIG.grid_resolution / 2 and np.array_equal(free[0], [0.0, 0.0])
    # Several objects at once: each direction is its own unit vector c -> p (or zero).
    state, hulls, com = random_heap(np.random.default_rng(19), 6)
    sc = scene(state, hulls, com, CONFIG)
    points, free = free_space_points(sc, np.arange(6))
    offset = points - sc.centers
    far = np.linalg.norm(offset, axis=1) > CONFIG.grid_resolution / 2
    assert far.sum() >= 5
    assert np.allclose(free[far], offset[far] / np.linalg.norm(offset[far], axis=1, keepdims=True))
    assert np.all(free[~far] == 0.0)


def test_a_clearance_ratio_is_the_inverse_of_its_opposite():
    state, hulls, com = random_heap(np.random.default_rng(20), 5)
    ratios, directions = clearance_ratios(scene(state, hulls, com, CONFIG))
    opposite = np.roll(ratios, -CONFIG.directions // 2, axis=1)
    assert np.allclose(directions, -np.roll(directions, -CONFIG.directions // 2, axis=0))
    roomy = (ratios > 0) & (opposite > 0) & np.isfinite(ratios) & np.isfinite(opposite)
    assert roomy.sum() > 20
    # Both clearances at least min_clearance there, forward / backward times backward / forward is 1.
    both = roomy & (ratios * opposite > 1e-6)
    assert np.allclose((ratios * opposite)[both], 1.0)


def test_a_stroke_starts_approach_offset_behind_the_footprint_and_pushes_push_length_past_contact():
    # The centre of mass 15 mm off the box's middle: the start is measured from the footprint's back.
    state, hulls, _ = heap([(0.0, 0.0), (0.15, 0.1)])
    com = np.array([[0.015, 0.0, 0.02], [0.0, 0.0, 0.02]])
    sc = scene(state, hulls, com, CONFIG)
    for d in ([1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [math.sqrt(0.5), -math.sqrt(0.5)]):
        s = strokes(sc, np.array([0]), np.array([d]))
        assert s.feasible[0]
        t_in, _ = fp.ray_interval(s.start, s.direction, sc.polygons[:1])  # along the stroke, to the footprint
        assert t_in[0] == pytest.approx(CONFIG.approach_offset)
        travel = np.linalg.norm(s.end[0] - s.start[0])
        assert travel == pytest.approx(CONFIG.approach_offset - CONFIG.finger_radius + CONFIG.push_length)
        line = s.end[0] - s.start[0]
        assert abs(line[0] * (sc.centers[0] - s.start[0])[1] - line[1] * (sc.centers[0] - s.start[0])[0]) < 1e-12


def test_a_start_past_the_wall_is_infeasible_unless_clipped_forward():
    # A box 2 cm from the right wall pushed left: the finger would start outside the bin.
    state, hulls, com = heap([(0.2, 0.0)])
    sc = scene(state, hulls, com, CONFIG)
    d = np.array([[-1.0, 0.0]])
    assert not strokes(sc, np.array([0]), d).feasible[0]
    assert not strokes(sc, np.array([0]), d, clip_start=False).feasible[0]
    clipped = strokes(sc, np.array([0]), d, clip_start=True)
    assert clipped.feasible[0]
    box_half = sc.half_extents - CONFIG.finger_radius
    assert clipped.start[0] == pytest.approx([box_half[0], 0.0])  # moved forward onto the limit


def test_a_stroke_cut_short_by_the_wall_is_feasible_only_if_it_moves_the_target_min_push():
    # A 8 mm box pushed towards the right wall: the finger meets it at x - 14 mm and may go on
    # to 0.24 m (a finger radius from the wall), at most push_length.
    config = PushConfig(min_push=0.02)
    limit = 0.25 - config.finger_radius
    for x in np.linspace(0.15, 0.245, 20):
        state, hulls, com = heap([(float(x), 0.0)], hulls=[box(0.004, 0.004)])
        sc = scene(state, hulls, com, config)
        s = strokes(sc, np.array([0]), np.array([[1.0, 0.0]]))
        contact = x - 0.004 - config.finger_radius
        travel = min(config.push_length, limit - contact)
        assert s.feasible[0] == (travel >= config.min_push - 1e-12)
        if s.feasible[0]:
            assert s.end[0, 0] == pytest.approx(contact + travel)


def test_the_approach_is_checked_against_the_other_objects_unless_told_not_to():
    # A small box 8 mm beside the approach of a push of box 0 along +x, but 13 mm from the start.
    state, hulls, com = heap([(0.0, 0.0), (-0.036, 0.012)], hulls=[box(), box(0.004, 0.004)])
    sc = scene(state, hulls, com, CONFIG)
    d = np.array([[1.0, 0.0]])
    assert not strokes(sc, np.array([0]), d).feasible[0]
    assert strokes(sc, np.array([0]), d, check_approach=False).feasible[0]


def test_best_stroke_looks_past_every_chunk_of_infeasible_candidates():
    # 39 pushes whose start is past the wall score highest; the one feasible push scores lowest.
    state, hulls, com = heap([(0.215, 0.0)])
    sc = scene(state, hulls, com, CONFIG)
    directions = np.array([[-1.0, 0.0]] * 39 + [[0.0, 1.0]])
    push = best_stroke(sc, "max_clearance", np.zeros(40, dtype=int), directions, -np.arange(40.0))
    assert push is not None and direction(push) == pytest.approx([0.0, 1.0])


def test_quasi_random_takes_the_first_draw_whose_clipped_start_is_free_approach_unchecked():
    rng = np.random.default_rng(21)
    clipped = approach_blocked = 0
    corners = heap([(0.21, 0.16), (-0.21, -0.16), (0.21, -0.16)])  # fingers often start past a wall here
    for seed in range(60):
        state, hulls, com = random_heap(rng, int(rng.integers(6, 12))) if seed % 2 else corners
        sc = scene(state, hulls, com, CONFIG)
        draws = np.random.default_rng(seed)  # the baseline's draws: all objects first, then all angles
        targets = draws.integers(len(sc), size=CONFIG.random_attempts)
        d = unit(draws.uniform(0.0, 2 * np.pi, size=CONFIG.random_attempts))
        s = strokes(sc, targets, d, check_approach=False, clip_start=True)
        push = plan_push("quasi_random", state, hulls, com, rng=np.random.default_rng(seed))
        if not s.feasible.any():
            assert push is None
            continue
        k = int(np.argmax(s.feasible))
        assert push.target == targets[k] and np.allclose(direction(push), d[k]) and np.allclose(push.start[:2], s.start[k])
        one = (sc, targets[k:k + 1], d[k:k + 1])
        approach_blocked += not strokes(*one, check_approach=True, clip_start=True).feasible[0]
        clipped += not strokes(*one, check_approach=False, clip_start=False).feasible[0]
    assert approach_blocked >= 1 and clipped >= 1


def test_quasi_random_directions_cover_the_circle_evenly():
    state, hulls, com = heap([(0.0, 0.0)])  # alone in the middle: every first draw is taken
    angles = np.array([math.atan2(*direction(plan_push("quasi_random", state, hulls, com, rng=np.random.default_rng(seed)))[::-1])
                       for seed in range(400)]) % (2 * np.pi)
    octants = np.bincount((angles // (np.pi / 4)).astype(int), minlength=8)
    assert len(octants) == 8 and octants.min() >= 25  # 50 expected in each
    assert abs(np.mean(angles < np.pi) - 0.5) < 0.1


def test_boundary_shear_pushes_across_a_diagonal_pair():
    state, hulls, com = heap([(-0.03, -0.03), (0.03, 0.03)])
    push = plan_push("boundary_shear", state, hulls, com)
    assert push is not None and abs(direction(push) @ [1.0, 1.0]) < 1e-9
    check_push(push, state, hulls, com)


@pytest.mark.parametrize("blocked", [0, 1])
def test_boundary_shear_pushes_the_other_object_when_one_cannot_be_reached(blocked):
    # Two boxes by the top wall, a third above one of them where the finger would come down for
    # its push towards the room below: that push is the other box's.
    places = [(-0.031, 0.1), (0.031, 0.1), ((-0.031, 0.031)[blocked], 0.17)]
    state, hulls, com = heap(places)
    push = plan_push("boundary_shear", state, hulls, com)
    assert push is not None and push.target == 1 - blocked
    assert direction(push) == pytest.approx([0.0, -1.0])
    check_push(push, state, hulls, com)


def test_free_space_turns_a_blocked_ideal_direction_by_the_fewest_steps():
    # A neighbour 5 mm behind each box's ideal push: the finger cannot come down there.
    state, hulls, com = heap([(0.0, 0.0), (-0.065, 0.0)])
    sc = scene(state, hulls, com, CONFIG)
    push = plan_push("free_space", state, hulls, com)
    assert push is not None
    check_push(push, state, hulls, com)
    _, free = free_space_points(sc, np.array([push.target]))
    step = 2 * np.pi / CONFIG.directions
    turn = (math.atan2(*direction(push)[::-1]) - math.atan2(free[0, 1], free[0, 0])) / step
    k = round(turn)
    assert abs(turn - k) < 1e-9
    k = (k + CONFIG.directions // 2) % CONFIG.directions - CONFIG.directions // 2  # -8 .. 7
    assert k != 0
    nearer = np.array([j for j in range(-CONFIG.directions // 2, CONFIG.directions // 2 + 1) if abs(j) < abs(k)])
    ideal = math.atan2(free[0, 1], free[0, 0])
    assert not strokes(sc, np.full(len(nearer), push.target), unit(ideal + nearer * step)).feasible.any()


def test_best_stroke_breaks_ties_by_the_earlier_candidate():
    # 60 candidates scoring 1 or 2 in blocks of three; the first four of score 2 cannot start
    # (past the wall), the others are told apart by their direction.
    state, hulls, com = heap([(0.215, 0.0)])
    sc = scene(state, hulls, com, CONFIG)
    score = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0] * 10)
    angles = np.radians(-80.0 + np.arange(60) * 160.0 / 60)
    angles[[3, 4, 5, 9]] = np.pi
    push = best_stroke(sc, "max_clearance", np.zeros(60, dtype=int), unit(angles), score)
    assert push is not None and direction(push) == pytest.approx(unit(angles[10]))


def test_an_object_ahead_of_the_target_does_not_block_the_push():
    # Only the finger's way down and in to the target is checked, not where the target goes.
    state, hulls, com = heap([(-0.1, 0.0), (0.1, 0.0)])
    s = strokes(scene(state, hulls, com, CONFIG), np.array([0, 1]), np.array([[1.0, 0.0], [-1.0, 0.0]]))
    assert s.feasible.all()


def test_free_space_has_no_push_when_both_objects_sit_at_their_free_space_points():
    # A bin four cells wide: each small box stands in a cell of most room, far from the other.
    state, hulls, com = heap([(0.005, 0.005), (0.205, 0.005)], hulls=[box(0.004, 0.004)] * 2, bin=Bin(length=0.5, width=0.04))
    sc = scene(state, hulls, com, CONFIG)
    points, free = free_space_points(sc, np.array([0, 1]))
    assert np.allclose(points, sc.centers, atol=1e-12) and np.all(free == 0.0)
    assert plan_push("free_space", state, hulls, com) is None


def test_free_space_and_boundary_shear_choose_by_their_rules_on_random_heaps():
    rng = np.random.default_rng(22)
    step = 2 * np.pi / CONFIG.directions
    turns = set()
    for _ in range(40):
        state, hulls, com = random_heap(rng, int(rng.integers(3, 10)))
        sc = scene(state, hulls, com, CONFIG)
        i, j = closest_pair(sc)
        _, free = free_space_points(sc, np.array([i, j]))
        push = plan_push("free_space", state, hulls, com)
        if push is not None:
            t = push.target
            ideal = np.arctan2(*free[[i, j].index(t)][::-1])
            turn = (math.atan2(*direction(push)[::-1]) - ideal) / step
            assert abs(turn - round(turn)) < 1e-9
            half = CONFIG.directions // 2
            k = (round(turn) + half) % CONFIG.directions - half
            k = half if k == -half else k
            # Every turn tried before it (fewer steps; of two the same size, counter-clockwise first) is blocked.
            order = [0, *[s * m for m in range(1, half) for s in (1, -1)], half]
            before = np.array(order[: order.index(k)], dtype=float)
            if len(before):
                assert not strokes(sc, np.full(len(before), t), unit(ideal + before * step)).feasible.any()
            turns.add(k)
        # Boundary shear: the feasible one of the four pushes closest to its own object's free direction.
        push = plan_push("boundary_shear", state, hulls, com)
        if push is not None:
            across = sc.centers[j] - sc.centers[i]
            b = np.array([-across[1], across[0]]) / np.linalg.norm(across)
            targets, dirs = np.array([i, i, j, j]), np.stack([b, -b, b, -b])
            s = strokes(sc, targets, dirs)
            score = cosine(dirs, free[[0, 0, 1, 1]])
            chosen = [n for n in range(4) if targets[n] == push.target and np.allclose(dirs[n], direction(push))]
            assert len(chosen) == 1 and s.feasible[chosen[0]]
            assert score[chosen[0]] >= score[s.feasible].max() - 1e-12
    assert len(turns) >= 4 and min(turns) < 0 < max(turns)
