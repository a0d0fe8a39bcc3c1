"""Heap grasp confidence (pipeline.heaps.grasps) on boxes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from clutter.state import HeapState
from pipeline.heaps.config import HeapConfig
from pipeline.heaps.grasps import build_scene, force_closure, heap_confidence, suction_blocked
from pipeline.heaps.objects import ObjectLibrary, box_model

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
