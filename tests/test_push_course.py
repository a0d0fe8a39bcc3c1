"""The push-course study: a stroke's course read from made-up transforms, the standing box traced
in pybullet, and the summary by hand; then the command on a small real dataset."""

import json

import numpy as np
import pytest
from shapes import pose_with_down, standing_box

from pipeline.model.config import Config
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
    main,
    summary,
    tip_angle,
    tip_side,
    tipped_edge,
    traced_play,
)
from pipeline.studies.pushsim import body_model, play_push
from schema.frames import transform_points
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
    c = course(np.eye(4), turned_about_y(angles, shift), np.arange(5.0), np.zeros(3), np.array([1.0, 0.0, -0.5]))
    np.testing.assert_allclose(c.tilt, angles, atol=1e-9)
    np.testing.assert_allclose(c.slide, np.arange(5) * 0.001, atol=1e-12)  # the point under the centre of mass (the origin)
    # A tip about an edge 2.5 cm away, centre of mass 7.5 cm up: the base hardly moves, the centre of mass 7.5 cm x tilt.
    pivot = np.array([0.025, 0.0, 0.0])
    tipped = turned_about_y(angles)
    tipped[:, :3, 3] = pivot - np.einsum("sij,j->si", tipped[:, :3, :3], pivot)
    tip = course(np.eye(4), tipped, np.ones(5), np.array([0.0, 0.0, 0.075]), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(tip.slide, 0.025 * (1 - np.cos(np.radians(angles))), atol=1e-12)
    np.testing.assert_allclose(c.yaw, 0.0, atol=1e-9)
    np.testing.assert_allclose(c.tip_direction, [1.0, 0.0], atol=1e-12)  # turning about +y leans the top to +x
    # Against a push towards -y the slide is sideways: nothing along it.
    assert np.allclose(course(np.eye(4), turned_about_y(angles, shift), np.zeros(5), np.zeros(3), np.array([0.0, -1.0, 0.0])).slide, 0.0)
    # A turn about the vertical is yaw, not tilt.
    turn = np.tile(np.eye(4), (2, 1, 1))
    turn[1, :2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    spun = course(np.eye(4), turn, np.zeros(2), np.zeros(3), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(spun.yaw, [0.0, np.degrees(0.3)])
    np.testing.assert_allclose(spun.tilt, 0.0, atol=1e-6)


def test_the_lean_is_read_at_the_tip_tilt_not_at_the_end():
    # It leans to +x first, then (past 8 degrees) swings round to +y: the tip's direction is the first.
    first = turned_about_y(np.array([0.0, 4.0, 9.0]))
    swing = np.eye(4)
    swing[:3, :3] = [[1, 0, 0], [0, np.cos(-0.8), -np.sin(-0.8)], [0, np.sin(-0.8), np.cos(-0.8)]]  # about x: up leans to +y
    c = course(np.eye(4), np.concatenate([first, swing[None]]), np.ones(4), np.zeros(3), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(c.tip_direction, [1.0, 0.0], atol=1e-12)
    # Never tipped that far: read at the largest tilt.
    small = course(np.eye(4), turned_about_y(np.array([0.0, 3.0, 1.0])), np.ones(3), np.zeros(3), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(small.tip_direction, [1.0, 0.0], atol=1e-12)


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


def test_landings_further_down_an_edges_chain_are_rolled_on_and_onward():
    _, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    rolled, onward = (p.index for p in pose_set.poses if p.index != pose.edge_final_pose[0])
    chained = type(pose)(**{**pose.__dict__, "edge_momentum_pose": np.full_like(pose.edge_momentum_pose, rolled),
                            "edge_onward_pose": np.full_like(pose.edge_onward_pose, onward)})
    assert [landing_kind(chained, 0, x) for x in (pose.edge_final_pose[0], rolled, onward)] == ["first pose", "rolled on", "onward"]


def test_the_standing_box_pushed_high_tips_first_away_from_the_finger_and_tracing_changes_nothing():
    obj, pose_set, standing = standing_box()
    body, transform = body_model(obj), pose_set.poses[standing].transform
    played, c = traced_play(body, transform, PUSH_POINT, PUSH_DIRECTION, Config(), None)
    untraced = play_push(body, transform, PUSH_POINT, PUSH_DIRECTION, Config())
    np.testing.assert_array_equal(played.final_transform, untraced.final_transform)  # the observer only reads
    assert len(c.tilt) == len(c.pressing) == len(c.slide) > 100
    assert c.pressing.max() > 0.0 and c.tilt.max() > 10.0  # past the tip tilt within the stroke; it falls on after
    assert course_kind(c, True, Config().topple.max_finger_force) == "tips first"
    assert tip_side(tip_angle(c.tip_direction, played.direction)) == "away"
    center_mass = transform_points(transform, obj.center_mass[None])[0]
    edge, off = tipped_edge(pose_set.poses[standing], center_mass, c.tip_direction)
    assert off < 5.0
    assert pose_set.poses[standing].edge_final_pose[edge] == pose_with_down(pose_set, [-1, 0, 0])


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


def test_the_summary_by_hand_with_topples_clustered_by_object():
    def play(o, toppled, kind, side=None, landing=None, expected=None, landed=None, probability=None, direction="above"):
        return Play(o, direction, 0.6, toppled, kind, side, landing, expected, landed, probability)

    plays = [play("a", True, "tips first", "away", "first pose", 0.5, 0.7, 0.8),
             play("a", True, "slides, then tips", "towards", "elsewhere", 0.5, 0.1, 0.0),
             play("b", False, "stalls"), play("b", True, "tips first", "away", "rolled on", 0.4, 0.4, 0.5),
             play("c", False, "tips, falls back", direction="side")]
    s = summary(plays)
    above = s["above"]
    assert above["plays"] == 4 and above["objects"] == 2 and above["topples"] == 3
    assert above["toppled"]["mean"] == pytest.approx(0.75)
    assert above["courses"]["tips first"] == pytest.approx(0.5) and above["courses"]["stalls"] == pytest.approx(0.25)
    assert sum(above["courses"].values()) == pytest.approx(1.0)
    assert above["sides"] == {"away": pytest.approx(2 / 3), "sideways": 0.0, "towards": pytest.approx(1 / 3)}
    assert above["landings"]["elsewhere"] == pytest.approx(1 / 3)
    assert above["value_landed_minus_expected"]["mean"] == pytest.approx((0.2 - 0.4 + 0.0) / 3)
    assert above["value_landed_minus_expected"]["objects"] == 2
    # Object a's two topples are one cluster: differences (+0.2, -0.4) and (0.0) -> cluster sums -0.2 and 0.0.
    mean = -0.2 / 3
    se = np.sqrt(2 / 1 * ((-0.2 - mean * 2) ** 2 + (0.0 - mean) ** 2) / 9)
    assert above["value_landed_minus_expected"]["se"] == pytest.approx(se)
    assert s["side"]["topples"] == 0 and "sides" not in s["side"]
    assert "below" not in s


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


def test_an_object_that_cannot_be_played_is_reported_not_fatal(tmp_path):
    from types import SimpleNamespace

    import trimesh

    from pipeline.build.corpus import ObjectSpec
    from pipeline.studies.push_course import play_object

    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")  # a face naming a vertex that does not exist
    plan = SimpleNamespace(spec=ObjectSpec("broken", str(broken), 1.0, 0.25, "test", "0" * 64), transforms=np.zeros((1, 4, 4)))
    reason = play_object(plan, [(0, 0)], [], Config(), Config(), 1, 0)
    assert isinstance(reason, str) and "broken" in reason and "\n" not in reason
    # A mesh that loads but whose stable poses are not the dataset's (one pose given; a box has several).
    box = tmp_path / "box.stl"
    mesh = trimesh.creation.box((0.05, 0.08, 0.15))
    mesh.export(box)
    plan = SimpleNamespace(spec=ObjectSpec("box", str(box), 1.0, 0.25, "test", "0" * 64), transforms=np.eye(4)[None])
    assert play_object(plan, [(0, 0)], [], Config(), Config(), 1, 0) == "box: its stable poses differ from the dataset's (other code or parameters)"


def test_the_command_refuses_a_missing_dataset_and_an_unknown_policy_in_one_line(tmp_path, capsys):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "error:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--policy", "nonsense"])
