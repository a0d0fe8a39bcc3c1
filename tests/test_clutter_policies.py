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
    clearance_ratios,
    clusters,
    floor_grid,
    free_space_points,
    outside_bin,
    plan_push,
    room,
    scene,
    strokes,
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
