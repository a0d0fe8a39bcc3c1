"""The push-course study: a stroke's course read from made-up transforms, the standing box traced
in pybullet, and the summary by hand; then the command on a small real dataset."""

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
from shapes import noise_free, pose_with_down, standing_box

from pipeline.model.config import Config
from pipeline.model.evaluation import evaluate
from pipeline.studies import push_course
from pipeline.studies.policies_physics import ExperimentError, dataset_config, object_plans, world_config
from pipeline.studies.push_course import (
    KINDS,
    LANDINGS,
    SIDES,
    Course,
    Play,
    chosen_pushes,
    course,
    course_kind,
    landing_kind,
    line_edge,
    main,
    model_edge,
    play_object,
    study,
    summary,
    text,
    tip_angle,
    tip_side,
    tipped_edge,
    traced_play,
)
from pipeline.studies.pushsim import PushNoise, body_model, draw_noise, play_push
from schema.frames import transform_points, unit
from schema.vocabulary import NO_OP
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)

PUSH_POINT, PUSH_DIRECTION = np.array([0.025, 0.0, 0.13]), np.array([-1.0, 0.0, 0.0])
"""The standing box pushed high on its +x face towards -x (test_pushsim's push): it tips over its -x edge."""


def turned_about_y(angles_deg: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    """(S, 4, 4) transforms turned by each angle about +y (up leans to +x), moved by ``shift`` (S, 3)."""
    out = np.tile(np.eye(4), (len(angles_deg), 1, 1))
    a = np.radians(angles_deg)
    out[:, 0, 0], out[:, 0, 2], out[:, 2, 0], out[:, 2, 2] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
    if shift is not None:
        out[:, :3, 3] = shift
    return out


def made(tilt, slide, yaw=None, pressing=None) -> Course:
    tilt = np.asarray(tilt, dtype=float)
    return Course(tilt, np.asarray(slide, dtype=float), np.zeros_like(tilt) if yaw is None else np.asarray(yaw, dtype=float),
                  np.ones_like(tilt) if pressing is None else np.asarray(pressing, dtype=float), np.array([1.0, 0.0]))


def test_a_course_reads_tilt_slide_yaw_and_where_the_object_leans():
    angles = np.array([0.0, 2.0, 5.0, 9.0, 20.0])
    shift = np.outer(np.arange(5) * 0.001, [1.0, 0.0, 0.0])
    c = course(np.eye(4), turned_about_y(angles, shift), np.arange(5.0), np.zeros(3))
    np.testing.assert_allclose(c.tilt, angles, atol=1e-9)
    np.testing.assert_allclose(c.slide, np.arange(5) * 0.001, atol=1e-12)  # the point under the centre of mass (the origin)
    # A tip about an edge 2.5 cm away, centre of mass 7.5 cm up: the base hardly moves, the centre of mass 7.5 cm x tilt.
    pivot = np.array([0.025, 0.0, 0.0])
    tipped = turned_about_y(angles)
    tipped[:, :3, 3] = pivot - np.einsum("sij,j->si", tipped[:, :3, :3], pivot)
    tip = course(np.eye(4), tipped, np.ones(5), np.array([0.0, 0.0, 0.075]))
    np.testing.assert_allclose(tip.slide, 0.025 * (1 - np.cos(np.radians(angles))), atol=1e-12)
    np.testing.assert_allclose(c.yaw, 0.0, atol=1e-9)
    np.testing.assert_allclose(c.tip_direction, [1.0, 0.0], atol=1e-12)  # turning about +y leans the top to +x
    # A slide is how far the base moved on the table, whichever way: sideways to a push, or under one straight down.
    sideways = turned_about_y(angles, np.outer(np.arange(5) * 0.001, [0.6, -0.8, 0.0]))
    np.testing.assert_allclose(course(np.eye(4), sideways, np.zeros(5), np.zeros(3)).slide, np.arange(5) * 0.001, atol=1e-12)
    # A turn about the vertical is yaw, not tilt.
    turn = np.tile(np.eye(4), (2, 1, 1))
    turn[1, :2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    spun = course(np.eye(4), turn, np.zeros(2), np.zeros(3))
    np.testing.assert_allclose(spun.yaw, [0.0, np.degrees(0.3)])
    np.testing.assert_allclose(spun.tilt, 0.0, atol=1e-6)


def test_the_lean_is_read_at_the_tip_tilt_not_at_the_end():
    # It leans to +x first, then (past 8 degrees) swings round to +y: the tip's direction is the first.
    first = turned_about_y(np.array([0.0, 4.0, 9.0]))
    swing = np.eye(4)
    swing[:3, :3] = [[1, 0, 0], [0, np.cos(-0.8), -np.sin(-0.8)], [0, np.sin(-0.8), np.cos(-0.8)]]  # about x: up leans to +y
    c = course(np.eye(4), np.concatenate([first, swing[None]]), np.ones(4), np.zeros(3))
    np.testing.assert_allclose(c.tip_direction, [1.0, 0.0], atol=1e-12)
    # Never tipped that far: read at the largest tilt.
    small = course(np.eye(4), turned_about_y(np.array([0.0, 3.0, 1.0])), np.ones(3), np.zeros(3))
    np.testing.assert_allclose(small.tip_direction, [1.0, 0.0], atol=1e-12)


def turned_about_z(start: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    """(S, 4, 4): ``start`` turned about its own origin's vertical by each angle."""
    out = np.tile(start, (len(angles_deg), 1, 1))
    a = np.radians(angles_deg)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    return out


def test_the_slide_follows_the_table_point_under_an_off_centre_centre_of_mass():
    # The object stands at (0.3, -0.2) and turns about its own origin; its centre of mass is (2, 1) cm off
    # that origin, so the table point under it swings round on an arc: r -> R(theta) r, the origin stays.
    start = np.eye(4)
    start[:3, 3] = [0.3, -0.2, 0.0]
    angles = np.array([0.0, 10.0, 30.0])
    a, r = np.radians(angles), np.array([0.02, 0.01])
    center_mass = np.array([0.02, 0.01, 0.05])
    turned = course(start, turned_about_z(start, angles), np.ones(3), center_mass)
    np.testing.assert_allclose(turned.slide, 2 * np.linalg.norm(r) * np.sin(a / 2), atol=1e-12)  # the chord of the arc
    np.testing.assert_allclose(turned.yaw, angles, atol=1e-9)
    np.testing.assert_allclose(turned.tilt, 0.0, atol=1e-6)
    # About the point under the centre of mass instead, the same turn slides nothing.
    about_com = turned_about_z(start, angles)
    about_com[:, :2, 3] = start[:2, 3] + r - np.einsum("sij,j->si", about_com[:, :2, :2], r)
    np.testing.assert_allclose(course(start, about_com, np.ones(3), center_mass).slide, 0.0, atol=1e-12)


def test_a_rotation_a_hair_past_unit_still_reads_0_or_180_degrees_of_tilt():
    # Rotations are orthonormal only to rounding: turned 0.1273 rad about x, the start's vertical has squared
    # length 1 + 2^-52, so up . up of the unmoved object is a hair past 1 (and of it upside down a hair past -1),
    # where arccos gives nan.
    t = 0.12731365682841422
    start = np.eye(4)
    start[1:3, 1:3] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    assert (start[:3, :3] @ start[:3, :3].T)[2, 2] > 1.0
    flipped = start.copy()
    flipped[:3, :3] = np.diag([1.0, -1.0, -1.0]) @ start[:3, :3]
    c = course(start, np.stack([start, flipped]), np.zeros(2), np.zeros(3))
    np.testing.assert_array_equal(c.tilt, [0.0, 180.0])


@pytest.mark.parametrize("c, toppled, kind", [
    (made([0, 4, 30], [0, 0, 0.004]), True, "tips first"),
    (made([0, 4, 30], [0, 0.004, 0.01]), True, "tips first"),  # tipping and sliding begin on the same step: tipping first
    (made([0, 1, 30], [0, 0.004, 0.01]), True, "slides, then tips"),
    (made([0, 1, 2], [0, 0, 0]), True, "slides, then tips"),  # it left its pose without tipping past the onset: not tipped first
    (made([0, 10, 20], [0, 0, 0]), False, "tips, falls back"),
    (made([0, 1, 1], [0, 0.002, 0.006]), False, "slides or turns, no tip"),
    (made([0, 1, 1], [0, 0, 0], yaw=[0, 3, 6]), False, "slides or turns, no tip"),
    (made([0, 2, 4], [0, 0, 0], pressing=[0, 19, 20]), False, "stalls"),
    (made([0, 2, 4], [0, 0, 0], pressing=[0, 1, 2]), False, "stays"),
    (made([0, 20, 80], [0, 0.01, 0.02], pressing=[0, 0, 0]), True, "no contact"),
    # Each threshold is a bound the reading must pass, not reach: 3 degrees is not tipping, 3 mm not sliding,
    (made([0, 3, 30], [0, 0.004, 0.01]), True, "slides, then tips"),
    (made([0, 4, 30], [0.003, 0.003, 0.01]), True, "tips first"),
    # 8 degrees not tipped and fallen back, 5 mm or 5 degrees at the end not moved;
    (made([0, 8, 2], [0, 0, 0]), False, "stays"),
    (made([0, 1, 1], [0, 0.004, -0.005]), False, "stays"),
    (made([0, 1, 1], [0, 0, 0], yaw=[0, 3, -5]), False, "stays"),
    # but pressing with exactly 0.9 of the limit (18 of 20 N) is stalling.
    (made([0, 2, 4], [0, 0, 0], pressing=[0, 18, 18]), False, "stalls"),
])
def test_each_course_kind_by_hand(c, toppled, kind):
    assert kind in KINDS
    assert course_kind(c, toppled, 20.0) == kind


def test_tip_sides_split_at_45_and_135_degrees_either_way():
    push = np.array([1.0, 0.0, -0.7])
    for degrees, side in [(0, "away"), (44, "away"), (-44, "away"), (46, "sideways"), (-90, "sideways"), (134, "sideways"),
                          (136, "towards"), (-179, "towards"), (180, "towards")]:
        a = np.radians(degrees)
        angle = tip_angle(np.array([np.cos(a), np.sin(a)]), push)
        assert angle == pytest.approx(degrees if degrees != 180 else 180.0, abs=1e-9)
        assert tip_side(angle) == side
    assert set(SIDES) == {"away", "sideways", "towards"}


def test_tip_angles_are_measured_from_the_pushs_own_heading_whatever_it_is():
    # The same split under pushes heading 30, 120 and -150 degrees: only the angle between them counts.
    for heading in (30.0, 120.0, -150.0):
        h = np.radians(heading)
        push = np.array([2.0 * np.cos(h), 2.0 * np.sin(h), 0.5])
        for degrees, side in [(0, "away"), (40, "away"), (-40, "away"), (60, "sideways"), (-100, "sideways"), (170, "towards")]:
            a = h + np.radians(degrees)
            angle = tip_angle(np.array([np.cos(a), np.sin(a)]), push)
            assert angle == pytest.approx(degrees, abs=1e-9)
            assert tip_side(angle) == side


def test_a_diagonal_tip_lies_on_the_sideways_bands_closed_ends():
    # A tip straight along a diagonal of the push reads exactly 45 or 135 degrees: both ends belong to sideways.
    push = np.array([1.0, 0.0, -0.5])
    for x, y in [(1, 1), (1, -1), (-1, 1), (-1, -1)]:
        angle = tip_angle(np.array([x, y]) / np.sqrt(2.0), push)
        assert abs(angle) == (45.0 if x > 0 else 135.0)
        assert tip_side(angle) == "sideways"
    assert tip_side(44.9) == "away" and tip_side(45.5) == "sideways" and tip_side(135.5) == "towards"


def test_the_tipped_edge_is_the_one_facing_the_lean_and_its_landing_is_named_by_its_chain():
    obj, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edge, off = tipped_edge(pose, center_mass, np.array([-np.cos(0.1), np.sin(0.1)]))
    assert off == pytest.approx(np.degrees(0.1), abs=1e-6)
    outward = pose.base_edges[edge, 1] - pose.base_edges[edge, 0]
    assert np.cross(outward, [0.0, 0.0, 1.0])[0] < 0  # counter-clockwise: the outward normal of the -x side
    assert pose.edge_final_pose[edge] == pose_with_down(pose_set, [-1, 0, 0])
    assert landing_kind(pose, edge, pose.edge_final_pose[edge]) == "first pose"
    assert landing_kind(pose, edge, -1) == "elsewhere"
    chain = {pose.edge_final_pose[edge], pose.edge_momentum_pose[edge], pose.edge_onward_pose[edge]}
    other = next(p.index for p in pose_set.poses if p.index not in chain)
    assert landing_kind(pose, edge, other) == "elsewhere"
    assert set(LANDINGS) == {"first pose", "rolled on", "onward", "elsewhere"}


def test_the_line_from_the_centre_of_mass_through_the_contact_crosses_the_edge_it_points_at():
    # The standing box's base is 5 x 8 cm about its centre of mass's foot: a contact beyond the +x side, or
    # above the base towards it, names that side; one towards a corner names the side the ray meets first.
    obj, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    base = pose.base_edges[:, :, :2]
    half = np.abs(base.reshape(-1, 2)).max(axis=0)  # (2,): the base's half extents in the pose frame
    geometry_outward = lambda edge: np.cross(pose.base_edges[edge, 1] - pose.base_edges[edge, 0], [0.0, 0.0, 1.0])[:2]
    for direction in ([1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]):
        for reach in (0.3, 1.5):  # over the base, and overhanging it
            contact = center_mass + np.array([*(reach * half * direction), 0.05])
            edge = line_edge(pose, center_mass, contact)
            assert unit(geometry_outward(edge)) @ direction == pytest.approx(1.0)
    # Towards a corner, the ray leaves through the side it meets first: at (0.9, 0.1) of the half extents the +x
    # side (at 1 / 0.9 of the way against 1 / 0.1 for +y), at (0.1, 0.9) the +y side.
    for share, side in (((0.9, 0.1), [1.0, 0.0]), ((0.1, 0.9), [0.0, 1.0])):
        contact = center_mass + np.array([*(3 * half * share), 0.0])
        assert unit(geometry_outward(line_edge(pose, center_mass, contact))) @ side == pytest.approx(1.0)
    assert line_edge(pose, center_mass, center_mass + [0.0, 0.0, 0.07]) == -1  # straight above: no side


def test_the_models_edge_of_a_push_is_the_one_its_trials_tip_over_most():
    # The standing box pushed high from -x along +x tips over its +x side.  Pressed straight down on its top it does
    # not tip without noise, and with the default's noise the most frequent edge of the few trials that tip.
    obj, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    config = Config()
    extent = np.abs(pose.base_edges[:, :, 0]).max()
    high = np.array([center_mass[0] - extent, center_mass[1], 0.14])
    edge, force = model_edge(obj, pose_set, standing, high, np.array([1.0, 0.0, 0.0]), config, seed=3)
    # The model's trials alone: the counts' config needs no candidates, and smoothing or maps change no trial.
    counts = dataclasses.replace(config, topple=config.topple.counted())
    alone = evaluate(obj, pose_set, standing, points=high[None], directions=np.array([[1.0, 0.0, 0.0]]), config=counts, seed=3)
    # Its mean force is the push's own row's: above the frictionless balance m g d_e / h (0.25 kg, 2.5 cm, 14 cm up:
    # 0.44 N), as the finger's friction (C.2) resists the tip, and well under twice it.
    frictionless = 0.25 * 9.81 * 0.025 / 0.14
    assert force == alone.table.mean_force[0] and frictionless < force < 2 * frictionless
    assert edge >= 0 and unit(np.cross(pose.base_edges[edge, 1] - pose.base_edges[edge, 0], [0.0, 0.0, 1.0])[:2]) @ [1.0, 0.0] \
        == pytest.approx(1.0)
    top, down = np.array([center_mass[0], center_mass[1], 0.15]), np.array([0.0, 0.0, -1.0])
    edge, force = model_edge(obj, pose_set, standing, top, down, dataclasses.replace(config, topple=noise_free()), seed=3)
    assert edge == -1 and np.isnan(force)
    outcomes = evaluate(obj, pose_set, standing, points=top[None], directions=down[None], config=counts, seed=3).table.outcomes[0]
    tipped = np.bincount(outcomes[outcomes >= 0], minlength=len(pose.base_edges))
    assert 0 < tipped.sum() < len(outcomes) / 2  # a few of the noisy trials tip
    assert model_edge(obj, pose_set, standing, top, down, config, seed=3)[0] == int(np.argmax(tipped))


def test_landings_further_down_an_edges_chain_are_rolled_on_and_onward():
    _, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    rolled, onward = (p.index for p in pose_set.poses if p.index != pose.edge_final_pose[0])
    chained = type(pose)(**{**pose.__dict__, "edge_momentum_pose": np.full_like(pose.edge_momentum_pose, rolled),
                            "edge_onward_pose": np.full_like(pose.edge_onward_pose, onward)})
    assert [landing_kind(chained, 0, x) for x in (pose.edge_final_pose[0], rolled, onward)] == ["first pose", "rolled on", "onward"]


def test_a_tip_direction_a_hair_past_unit_still_finds_its_edge_at_0_degrees():
    # unit() is unit only to rounding: straight along the -x side's outward normal and a hair long, it meets
    # that normal at cos 1 + 2^-52 and the +x side's at -(1 + 2^-52), where arccos gives nan.
    obj, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edge, off = tipped_edge(pose, center_mass, np.array([-1.0, 0.0]) * np.nextafter(1.0, 2.0))
    assert off == 0.0
    assert pose.edge_final_pose[edge] == pose_with_down(pose_set, [-1, 0, 0])


def test_the_standing_box_pushed_high_tips_first_away_from_the_finger_and_tracing_changes_nothing():
    obj, pose_set, standing = standing_box()
    body, transform = body_model(obj), pose_set.poses[standing].transform
    played, c = traced_play(body, transform, PUSH_POINT, PUSH_DIRECTION, Config(), None)
    untraced = play_push(body, transform, PUSH_POINT, PUSH_DIRECTION, Config())
    np.testing.assert_array_equal(played.final_transform, untraced.final_transform)  # the observer only reads
    assert len(c.tilt) == len(c.pressing) == len(c.slide) > 100
    assert c.pressing.max() > 0.0 and c.tilt.max() > 10.0  # past the tip tilt within the stroke; it falls on after
    # Pressing is the finger's normal force on the object alone: nothing before the finger arrives (it starts
    # short of the contact), and its largest the player's own peak force.
    assert c.pressing[0] == 0.0 and c.pressing.max() == played.peak_force
    assert course_kind(c, True, Config().topple.max_finger_force) == "tips first"
    assert tip_side(tip_angle(c.tip_direction, played.direction)) == "away"
    center_mass = transform_points(transform, obj.center_mass[None])[0]
    edge, off = tipped_edge(pose_set.poses[standing], center_mass, c.tip_direction)
    assert off < 5.0
    assert pose_set.poses[standing].edge_final_pose[edge] == pose_with_down(pose_set, [-1, 0, 0])


def test_a_traced_play_plays_the_noise_it_is_given():
    obj, pose_set, standing = standing_box()
    body, transform = body_model(obj), pose_set.poses[standing].transform
    noise = draw_noise(world_config("thesis"), np.random.default_rng(5), noise=True)
    played, _ = traced_play(body, transform, PUSH_POINT, PUSH_DIRECTION, Config(), noise)
    assert played.noise is noise
    np.testing.assert_array_equal(played.point, transform_points(played.start_transform, PUSH_POINT[None])[0] + noise.contact_offset)
    untraced = play_push(body, transform, PUSH_POINT, PUSH_DIRECTION, Config(), noise)
    np.testing.assert_array_equal(played.final_transform, untraced.final_transform)


def plan_of(directions_z: list[float], actions: list[int]):
    """A made-up plan: pose i pushes with action actions[i] (NO_OP: none), direction z directions_z[i]."""
    from types import SimpleNamespace

    pushes = {(pose, a): (np.zeros(3), np.array([np.sqrt(1 - z * z), 0.0, z]), 0.5)
              for pose, (z, a) in enumerate(zip(directions_z, actions)) if a != NO_OP}
    return SimpleNamespace(actions={"value_iteration": np.array(actions)}, pushes=pushes)


def test_each_direction_class_gets_one_start_per_object_at_most_and_the_draw_is_seeded():
    plans = {f"o{i}": plan_of([-0.9, 0.0, 0.0, 0.8, -0.5], [3, 4, NO_OP, 1, 2]) for i in range(5)}
    chosen = chosen_pushes(plans, "value_iteration", 3, seed=1)
    assert chosen == chosen_pushes(plans, "value_iteration", 3, seed=1)
    by_class = {}
    for object_id, pose, action in chosen:
        z = plans[object_id].pushes[(pose, action)][1][2]
        by_class.setdefault("above" if z < -0.3 else "below" if z >= 0.3 else "side", []).append(object_id)
    assert {k: len(v) for k, v in by_class.items()} == {"above": 3, "side": 3, "below": 3}
    assert all(len(set(v)) == len(v) for v in by_class.values())
    assert all(action != NO_OP and pose != 2 for _, pose, action in chosen)
    # Both from-above poses are drawn from over seeds; an object without a class's push gives none.
    poses = {pose for s in range(20) for o, pose, _ in chosen_pushes(plans, "value_iteration", 5, s) if pose in (0, 4)}
    assert poses == {0, 4}
    assert chosen_pushes({"x": plan_of([0.0], [NO_OP])}, "value_iteration", 3, 0) == []


def course_of(tilt, pressing, tip=(1.0, 0.0)) -> Course:
    """A made-up course that never slides or turns, leaning along ``tip``."""
    tilt = np.asarray(tilt, dtype=float)
    return Course(tilt, np.zeros_like(tilt), np.zeros_like(tilt), np.asarray(pressing, dtype=float), np.asarray(tip))


def test_a_play_is_described_against_its_rows_and_values_by_hand(dataset, monkeypatch):  # noqa: F811 (fixture)
    # play_object's bookkeeping with the physics replaced: each play's course and landing pose are given, so
    # its topple, kind, side, landing, values and probability can be worked out by hand from the rows.
    from pipeline.model.contacts import snap_to_surface
    from pipeline.model.evaluation import load_object
    from pipeline.model.poses import stable_poses
    from schema.reader import Dataset

    ds = Dataset.open(dataset)
    config, world = dataset_config(ds), world_config("thesis")
    limit = config.topple.max_finger_force
    plans = object_plans(ds, ["random_000", "random_002"])
    obj = load_object(plans["random_002"].spec, config)
    pose_set = stable_poses(obj, config.poses)
    n = len(pose_set.poses)
    assert n >= 3
    v_s = np.linspace(0.1, 0.8, n)
    # Pose-frame pushes: from above at pose 0, from the side at pose 1, from below at pose 2.
    # Each point is put on the surface, where the dataset's pushes are (the model refuses a push off it).
    near = {(0, 1): (np.array([0.01, -0.02, 0.03]), np.array([0.6, 0.0, -0.8]), 0.35),
            (1, 2): (np.array([0.0, 0.01, 0.02]), np.array([0.0, 1.0, 0.0]), 0.2),
            (2, 3): (np.array([-0.01, 0.0, 0.01]), np.array([0.8, 0.0, 0.6]), 0.9)}
    pushes = {(p, a): (snap_to_surface(obj, pose_set.poses[p].transform, point[None])[0][0], direction, q)
              for (p, a), (point, direction, q) in near.items()}
    plan = dataclasses.replace(plans["random_002"], v_s=v_s, pushes=pushes)
    rows = [np.zeros((4, n)) for _ in range(n)]
    rows[0][1] = np.arange(1.0, n + 1) / np.arange(1.0, n + 1).sum()  # P(x' | 0, 1) grows with x'
    rows[1][2] = np.full(n, 0.3 / (n - 1))
    rows[1][2][1] = 0.7  # P(topple) 0.3, spread evenly over the other poses
    rows[2][3][2] = 1.0  # never topples, by the rows
    # The tipped edge for a lean to +x and to +y (the world is the pose frame at the start).
    center_mass = {p: transform_points(pose_set.poses[p].transform, obj.center_mass[None])[0] for p in range(3)}
    first_x = int(pose_set.poses[0].edge_final_pose[tipped_edge(pose_set.poses[0], center_mass[0], np.array([1.0, 0.0]))[0]])
    assert first_x not in (0, -1)
    # (start pose, landed, course, tip side expected, landing expected): per start three plays.
    script = [
        (0, 0, course_of([0, 2, 4], [0, limit, limit]), None, None),  # stays put, pressing at the limit: stalls
        (0, first_x, course_of([0, 4, 30], [0, 5, 5]), "away", "first pose"),
        (0, -1, course_of([0, 4, 30], [0, 5, 5], tip=(0.0, 1.0)), "sideways", "elsewhere"),  # lands outside the pose set
        (1, 0, course_of([0, 4, 30], [0, 5, 5], tip=(0.0, -1.0)), "towards", None),
        (1, 1, course_of([0, 10, 1], [0, 5, 0]), None, None),  # tips and falls back
        (1, 2, course_of([0, 1, 30], [0, 5, 5], tip=(0.0, 1.0)), "away", None),
        (2, 2, course_of([0, 1, 1], [0, 0, 0]), None, None),  # never touched
        (2, 0, course_of([0, 4, 30], [0, 5, 5]), "away", None),  # a topple the rows give no chance
        (2, 2, course_of([0, 1, 1], [0, 1, 1]), None, None),
    ]
    world_direction = {0: np.array([1.0, 0.0, -1.0]), 1: np.array([0.0, 1.0, 0.0]), 2: np.array([1.0, 0.0, 1.0])}
    calls, played_poses = [], iter(p for p, *_ in script)
    landed_poses = iter(landed for _, landed, *_ in script)
    courses = iter(c for _, _, c, *_ in script)

    def traced(body, transform, point, direction, config_, noise):
        calls.append((transform, point, direction, noise))
        return SimpleNamespace(direction=world_direction[next(played_poses)], final_transform=np.eye(4), start_transform=transform), next(courses)

    monkeypatch.setattr(push_course, "traced_play", traced)
    monkeypatch.setattr("pipeline.model.poses.settle", lambda *args: next(landed_poses))
    plays = play_object(plan, [(0, 1), (1, 2), (2, 3)], rows, config, world, 3, seed=11)
    assert len(plays) == 9
    for play, (pose, landed, c, side, landing), (transform, point, direction, noise) in zip(plays, script, calls):
        action = {0: 1, 1: 2, 2: 3}[pose]
        row, (pose_point, pose_direction, predicted) = rows[pose][action], pushes[(pose, action)]
        # The push handed to the player is the plan's, carried from the pose frame into the object frame.
        np.testing.assert_allclose(transform_points(transform, point[None])[0], pose_point, atol=1e-12)
        np.testing.assert_allclose(transform[:3, :3] @ direction, pose_direction, atol=1e-12)
        assert isinstance(noise, PushNoise) and np.any(noise.contact_offset != 0.0)  # a noisy draw from the world
        assert play.object_id == "random_002" and play.predicted == predicted
        assert play.direction == {0: "above", 1: "side", 2: "below"}[pose]
        assert play.toppled is (landed != pose)
        assert play.kind == course_kind(c, landed != pose, limit)
        if landed == pose:
            assert (play.side, play.landing, play.value_expected, play.value_landed, play.landing_probability) == (None,) * 5
            continue
        topple = 1.0 - row[pose]
        others = [x for x in range(n) if x != pose]
        assert play.value_expected == (pytest.approx(sum(row[x] * v_s[x] for x in others) / topple) if topple > 0 else None)
        assert play.value_landed == (pytest.approx(v_s[landed]) if landed >= 0 else 0.0)
        assert play.landing_probability == (pytest.approx(row[landed] / topple) if topple > 0 and landed >= 0 else 0.0)
        assert play.side == side
        if landing is not None:
            assert play.landing == landing
        else:  # its own edge's chain, as landing_kind reads it
            edge, _ = tipped_edge(pose_set.poses[pose], center_mass[pose], c.tip_direction)
            assert play.landing == landing_kind(pose_set.poses[pose], edge, landed)
    assert [p.kind for p in plays[:3]] == ["stalls", "tips first", "tips first"]
    assert [p.kind for p in plays[3:6]] == ["tips first", "tips, falls back", "tips first"]
    assert [p.kind for p in plays[6:]] == ["no contact", "tips first", "stays"]
    assert plays[7].value_expected is None and plays[7].landing_probability == 0.0  # P(topple) 0: nothing to divide by
    assert plays[1].value_landed == pytest.approx(v_s[first_x]) and plays[2].value_landed == 0.0
    # Every play draws its own noise; the draws are seeded by object, pose and action, not shared between objects.
    offsets = [noise.contact_offset.tolist() for *_, noise in calls]
    assert len({tuple(o) for o in offsets}) == 9
    m = len(plans["random_000"].transforms)
    obj = load_object(plans["random_000"].spec, config)
    first = stable_poses(obj, config.poses).poses[0]
    point, direction, q = near[0, 1]
    other = dataclasses.replace(plans["random_000"], v_s=np.zeros(m),
                                pushes={(0, 1): (snap_to_surface(obj, first.transform, point[None])[0][0], direction, q)})
    calls.clear()
    played_poses, landed_poses, courses = iter([0]), iter([0]), iter([course_of([0, 1, 1], [0, 1, 1])])
    play_object(other, [(0, 1)], [np.full((4, m), 1.0 / m)], config, world, 1, seed=11)
    assert calls[0][3].contact_offset.tolist() != offsets[0]


def test_a_play_refuses_an_object_whose_stable_poses_differ_from_the_datasets(dataset):  # noqa: F811 (fixture)
    # Fewer poses under a higher drop-probability floor (8 -> 7): the plan's poses are no longer the model's.
    from schema.reader import Dataset

    ds = Dataset.open(dataset)
    config = dataset_config(ds)
    plan = object_plans(ds, ["random_002"])["random_002"]
    fewer = dataclasses.replace(config, poses=dataclasses.replace(config.poses, min_probability=0.05))
    # Reported as the object's one-line reason, not raised: the other objects are still played.
    reason = "random_002: its stable poses differ from the dataset's (other code or parameters)"
    assert play_object(plan, [], [], fewer, world_config("thesis"), 1, 0) == reason
    # As many poses, one of them placed 1 mm apart: every row index would name another placement.
    moved = plan.transforms.copy()
    moved[0, 0, 3] += 0.001
    assert play_object(dataclasses.replace(plan, transforms=moved), [], [], config, world_config("thesis"), 1, 0) == reason
    assert play_object(plan, [], [], config, world_config("thesis"), 1, 0) == []  # as the dataset had them: played


def test_the_summary_by_hand_with_topples_clustered_by_object():
    def play(o, toppled, kind, side=None, landing=None, expected=None, landed=None, probability=None, direction="above",
             edge=-1, model=-1, line=-1, angle=None, force=np.nan, in_model=False, in_line=False):
        return Play(o, direction, 0.6, toppled, kind, side, landing, expected, landed, probability, 0, 0, 1 if toppled else 0,
                    edge, model, line, angle, 0.0, force, in_model, in_line)

    plays = [play("a", True, "tips first", "away", "first pose", 0.5, 0.7, 0.8, edge=1, model=1, line=2, angle=10.0,
                  force=0.5, in_model=True),
             play("a", True, "slides, then tips", "towards", "elsewhere", 0.5, 0.1, 0.0, edge=2, model=1, line=2, angle=170.0,
                  force=3.0, in_line=True),
             play("b", False, "stalls", model=3, line=3), play("b", True, "tips first", "away", "rolled on", 0.4, 0.4, 0.5,
                                                               edge=0, model=0, line=0, angle=20.0, force=2.0,
                                                               in_model=True, in_line=True),
             play("c", False, "tips, falls back", direction="side")]
    s = summary(plays)
    above = s["above"]
    assert above["plays"] == 4 and above["objects"] == 2 and above["topples"] == 3 and above["untouched_topples"] == 0
    assert above["toppled_minus_predicted"]["mean"] == pytest.approx(0.75 - 0.6)
    # A start that fell with no finger on it counts as toppled, but its lean and landing are not the push's.
    untouched = summary([*plays, play("d", True, "no contact", "away", "elsewhere", 0.5, 0.0, 0.0)])["above"]
    assert untouched["toppled"]["mean"] == pytest.approx(0.8) and untouched["topples"] == 3 and untouched["untouched_topples"] == 1
    assert untouched["sides"] == above["sides"] and untouched["value_landed_minus_expected"] == above["value_landed_minus_expected"]
    assert above["toppled"]["mean"] == pytest.approx(0.75)
    assert above["courses"]["tips first"] == pytest.approx(0.5) and above["courses"]["stalls"] == pytest.approx(0.25)
    assert sum(above["courses"].values()) == pytest.approx(1.0)
    assert above["sides"] == {"away": pytest.approx(2 / 3), "sideways": 0.0, "towards": pytest.approx(1 / 3)}
    assert above["landings"]["elsewhere"] == pytest.approx(1 / 3)
    assert above["value_landed_minus_expected"]["mean"] == pytest.approx((0.2 - 0.4 + 0.0) / 3)
    assert above["value_landed_minus_expected"]["objects"] == 2 and above["value_landed_minus_expected"]["plays"] == 3
    assert above["value_expected"]["mean"] == pytest.approx((0.5 + 0.5 + 0.4) / 3)
    assert above["value_landed"]["mean"] == pytest.approx((0.7 + 0.1 + 0.4) / 3)
    assert above["landing_probability"]["mean"] == pytest.approx((0.8 + 0.0 + 0.5) / 3)
    # Object a's two topples are one cluster: differences (+0.2, -0.4) and (0.0) -> cluster sums -0.2 and 0.0.
    mean = -0.2 / 3
    se = np.sqrt(2 / 1 * ((-0.2 - mean * 2) ** 2 + (0.0 - mean) ** 2) / 9)
    assert above["value_landed_minus_expected"]["se"] == pytest.approx(se)
    # The edges named over the three topples: the model's 2 of 3, the line's 2 of 3; tipped back, one, the line's.
    named = above["edge_named"]
    assert named["model"]["mean"] == pytest.approx(2 / 3) and named["line"]["mean"] == pytest.approx(2 / 3)
    assert named["line_minus_model"]["mean"] == pytest.approx(0.0) and named["model"]["topples"] == 3
    back = above["edge_named_tipped_back"]
    assert back["model"]["mean"] == 0.0 and back["line"]["mean"] == 1.0 and back["model"]["topples"] == 1
    # Landings by chain, split at TIP_BACK_FORCE (0.7 N): two hard pushes (3.0, 2.0 N) and one light (0.5 N).
    hard, light = above["landing_chains"]["hard"], above["landing_chains"]["light"]
    assert hard["model"]["topples"] == 2 and hard["model"]["mean"] == 0.5 and hard["line"]["mean"] == 1.0
    assert hard["line_minus_model"]["mean"] == 0.5
    assert light["model"]["topples"] == 1 and light["model"]["mean"] == 1.0 and light["line"]["mean"] == 0.0
    assert s["side"]["topples"] == 0 and "sides" not in s["side"]
    assert "below" not in s


def test_the_summary_keeps_every_class_with_plays_and_leaves_empty_what_it_cannot_estimate():
    # No pushes from above: the classes after it are still summed up.  One object a class: no standard error
    # from one cluster.  Topples whose rows gave them no chance (no expected value): no values at all.
    plays = [Play("a", "side", 0.2, True, "tips first", "away", "first pose", None, 0.5, 0.0, 0, 3, 1, 2, 2, 1, 10.0, 0.0, 1.0,
                  True, False),
             Play("a", "side", 0.2, False, "stays", None, None, None, None, None, 0, 3, 0, -1, 2, 1, None, 0.0, 1.0, False, False),
             Play("b", "below", 0.9, True, "tips first", "away", "onward", 0.3, 0.6, 0.25, 1, 5, 0, 0, 0, 0, 5.0, 0.0, 2.0, True,
                  True),
             Play("b", "below", 0.9, True, "slides, then tips", "sideways", "first pose", 0.3, 0.2, 0.5, 1, 5, 2, 1, 0, 0, 60.0,
                  0.01, 2.0, False, True)]
    s = summary(plays)
    assert list(s) == ["side", "below"]
    side, below = s["side"], s["below"]
    assert side["toppled"] == {"mean": 0.5, "se": None, "objects": 1, "plays": 2}
    assert side["topples"] == 1 and side["landing_probability"] == {"mean": 0.0, "se": None, "objects": 1, "plays": 1}
    assert side["value_expected"] is None and side["value_landed"] is None and side["value_landed_minus_expected"] is None
    assert below["value_expected"] == {"mean": pytest.approx(0.3), "se": None, "objects": 1, "plays": 2}
    assert below["value_landed"]["mean"] == pytest.approx(0.4) and below["value_landed_minus_expected"]["mean"] == pytest.approx(0.1)
    assert below["predicted"]["mean"] == pytest.approx(0.9) and below["landing_probability"]["mean"] == pytest.approx(0.375)
    assert below["sides"] == {"away": 0.5, "sideways": 0.5, "towards": 0.0}


def test_the_text_reads_each_class_its_topples_and_standard_errors_where_there_are_any():
    above = {"plays": 4, "objects": 2, "predicted": {"mean": 0.6}, "toppled": {"mean": 0.75, "se": 0.125},
             "toppled_minus_predicted": {"mean": 0.15, "se": 0.1}, "untouched_topples": 1,
             "courses": {"tips first": 0.5, "stalls": 0.25, "slides, then tips": 0.25}, "topples": 3,
             "sides": {"away": 2 / 3, "sideways": 0.0, "towards": 1 / 3},
             "landings": {"first pose": 1 / 3, "rolled on": 1 / 3, "onward": 0.0, "elsewhere": 1 / 3},
             "landing_probability": {"mean": 0.4333}, "value_expected": {"mean": 0.4667}, "value_landed": {"mean": 0.4},
             "value_landed_minus_expected": {"mean": -0.0667, "se": 0.0471}}
    side = {"plays": 1, "objects": 1, "predicted": {"mean": 0.2}, "toppled": {"mean": 0.0, "se": None}, "courses": {"stays": 1.0},
            "toppled_minus_predicted": {"mean": -0.2, "se": None}, "topples": 0, "untouched_topples": 0}
    below = {"plays": 2, "objects": 1, "predicted": {"mean": 0.9}, "toppled": {"mean": 1.0, "se": None}, "courses": {"tips first": 1.0},
             "toppled_minus_predicted": {"mean": 0.1, "se": None}, "topples": 2, "untouched_topples": 0, "sides": {"away": 1.0}, "landings": {"elsewhere": 1.0}, "landing_probability": {"mean": 0.0},
             "value_expected": None}
    result = {"policy": "greedy", "dataset": "data/x", "pushes": 3, "repeats": 2, "seed": 7,
              "failed_objects": {"bad": "bad: its mesh does not load"}, "by_direction": {"above": above, "side": side, "below": below}}
    assert text(result).split("\n") == [
        "greedy's pushes on data/x, 3 pushes x 2 plays (seed 7):",
        "  not played: bad: its mesh does not load",
        "from above: 4 plays on 2 objects; predicted 0.600, toppled 0.750 +/- 0.125 (difference +0.150 +/- 0.100)",
        "  courses: tips first 0.50, stalls 0.25, slides, then tips 0.25",
        "  3 pushed topples (and 1 with no finger on it); sides: away 0.67, sideways 0.00, towards 0.33",
        "  landings against the tipped edge's poses: first pose 0.33, rolled on 0.33, onward 0.00, elsewhere 0.33",
        "  the rows' probability of the landing pose 0.433",
        "  V_s of a topple: expected 0.467, landed 0.400 (difference -0.067 +/- 0.047)",
        "from the side: 1 plays on 1 objects; predicted 0.200, toppled 0.000 (difference -0.200)",
        "  courses: stays 1.00",
        "from below: 2 plays on 1 objects; predicted 0.900, toppled 1.000 (difference +0.100)",
        "  courses: tips first 1.00",
        "  2 pushed topples; sides: away 1.00",
        "  landings against the tipped edge's poses: elsewhere 1.00",
        "  the rows' probability of the landing pose 0.000",
    ]


def test_the_study_hands_its_arguments_to_the_draw_and_the_plays(dataset, monkeypatch):  # noqa: F811 (fixture)
    # study's wiring, with the draw watched and the plays replaced (run in this process, they return nothing).
    import joblib

    from schema.reader import Dataset

    drawn, played, asked = [], [], []
    real_choice = push_course.chosen_pushes

    def choose(plans, policy, per_class, seed):
        drawn.append((sorted(plans), policy, per_class, seed))
        return real_choice(plans, policy, per_class, seed)

    def play(plan, starts, rows, config, world, repeats, seed):
        played.append((plan, starts, rows, config, world, repeats, seed))
        return []

    class InProcess(joblib.Parallel):  # what study asked for is kept; the jobs run here, where the replacements are
        def __init__(self, n_jobs=None, **kwargs):
            asked.append(n_jobs)
            super().__init__(n_jobs=1, **kwargs)

    monkeypatch.setattr(push_course, "chosen_pushes", choose)
    monkeypatch.setattr(push_course, "play_object", play)
    monkeypatch.setattr(joblib, "Parallel", InProcess)
    world = Config()  # not the thesis preset a missing world stands for
    result = study(dataset, "greedy", per_class=1, repeats=3, seed=7, world=world, workers=2)
    ds = Dataset.open(dataset)
    plans = object_plans(ds, ["random_000", "random_002"])
    chosen = real_choice(plans, "greedy", 1, 7)
    assert chosen and drawn == [(["random_000", "random_002"], "greedy", 1, 7)]
    assert result == {"dataset": str(dataset), "policy": "greedy", "per_class": 1, "repeats": 3, "seed": 7, "pushes": len(chosen),
                      "failed_objects": {}, "by_direction": {}}
    assert asked == [2]
    by_object = {}
    for object_id, pose, action in chosen:
        by_object.setdefault(object_id, []).append((pose, action))
    assert [(plan.spec.object_id, starts) for plan, starts, *_ in played] == list(by_object.items())
    for plan, _, rows, config, given_world, repeats, seed in played:
        assert given_world is world and (repeats, seed) == (3, 7) and config == dataset_config(ds)
        assert len(rows) == len(plan.transforms) and all(r.shape[1] == len(plan.transforms) for r in rows)


def test_the_command_traces_a_small_dataset_prints_and_records(dataset, tmp_path, capsys):  # noqa: F811 (fixture)
    out = tmp_path / "course.json"
    assert main([str(dataset), "--per-class", "1", "--repeats", "2", "--seed", "3", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    record = json.loads(out.read_text())
    assert record["repeats"] == 2 and record["pushes"] >= 1 and record["failed_objects"] == {}
    for entry in record["by_direction"].values():
        assert entry["plays"] == 2 and entry["objects"] == 1
        assert sum(entry["courses"].values()) == pytest.approx(1.0)
        assert f"{entry['plays']} plays on 1 objects" in printed
    again = tmp_path / "again.json"
    assert main([str(dataset), "--per-class", "1", "--repeats", "2", "--seed", "3", "--json", str(again)]) == 0
    assert json.loads(again.read_text())["by_direction"] == record["by_direction"]  # seeded: the same plays


def test_an_object_whose_mesh_does_not_load_is_reported_not_fatal(tmp_path):
    from types import SimpleNamespace

    from pipeline.build.corpus import ObjectSpec

    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")  # a face naming a vertex that does not exist
    plan = SimpleNamespace(spec=ObjectSpec("broken", str(broken), 1.0, 0.25, "test", "0" * 64), transforms=np.zeros((1, 4, 4)))
    reason = play_object(plan, [(0, 0)], [], Config(), Config(), 1, 0)
    assert isinstance(reason, str) and "broken" in reason and "\n" not in reason


def test_the_command_refuses_a_missing_dataset_and_an_unknown_policy_in_one_line(tmp_path, capsys):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert f"error: {tmp_path / 'nowhere'}" in capsys.readouterr().err  # the reader's reason, naming the directory
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--policy", "nonsense"])
    with pytest.raises(ExperimentError, match="unknown policy 'nonsense'; one of max_height, greedy, value_iteration"):
        study(tmp_path, "nonsense")


def test_the_command_passes_its_defaults_and_flags_to_the_study_and_checks_its_output_first(tmp_path, monkeypatch, capsys):
    calls = []

    def traced(*args, keep_plays):
        calls.append(args + (keep_plays,))
        result = {"dataset": str(args[0]), "policy": args[1], "per_class": args[2], "repeats": args[3], "seed": args[4],
                  "pushes": 0, "failed_objects": {}, "by_direction": {}}
        return {**result, "plays": [{"object_id": "a", "landed": 2}, {"object_id": "b", "landed": -1}]} if keep_plays else result

    monkeypatch.setattr(push_course, "study", traced)
    assert main([str(tmp_path)]) == 0
    assert main([str(tmp_path), "--policy", "greedy", "--per-class", "2", "--repeats", "3", "--seed", "4", "--workers", "2"]) == 0
    (root, policy, per_class, repeats, seed, world, workers, keep), flagged = calls
    assert not keep and not flagged[-1]
    # The documented run: value iteration, 70 objects a class, 5 plays, seed 53, one worker, the thesis world's noise.
    assert (str(root), policy, per_class, repeats, seed, workers) == (str(tmp_path), "value_iteration", 70, 5, 53, 1)
    assert world == world_config("thesis") and world != Config()
    assert flagged[1:5] == ("greedy", 2, 3, 4) and flagged[6] == 2
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--workers", "0"])
    # An output it could not write is refused before the study runs.
    calls.clear()
    capsys.readouterr()
    assert main([str(tmp_path), "--json", str(tmp_path)]) == 2
    assert calls == [] and "cannot write" in capsys.readouterr().err
    assert main([str(tmp_path), "--plays", str(tmp_path)]) == 2
    assert calls == [] and "cannot write" in capsys.readouterr().err
    # --plays: every play, a JSON line each, and the report without them.
    plays, report = tmp_path / "plays.jsonl", tmp_path / "report.json"
    assert main([str(tmp_path), "--plays", str(plays), "--json", str(report)]) == 0
    assert calls[-1][-1] is True
    assert [json.loads(line) for line in plays.read_text().splitlines()] == [{"object_id": "a", "landed": 2},
                                                                             {"object_id": "b", "landed": -1}]
    assert "plays" not in json.loads(report.read_text())


def test_the_study_reports_an_object_it_could_not_play_and_summarises_the_others(dataset, monkeypatch):  # noqa: F811 (fixture)
    def play(plan, starts, rows, config, world, repeats, seed):  # one worker: the fan-out runs it in this process
        if plan.spec.object_id == "random_000":
            return "random_000: its mesh does not load"
        return [Play(plan.spec.object_id, "side", 0.5, True, "tips first", "away", "first pose", 0.4, 0.6, 1.0, 0, 0, 1, 0, 0, 0,
                     5.0, 0.0, 1.0, True, True)]

    monkeypatch.setattr(push_course, "play_object", play)
    monkeypatch.setattr(push_course, "chosen_pushes", lambda plans, policy, per_class, seed: [("random_000", 0, 0), ("random_002", 0, 0)])
    result = study(dataset, "greedy", per_class=2, repeats=1, seed=7, world=Config(), workers=1)
    assert result["pushes"] == 2
    assert result["failed_objects"] == {"random_000": "random_000: its mesh does not load"}
    assert result["by_direction"]["side"]["objects"] == 1 and result["by_direction"]["side"]["toppled"]["mean"] == 1.0


def test_a_lean_seen_in_the_world_is_turned_back_into_the_pose_frame():
    # The object settled 2 degrees about z from where it was placed: a lean seen along world +x is, in the pose
    # frame, turned back by those 2 degrees; a placement turned 90 degrees is the pose frame's own and stays.
    turn = lambda degrees: np.array([[np.cos(np.radians(degrees)), -np.sin(np.radians(degrees)), 0, 0],
                                     [np.sin(np.radians(degrees)), np.cos(np.radians(degrees)), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    placed = np.eye(4)  # object -> pose frame
    settled = turn(2.0)  # object -> world
    np.testing.assert_allclose(push_course.lean_in_pose_frame(np.array([1.0, 0.0]), placed, settled),
                               [np.cos(np.radians(-2.0)), np.sin(np.radians(-2.0))], atol=1e-12)
    np.testing.assert_allclose(push_course.lean_in_pose_frame(np.array([0.0, 1.0]), turn(90.0), turn(92.0)),
                               [np.sin(np.radians(2.0)), np.cos(np.radians(2.0))], atol=1e-12)
