"""The validation report: metrics on hand-made cases, the log reader's per-row checks, the report end to end."""

import json
import math
import re
from dataclasses import replace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import trimesh
from shapes import THESIS

from pipeline.build.atomic import file_sha256
from pipeline.model.config import VARIANTS, Config
from pipeline.studies.logreader import OUTSIDE, LogError, PushLog, logs_under, read_log
from pipeline.studies.scoring import Scorer, Scores, brier_floor, brier_score, sup_tv, topple_spread
from pipeline.studies.synthetic_log import planar
from pipeline.studies.validation import (
    SPREAD_SHARE,
    average_precision,
    bootstrap_difference,
    bootstrap_intervals,
    by_direction,
    expected_calibration_error,
    log_direction_classes,
    main,
    push_metrics,
    ranking_by_direction,
    reliability,
    report,
)
from schema.pushlog import PUSHLOG

BOX = (0.05, 0.08, 0.15)


# ---------------------------------------------------------------- metrics on hand-made numbers


def test_total_variation_sup_form():
    p = np.array([[0.2, 0.3, 0.5]])
    assert sup_tv(p, p)[0] == 0.0
    assert sup_tv(np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.5, 0.5]]))[0] == 1.0
    assert sup_tv(np.array([[0.5, 0.5]]), np.array([[0.25, 0.75]]))[0] == pytest.approx(0.25)
    assert sup_tv(np.array([[0.7, 0.1, 0.2]]), np.array([[0.4, 0.5, 0.1]]))[0] == pytest.approx(0.4)


def test_average_precision_on_hand_made_rankings():
    labels = np.array([True, True, False, False])
    assert average_precision([0.9, 0.8, 0.3, 0.1], labels) == 1.0
    assert average_precision([0.1, 0.2, 0.8, 0.9], labels) == pytest.approx((1 / 3 + 2 / 4) / 2)
    assert average_precision([0.9, 0.1, 0.8, 0.2], labels) == pytest.approx((1 + 2 / 4) / 2)  # ranks 1 and 4
    # One tie of all scores: precision is the base rate, whatever the order.
    assert average_precision([1.0, 1.0, 1.0, 1.0], labels) == pytest.approx(0.5)
    assert np.isnan(average_precision([0.5, 0.5], [False, False]))


def test_reliability_bins_and_ece_on_hand_made_bins():
    predicted = np.array([0.05, 0.05, 0.15, 0.15, 0.85, 0.85, 1.0])
    observed = np.array([0.0, 0.1, 0.5, 0.5, 0.9, 0.7, 1.0])
    result = reliability(predicted, observed, n_bins=10)
    counts = [b["count"] for b in result["bins"]]
    assert counts == [2, 2, 0, 0, 0, 0, 0, 0, 2, 1]  # 1.0 falls in the last bin
    assert result["bins"][1]["observed"] == pytest.approx(0.5)
    assert result["bins"][2]["predicted"] is None
    # Bin gaps: |0.05 - 0.05| = 0, |0.15 - 0.5| = 0.35, |0.85 - 0.8| = 0.05, |1 - 1| = 0
    assert result["ece"] == pytest.approx((2 * 0.0 + 2 * 0.35 + 2 * 0.05 + 1 * 0.0) / 7)
    # Calibrated within each bin (mean observed = mean predicted) is perfect, whatever the spread.
    assert expected_calibration_error([0.05, 0.05, 0.55], [0.0, 0.1, 0.55]) == pytest.approx(0.0, abs=1e-12)
    assert expected_calibration_error(np.full(4, 0.9), np.zeros(4)) == pytest.approx(0.9)


def test_push_metrics_informative_and_labels():
    tv = np.array([0.0, 0.0, 0.4, 0.2])
    predicted = np.array([0.0, 0.0, 0.6, 0.1])
    observed = np.array([0.0, 0.0, 0.2, 0.3])
    m = push_metrics(tv, predicted, observed, np.array([0, 0, 0, 1]))
    assert m["tv_all"] == pytest.approx(0.15)
    assert m["tv_informative"] == pytest.approx(0.3)  # the two pushes where someone says "topples"
    assert m["informative"] == pytest.approx(0.5)
    assert np.isnan(m["ap"])  # no push toppled in more than half its repeats


def _object_level_data(n_objects, pushes, rng):
    objects = np.repeat(np.arange(n_objects), pushes)
    level = rng.uniform(0.1, 0.5, n_objects)[objects]
    tv = np.clip(level + rng.normal(0, 0.05, len(objects)), 0, 1)
    observed = rng.uniform(0, 1, len(objects))
    predicted = np.clip(observed + rng.normal(0, 0.2, len(objects)), 0, 1)
    return tv, predicted, observed, objects


def test_bootstrap_interval_contains_the_estimate_and_shrinks_with_more_objects():
    rng = np.random.default_rng(0)
    widths = []
    for n_objects in (8, 80):
        tv, predicted, observed, objects = _object_level_data(n_objects, 20, rng)
        point = push_metrics(tv, predicted, observed, objects)
        ci = bootstrap_intervals(tv, predicted, observed, objects, n_resamples=200, seed=1)
        for key in ("tv_all", "tv_informative", "ap", "ece"):
            assert ci[key][0] <= point[key] <= ci[key][1], (n_objects, key, ci[key], point[key])
        widths.append(ci["tv_all"][1] - ci["tv_all"][0])
    assert widths[1] < 0.6 * widths[0]
    # Seeded: the same seed gives the same interval.
    again = bootstrap_intervals(tv, predicted, observed, objects, n_resamples=200, seed=1)
    assert again == ci


def test_by_direction_groups_pushes_by_their_vertical_component_and_predicted_band():
    from types import SimpleNamespace

    directions = [(0, 0, -1), (0.6, 0, -0.8), (1, 0, 0), (1, 0, 0), (0.8, 0, 0.6), (0, 0.6, -0.8)]
    log = SimpleNamespace(pushes=[SimpleNamespace(direction=np.array(d, dtype=float)) for d in directions])
    scorer = SimpleNamespace(log=log, empirical_topple=np.array([0.5, 0.9, 0.1, 0.3, 1.0, 0.0]))
    scores = Scores(np.zeros(6), np.array([0.1, 0.2, 0.0, 0.0, 1.0, 0.5]), np.zeros(6))
    cells = {(c["direction"], c["band"]): (c["pushes"], c["predicted_topple"], c["observed_topple"])
             for c in by_direction(scores, scorer, log_direction_classes(scorer))}
    assert cells == {
        ("from above", "0 < P < 0.25"): (2, pytest.approx(0.15), pytest.approx(0.7)),  # u_z -1 and -0.8
        ("from above", "0.25 <= P < 0.75"): (1, 0.5, 0.0),
        ("side", "P = 0"): (2, 0.0, pytest.approx(0.2)),
        ("from below", "P >= 0.75"): (1, 1.0, 1.0),  # P = 1 and u_z 0.6 fall in the top cells
    }


def test_ranking_by_direction_scores_each_class_on_its_own_pushes():
    from types import SimpleNamespace

    # From above: the predictor ranks them backwards (the toppler lowest); from the side, right.
    directions = [(0, 0, -1), (0, 0.6, -0.8), (0.6, 0, -0.8), (1, 0, 0), (1, 0, 0), (1, 0, 0)]
    log = SimpleNamespace(pushes=[SimpleNamespace(direction=np.array(d, dtype=float)) for d in directions])
    scorer = SimpleNamespace(log=log, empirical_topple=np.array([0.9, 0.1, 0.2, 0.8, 0.0, 0.6]))
    scores = Scores(np.zeros(6), np.array([0.1, 0.7, 0.5, 0.9, 0.1, 0.6]), np.zeros(6))
    rows = {r["direction"]: r for r in ranking_by_direction(scores, scorer, log_direction_classes(scorer))}
    assert list(rows) == ["from above", "side"]
    assert rows["from above"]["pushes"] == 3 and rows["from above"]["ap"] == pytest.approx(1 / 3)
    assert rows["from above"]["predicted_topple"] == pytest.approx(1.3 / 3)
    assert rows["from above"]["observed_topple"] == pytest.approx(0.4)
    assert rows["side"]["ap"] == 1.0  # both topplers (0.8, 0.6) ranked above the push that stays


def test_paired_bootstrap_of_a_difference():
    from pipeline.studies.scoring import Scores

    rng = np.random.default_rng(2)
    tv, predicted, observed, objects = _object_level_data(30, 10, rng)
    same = bootstrap_difference(Scores(tv, predicted, tv), Scores(tv, predicted, tv), observed, objects, n_resamples=100)
    assert same["tv_all"] == {"difference": 0.0, "ci": [0.0, 0.0]}
    better = bootstrap_difference(Scores(tv * 0.8, predicted, tv), Scores(tv, predicted, tv), observed, objects, n_resamples=100)
    assert better["tv_all"]["difference"] == pytest.approx(-0.2 * tv.mean())
    assert better["tv_all"]["ci"][1] < 0 and better["tv_informative"]["ci"][1] < 0


def test_a_difference_the_log_cannot_define_is_shown_as_a_dash():
    """AP of a log without a topple is undefined: the report's difference line shows "-", not "+nan"."""
    from pipeline.studies.validation import _difference

    assert _difference({"difference": math.nan, "ci": [math.nan, math.nan]}) == "-"
    assert _difference({"difference": None, "ci": None}) == "-"  # as JSON reads NaN back
    assert _difference({"difference": 0.0123, "ci": [math.nan, math.nan]}) == "+0.012"
    assert _difference({"difference": -0.0123, "ci": [-0.02, -0.004]}) == "-0.012 [-0.020, -0.004]"


# ---------------------------------------------------------------- hand-made logs


@pytest.fixture(scope="module")
def box_file(tmp_path_factory):
    mesh = trimesh.creation.box(BOX)
    mesh.apply_translation([0, 0, BOX[2] / 2])
    path = tmp_path_factory.mktemp("meshes") / "box.stl"
    mesh.export(path)
    return path


def _rows(box_file, pushes):
    """A push log from (push_id, start transform, point, direction, [final transforms]) tuples."""
    columns = {name: [] for name in PUSHLOG.names}
    digest = file_sha256(box_file)
    for push_id, start, point, direction, finals in pushes:
        for repeat, final in enumerate(finals):
            row = {
                "object_id": "box", "mesh_sha256": digest, "mesh_source": "file", "mesh_path": str(box_file),
                "scale": 1.0, "mass": 0.25, "push_id": push_id, "repeat": repeat, "start_pose": None,
                "start_transform": np.asarray(start, float).ravel().tolist(),
                "point_x": point[0], "point_y": point[1], "point_z": point[2],
                "direction_x": direction[0], "direction_y": direction[1], "direction_z": direction[2],
                "action": None, "finger_speed": 0.05, "approach_offset": 0.015, "push_depth": 0.04,
                "finger_radius": 0.004, "final_transform": np.asarray(final, float).ravel().tolist(),
                "mu_table": None, "mu_finger": None, "source": "test", "seed": None,
            }
            for name, value in row.items():
                columns[name].append(value)
    return pa.Table.from_pydict(columns, schema=PUSHLOG)


def _replace(table, name, values):
    index = table.schema.get_field_index(name)
    return table.set_column(index, PUSHLOG.field(name), pa.array(values, PUSHLOG.field(name).type))


@pytest.fixture(scope="module")
def box_poses(box_file):
    """(pose set, standing pose, pose a topple over the standing pose's -x edge reaches, mesh file).

    Found from the geometry, not from a down vector: a symmetric box may list either end as "standing".
    """
    from pipeline.model.mesh import load_mesh
    from pipeline.model.poses import face_below, stable_poses

    obj = load_mesh(box_file, mass=0.25)
    poses = stable_poses(obj)
    standing = int(poses.face_pose[face_below(obj.hull, obj.center_mass, np.array([[0.0, 0.0, -1.0]]))[0]])
    pose = poses.poses[standing]
    minus_x = int(np.argmin(pose.base_edges[:, :, 0].mean(axis=1)))
    return poses, standing, int(pose.edge_final_pose[minus_x]), box_file


def _object_frame(pose, point, direction):
    """A push given in a pose's frame, in the object frame (what a log holds)."""
    to_object = np.linalg.inv(pose.transform)
    return (to_object[:3, :3] @ point + to_object[:3, 3]).tolist(), (to_object[:3, :3] @ direction).tolist()


HIGH_PUSH = (np.array([BOX[0] / 2, 0.0, 0.13]), np.array([-1.0, 0.0, 0.0]))
"""Pose frame of the standing box: the +x face 13 cm up, pushed towards -x (topples over the -x edge)."""


def test_high_push_known_outcomes_give_known_tv(box_file, box_poses, tmp_path):
    """A push the noise-free model says topples onto -x, observed toppling in 1 of 4 repeats: TV 0.75."""
    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    start = planar(0.3, 0.1, -0.05) @ stand
    finals = [planar(1.0, 0.2, 0.0) @ lie] + [planar(0.1 * k, 0.0, 0.0) @ stand for k in range(3)]
    point, direction = _object_frame(poses.poses[standing], *HIGH_PUSH)
    log_table = _rows(box_file, [(0, start, point, direction, finals)])
    pq.write_table(log_table, tmp_path / "log.parquet")
    log = read_log([tmp_path], Config())
    assert log.rejected == {} and len(log.pushes) == 1
    push = log.pushes[0]
    assert push.pose == standing and sorted(push.outcomes.tolist()) == sorted([lying, standing, standing, standing])
    assert push.topple_rate == pytest.approx(0.25)
    scores = Scorer(log).score_variant(THESIS.topple, "baseline")  # the thesis's friction: the push is inside mu_f's cone
    assert scores.p_topple[0] == 1.0 and scores.tv[0] == pytest.approx(0.75)
    never = Scorer(log).never_topples()
    assert never.p_topple[0] == 0.0 and never.tv[0] == pytest.approx(0.25)


def test_a_logged_push_is_predicted_along_its_own_direction(box_file, box_poses, tmp_path):
    """The scorer's actions keep each logged direction (pose frame), not the surface's inward normal,
    and its per-push arrays follow the log: object index, repeats, observed topple rate, empirical
    next-pose distribution (the outside bucket last)."""
    from pipeline.model.config import ContactConfig

    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    downward = np.array([-0.8, 0.0, -0.6])  # into the +x face and down, not along its normal
    pushes = [(0, stand, *_object_frame(poses.poses[standing], HIGH_PUSH[0], downward), [lie, stand, stand]),
              (1, stand, *_object_frame(poses.poses[standing], *HIGH_PUSH), [lie, lie])]
    pq.write_table(_rows(box_file, pushes), tmp_path / "log.parquet")
    log = read_log([tmp_path], Config())
    contacts = ContactConfig(n_contacts=17)
    scorer = Scorer(log, 3, contacts)
    assert scorer.seed == 3 and scorer.contacts == contacts and Scorer(log).contacts == ContactConfig()
    (group,) = scorer.groups
    np.testing.assert_allclose(group.actions.directions, [downward, HIGH_PUSH[1]], atol=1e-9)
    np.testing.assert_allclose(group.actions.normals[0], [1.0, 0.0, 0.0], atol=1e-9)
    assert scorer.object_ids == ["box"] and scorer.object_index.tolist() == [0, 0] and scorer.repeats.tolist() == [3, 2]
    np.testing.assert_allclose(scorer.empirical_topple, [1 / 3, 1.0])
    expected = np.zeros((2, len(poses.poses) + 1))
    expected[0, [lying, standing]] = [1 / 3, 2 / 3]
    expected[1, lying] = 1.0
    np.testing.assert_allclose(group.empirical, expected)


def test_bad_rows_are_counted_by_reason_never_dropped_silently(box_file, box_poses, tmp_path):
    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    tilted = trimesh.transformations.rotation_matrix(np.radians(40), [1, 0, 0]) @ stand
    nan = stand.copy()
    nan[0, 0] = np.nan
    stretched = stand.copy()
    stretched[:3, :3] *= 2.0
    point, direction = _object_frame(poses.poses[standing], *HIGH_PUSH)
    good = _rows(box_file, [(0, stand, point, direction, [lie, stand])])
    bad = _rows(box_file, [
        (1, tilted, point, direction, [lie]),
        (2, nan, point, direction, [lie]),
        (3, stand, point, direction, [stretched]),
        (4, stand, point, [0.0, 0.0, 0.0], [lie]),
    ])
    unknown = _rows(box_file, [(5, stand, point, direction, [lie])])
    unknown = _replace(_replace(unknown, "mesh_path", ["/nonexistent/box.stl"]), "object_id", ["ghost"])
    changed = _rows(box_file, [(6, stand, point, direction, [lie])])
    changed = _replace(_replace(changed, "mesh_sha256", ["0" * 64]), "object_id", ["box2"])
    duplicate = _rows(box_file, [(0, stand, point, direction, [lie])])  # push 0, repeat 0 again
    disagree = _rows(box_file, [(7, stand, point, direction, [lie])])
    disagree = _replace(disagree, "start_pose", [lying])
    table = pa.concat_tables([good, bad, unknown, changed, duplicate, disagree])
    pq.write_table(table, tmp_path / "bad.parquet")

    log = read_log([tmp_path / "bad.parquet"], Config())
    assert log.rows == table.num_rows
    assert log.rows_used == 2 and len(log.pushes) == 1
    assert sum(log.rejected.values()) == table.num_rows - 2
    reasons = log.rejected
    assert reasons["start pose matches no stable pose (tilted beyond poses.same_pose_angle)"] == 1
    assert reasons["start_transform has NaN or infinite entries"] == 1
    assert any("final_transform is not a rigid transform" in r for r in reasons)
    assert reasons["direction is zero"] == 1
    assert reasons["unknown object: mesh file not found"] == 1
    assert reasons["mesh changed: file sha256 differs from mesh_sha256"] == 1
    assert reasons["duplicate (push_id, repeat)"] == 1
    assert reasons["start_pose column disagrees with the pose start_transform matches"] == 1
    assert all(len(v) >= 1 for v in log.examples.values())
    assert log.counts()["rows_rejected"] == table.num_rows - 2


def test_the_start_pose_column_is_read_in_the_numbering_of_the_world_the_log_records(tmp_path):
    """A square prism has 6 stable poses unmerged (the thesis's world, where logs are played) and 2 merged (the
    default). A part file of ``toppledb play`` records its world's pose parameters, and its start_pose column is
    held against that numbering only: the right index is used, an index right only in the reader's numbering,
    or -1, is rejected. A log that records nothing (a robot's) is read in the reader's numbering."""
    import json

    from pipeline.model.mesh import load_mesh
    from pipeline.model.poses import stable_poses
    from pipeline.studies.logreader import PLAY_METADATA_KEY

    mesh = trimesh.creation.box((0.06, 0.06, 0.15))
    mesh.apply_translation([0, 0, 0.075])
    path = tmp_path / "prism.stl"
    mesh.export(path)
    thesis_world = Config().with_overrides({"poses.merge_symmetric": False})
    obj = load_mesh(path, mass=0.25)
    unmerged, merged = stable_poses(obj, thesis_world.poses), stable_poses(obj, Config().poses)
    assert len(unmerged.poses) == 6 and len(merged.poses) == 2
    lying = max(i for i, pose in enumerate(unmerged.poses) if abs(pose.down[2]) < 0.5)  # on a long side
    standing = max(i for i, pose in enumerate(unmerged.poses) if abs(pose.down[2]) > 0.5)
    merged_standing = next(i for i, pose in enumerate(merged.poses) if abs(pose.down[2]) > 0.5)
    assert lying >= len(merged.poses) and standing != merged_standing
    recorded = {PLAY_METADATA_KEY: json.dumps({"key": {"config": thesis_world.to_dict()}}).encode()}

    def log(start, column, metadata=recorded):
        table = _rows(path, [(0, start, [0.03, 0.0, 0.02], [-1.0, 0.0, 0.0], [start, start])])
        table = _replace(table, "start_pose", [column, column]).replace_schema_metadata(metadata)
        pq.write_table(table, tmp_path / "log.parquet")
        return read_log([tmp_path / "log.parquet"], Config())

    read = log(unmerged.poses[lying].transform, lying)
    assert read.rejected == {} and read.rows_used == 2
    assert abs(merged.poses[read.pushes[0].pose].down[2]) < 0.5, "scored in the reader's numbering"
    disagrees = {"start_pose column disagrees with the pose start_transform matches": 2}
    assert log(unmerged.poses[standing].transform, merged_standing).rejected == disagrees, "right only in the reader's"
    assert log(unmerged.poses[lying].transform, -1).rejected == disagrees
    assert log(unmerged.poses[lying].transform, lying, metadata=None).rejected == disagrees, "a robot's log: the reader's"
    assert log(unmerged.poses[standing].transform, merged_standing, metadata=None).rejected == {}


def test_two_logs_that_use_the_same_push_id_keep_each_push_and_its_repeats(box_file, box_poses, tmp_path):
    """Push ids are unique within one log: two logs that both hold push 0 of the box hold two pushes
    (here one high that topples and one low that does not), every repeat kept, none rejected; the
    same file named twice is refused rather than counted twice."""
    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    high = _object_frame(poses.poses[standing], *HIGH_PUSH)
    low = _object_frame(poses.poses[standing], np.array([BOX[0] / 2, 0.0, 0.01]), HIGH_PUSH[1])
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    pq.write_table(_rows(box_file, [(0, stand, *high, [lie, lie, stand])]), tmp_path / "a" / "box.parquet")
    pq.write_table(_rows(box_file, [(0, stand, *low, [stand, stand])]), tmp_path / "b" / "box.parquet")

    log = read_log([tmp_path / "a", tmp_path / "b"], Config())
    assert not log.rejected and log.rows_used == 5
    assert [(p.log, p.push_id, len(p.outcomes)) for p in log.pushes] == [(0, 0, 3), (1, 0, 2)]
    assert [p.topple_rate for p in log.pushes] == pytest.approx([2 / 3, 0.0])
    with pytest.raises(LogError, match="named twice"):
        read_log([tmp_path / "a", tmp_path / "a" / "box.parquet"], Config())
    # A log that is part of another (the same rows in a second file) adds nothing and says so.
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "box.parquet").write_bytes((tmp_path / "a" / "box.parquet").read_bytes())
    both = read_log([tmp_path / "a", tmp_path / "c"], Config())
    assert [(p.log, len(p.outcomes)) for p in both.pushes] == [(0, 3)]
    assert both.rejected == {"the same row (push, repeat, start, point, direction, final) as in an earlier log": 3}
    # A directory of several logs (as data/logs is) is read as those logs, in name order, not as one.
    parent = read_log([tmp_path], Config())
    assert [(p.log, p.push_id, len(p.outcomes)) for p in parent.pushes] == [(0, 0, 3), (1, 0, 2)]
    assert parent.rejected == both.rejected and parent.rows_used == 5
    assert parent.logs == [str(tmp_path / name) for name in ("a", "b", "c")]


def test_which_files_make_one_log(tmp_path):
    """A file is a log, and so is a directory with files of its own, with every file under it (a log
    kept by session); a directory with none of its own is its subdirectories' logs, in name order,
    hidden and writer's ("_") directories and files left out."""
    def touch(*parts):
        path = tmp_path.joinpath(*parts)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
        return path

    one = touch("single.parquet")
    assert logs_under(one) == [(one, [one])]
    # A log with its own files and a session subdirectory is one log, its repeats kept together.
    own, session = touch("mylog", "a.parquet"), touch("mylog", "day2", "b.parquet")
    touch("mylog", "_play.json")
    assert logs_under(tmp_path / "mylog") == [(tmp_path / "mylog", [own, session])]
    # A directory of logs: one log per subdirectory, each with every file under it.
    b, c = touch("logs", "b", "x.parquet"), touch("logs", "b", "day1", "y.parquet")
    a = touch("logs", "a", "z.parquet")
    touch("logs", ".old_a", "z.parquet")
    touch("logs", "_tmp", "w.parquet")
    touch("logs", "b", "_part.parquet")
    touch("logs", "b", ".temp.parquet")
    (tmp_path / "logs" / "empty").mkdir()
    assert logs_under(tmp_path / "logs") == [(tmp_path / "logs" / "a", [a]), (tmp_path / "logs" / "b", [c, b])]
    (tmp_path / "none" / "sub").mkdir(parents=True)
    with pytest.raises(LogError, match="no .parquet files"):
        logs_under(tmp_path / "none")


def test_a_replay_of_two_logs_is_matched_log_by_log(box_file, box_poses, tmp_path):
    """The same push id in two logs is two pushes; their replay must name the logs in the same order."""
    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    high = _object_frame(poses.poses[standing], *HIGH_PUSH)
    low = _object_frame(poses.poses[standing], np.array([BOX[0] / 2, 0.0, 0.01]), HIGH_PUSH[1])
    for name, push, finals in (("a", high, [lie, lie]), ("b", low, [stand, stand]), ("ra", high, [lie, stand]),
                               ("rb", low, [stand, stand])):
        (tmp_path / name).mkdir()
        pq.write_table(_rows(box_file, [(0, stand, *push, finals)]), tmp_path / name / "box.parquet")
    scorer = Scorer(read_log([tmp_path / "a", tmp_path / "b"], Config()))
    replayed = scorer.replay(read_log([tmp_path / "ra", tmp_path / "rb"], Config()))
    assert replayed.p_topple == pytest.approx([0.5, 0.0]), "each push predicted by its own replay"
    with pytest.raises(LogError, match="is another push in the replay"):
        scorer.replay(read_log([tmp_path / "rb", tmp_path / "ra"], Config()))
    with pytest.raises(LogError, match=re.escape(f"log {tmp_path / 'b'})")):  # a replay of the first log only names the other
        scorer.replay(read_log([tmp_path / "ra"], Config()))


def test_rows_pushed_with_another_stroke_are_rejected_when_the_model_reads_the_stroke(box_file, box_poses, tmp_path):
    """With the ``stroke`` correction (MODEL.md C.10) the model predicts a push of its own depth:
    a row pushed 6 cm deep is another push, counted with its reason; without it the row is read."""
    poses, standing, lying, _ = box_poses
    stand, lie = poses.poses[standing].transform, poses.poses[lying].transform
    point, direction = _object_frame(poses.poses[standing], *HIGH_PUSH)
    rows = _rows(box_file, [(0, stand, point, direction, [lie]), (1, stand, point, direction, [stand])])
    rows = _replace(rows, "push_depth", [0.04, 0.06])
    pq.write_table(rows, tmp_path / "log.parquet")
    with_stroke = read_log([tmp_path], Config().with_overrides({"topple.corrections": "finger_friction,stroke"}))
    assert len(with_stroke.pushes) == 1 and with_stroke.pushes[0].push_id == 0
    assert with_stroke.rejected == {"push_depth 0.06 m is not the model's stroke (topple.stroke 0.04 m); "
                                    "score it with a configuration of that stroke": 1}
    assert read_log([tmp_path], Config()).rejected == {}


def test_vectorised_pose_matching_agrees_with_match_pose_and_settle(box_poses):
    from scipy.spatial.transform import Rotation

    from pipeline.model.mesh import load_mesh
    from pipeline.model.poses import face_below, settle
    from pipeline.studies.logreader import match_downs, object_downs
    from schema.frames import match_pose

    poses = box_poses[0]
    obj = load_mesh(box_poses[3], mass=0.25)
    transforms = np.tile(np.eye(4), (200, 1, 1))
    transforms[:100, :3, :3] = Rotation.random(100, random_state=0).as_matrix()
    # Half near a stable pose (within a few degrees), so that both branches of the tolerance occur.
    near = Rotation.from_rotvec(np.random.default_rng(1).normal(0, 0.1, (100, 3))).as_matrix()
    transforms[100:] = [p.transform for p in poses.poses for _ in range(100 // len(poses.poses) + 1)][:100]
    transforms[100:, :3, :3] = near @ transforms[100:, :3, :3]
    tolerance = Config().poses.same_pose_angle
    matched, _ = match_downs(object_downs(transforms), poses.downs, tolerance)
    expected = [match_pose(t, poses.downs, poses.transforms, tolerance).pose for t in transforms]
    assert matched.tolist() == expected and (matched >= 0).sum() > 50 and (matched < 0).sum() > 20
    faces = face_below(obj.hull, obj.center_mass, object_downs(transforms))
    assert poses.face_pose[faces].tolist() == [settle(poses, obj, t[:3, :3]) for t in transforms]


def test_unreadable_logs_are_one_line_errors(tmp_path, capsys):
    (tmp_path / "junk.parquet").write_text("not parquet")
    with pytest.raises(LogError, match="not a readable Parquet file"):
        read_log([tmp_path / "junk.parquet"])
    pq.write_table(pa.table({"x": [1]}), tmp_path / "other.parquet")
    with pytest.raises(LogError, match="missing column"):
        read_log([tmp_path / "other.parquet"])
    assert main([str(tmp_path / "missing.parquet"), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: push log not found") and "\n" not in err


def test_a_log_with_nulls_where_every_row_needs_a_value_is_a_one_line_error(box_file, tmp_path, capsys):
    """A log another tool wrote: a null object id, or a missing transform in a column of plain lists (as pandas
    and polars write 16-number lists), is the file's one-line refusal, not a traceback."""
    table = _rows(box_file, [(0, np.eye(4), [0.0, 0.0, 0.1], [1.0, 0.0, 0.0], [np.eye(4)] * 2)])
    ids = table.schema.get_field_index("object_id")
    no_id = table.set_column(ids, pa.field("object_id", pa.string()), pa.array([None] * table.num_rows, pa.string()))
    pq.write_table(no_id, tmp_path / "no_id.parquet")
    with pytest.raises(LogError, match=r"no_id.parquet: null values in column\(s\) a push log requires in every row: object_id \(2\)"):
        read_log([tmp_path / "no_id.parquet"])
    plain = pa.list_(pa.float64())
    finals = table.column("final_transform").to_pylist()
    no_final = table.set_column(table.schema.get_field_index("final_transform"), pa.field("final_transform", plain),
                                pa.array([finals[0], None], plain))
    pq.write_table(no_final, tmp_path / "no_final.parquet")
    assert main([str(tmp_path / "no_final.parquet"), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no_final.parquet: null values in column(s)" in err and "final_transform (1)" in err and "\n" not in err
    short = pa.list_(pa.float64(), 15)  # a fixed size the push log does not have: arrow's type error, one line too
    pq.write_table(table.set_column(table.schema.get_field_index("final_transform"), pa.field("final_transform", short),
                                    pa.array([f[:15] for f in finals], short)), tmp_path / "short.parquet")
    with pytest.raises(LogError, match="short.parquet: columns do not have the push-log types"):
        read_log([tmp_path / "short.parquet"])


# ---------------------------------------------------------------- the report end to end


@pytest.fixture(scope="module")
def model_logs(tmp_path_factory):
    """Two small logs made by the model on boxes: a 'calibration' one and a 'reported' one."""
    from pipeline.studies.synthetic_log import MeshSpec, model_log

    root = tmp_path_factory.mktemp("logs")
    specs = []
    for i, size in enumerate([(0.05, 0.08, 0.15), (0.06, 0.06, 0.12), (0.04, 0.1, 0.2)]):
        mesh = trimesh.creation.box(size)
        mesh.export(root / f"box{i}.stl")
        specs.append(MeshSpec(f"box{i}", str(root / f"box{i}.stl"), 1.0, 0.25))
    low_friction = Config().with_overrides({"topple.mu_table_mean": 0.25})
    pq.write_table(model_log(specs[:2], low_friction, pushes_per_pose=6, repeats=5, seed=1), root / "calibration.parquet")
    pq.write_table(model_log(specs, Config(), pushes_per_pose=6, repeats=5, seed=2), root / "reported.parquet")
    return root


def test_report_writes_json_with_variants_references_and_counts(model_logs, tmp_path):
    out, png = tmp_path / "validation.json", tmp_path / "validation.png"
    code = main([str(model_logs / "reported.parquet"), "--rate-from", str(model_logs / "calibration.parquet"),
                 "--corpus", "", "--bootstrap", "50", "--out", str(out), "--plot", str(png)])
    assert code == 0 and png.stat().st_size > 0
    result = json.loads(out.read_text())
    assert set(result["variants"]) == set(VARIANTS)
    assert set(result["references"]) == {"never_topples", "constant_rate", "spread_1pct"}
    spread = result["references"]["spread_1pct"]
    assert spread["of"] == result["main_variant"] and spread["share"] == SPREAD_SHARE
    # Moving 1 % of every push to a topple makes more pushes informative, never fewer.
    assert spread["informative"] >= result["variants"][result["main_variant"]]["informative"]
    calibration_rate = np.mean([p.topple_rate for p in read_log([model_logs / "calibration.parquet"]).pushes])
    reported_rate = np.mean([p.topple_rate for p in read_log([model_logs / "reported.parquet"]).pushes])
    # The constant-rate reference uses the calibration data's rate, not the reported log's.
    assert result["references"]["constant_rate"]["rate"] == pytest.approx(calibration_rate)
    assert abs(calibration_rate - reported_rate) > 1e-6
    assert result["counts"]["objects"] == 3 and result["counts"]["rows_rejected"] == 0
    assert len(result["objects"]) == 3 and 1 <= len(result["worst_objects"]) <= 3
    for m in result["variants"].values():
        assert m["ci"]["tv_informative"][0] <= m["tv_informative"] <= m["ci"]["tv_informative"][1]
        assert sum(b["count"] for b in m["reliability"]) == result["counts"]["pushes"]
    # A log made by the robust model is predicted better by it than by "never topples".
    assert result["variants"]["robust"]["tv_informative"] < result["references"]["never_topples"]["tv_informative"]


def test_brier_score_is_the_squared_distance_and_least_for_the_true_distribution():
    empirical = np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 1.0]])
    assert brier_score(np.array([[1.0, 0.0, 0.0]]), empirical).tolist() == [0.5, 2.0]
    # Proper: for outcomes drawn from q, the expected score of p is |p - q|^2 + the
    # outcomes' own spread, so no p beats q; sup-TV's expectation, by contrast, is least
    # at the sharp prediction of the likelier outcome.
    q = np.array([0.7, 0.3])
    outcomes = np.eye(2)  # each outcome as a one-hot empirical distribution
    def expected(score, p):
        return q @ score(np.array([p]), outcomes)
    assert expected(brier_score, q) < min(expected(brier_score, p) for p in ([1.0, 0.0], [0.6, 0.4], [0.8, 0.2]))
    assert expected(sup_tv, [1.0, 0.0]) < expected(sup_tv, q)


def test_scores_carry_the_brier_score_of_every_push(model_logs):
    log = read_log([model_logs / "reported.parquet"])
    scorer = Scorer(log)
    for scores in (scorer.score(replace(Config().topple, n_trials=10)), scorer.constant_rate(0.3), scorer.never_topples()):
        assert scores.brier.shape == scores.tv.shape
        assert np.all(scores.brier >= scores.tv ** 2 - 1e-12)  # the largest bucket's square is part of the sum
        assert np.all(scores.brier <= 2.0 + 1e-12)
    never = scorer.never_topples()
    for group in scorer.groups:  # all mass on the start pose: 1 - 2 e_start + sum e^2
        e = group.empirical
        np.testing.assert_allclose(never.brier[group.rows], 1.0 - 2.0 * e[:, group.pose.index] + (e ** 2).sum(axis=1))


def test_spread_share_mixes_the_models_distribution_with_the_geometric_topple(model_logs):
    """score(spread_share=s) is (1 - s) model + s ``topple_spread``: P(topple) and TV follow."""
    log = read_log([model_logs / "reported.parquet"])
    scorer = Scorer(log)
    topple = replace(Config().topple, n_trials=10)
    model, mixed = scorer.score(topple), scorer.score(topple, spread_share=0.2)
    np.testing.assert_array_equal(scorer.score(topple, spread_share=0.0).tv, model.tv)
    for group in scorer.groups:
        spread = topple_spread(group)
        assert spread.sum() == pytest.approx(1.0) and spread[-1] == 0.0
        expected = 0.8 * model.p_topple[group.rows] + 0.2 * (1.0 - spread[group.pose.index])
        np.testing.assert_allclose(mixed.p_topple[group.rows], expected, rtol=0, atol=1e-12)
        # The rate-r constant predictor is the same spread mixed into "it stays".
        constant = scorer.constant_rate(0.3).p_topple[group.rows]
        np.testing.assert_allclose(constant, 0.3 * (1.0 - spread[group.pose.index]), atol=1e-12)


def test_report_outcomes_outside_the_pose_set_are_their_own_bucket(model_logs):
    log = read_log([model_logs / "reported.parquet"])
    push = log.pushes[0]
    push.outcomes = np.array([OUTSIDE] * len(push.outcomes))
    n_poses = len(log.objects[push.object_id].poses.poses)
    assert push.empirical(n_poses)[-1] == 1.0 and push.topple_rate == 1.0
    result = report(log, Config(), ("baseline",), n_resamples=0)
    assert result["variants"]["baseline"]["tv_all"] > 0


def test_an_empty_log_file_reads_as_no_rows(tmp_path):
    """A player that loaded no pushes for an object writes a 0-row part; readers take it as nothing."""
    from pipeline.studies.logreader import read_tables

    zero = {pa.string(): "", pa.float64(): 0.0, pa.int64(): 0, pa.int32(): 0}
    one_row = {f.name: None if f.nullable else zero.get(f.type) for f in PUSHLOG}
    one_row.update(object_id="a", start_transform=np.eye(4).ravel().tolist(), final_transform=np.eye(4).ravel().tolist())
    pq.write_table(PUSHLOG.empty_table(), tmp_path / "a.parquet")
    pq.write_table(pa.Table.from_pylist([one_row], schema=PUSHLOG), tmp_path / "b.parquet")
    table = read_tables([tmp_path / "a.parquet", tmp_path / "b.parquet"])
    assert table.num_rows == 1 and table.column("_file").to_pylist() == [str(tmp_path / "b.parquet")]


# ---------------------------------------------------------------- physics predicting itself


def test_brier_floor_is_an_unbiased_estimate_of_the_true_distributions_expected_score():
    """Over every way R repeats can fall, the floor's expectation is sum p (1 - p) / R, which is
    also the expected Brier score of the true distribution itself."""
    from itertools import product
    from math import comb

    p, repeats = np.array([0.6, 0.3, 0.1]), 4
    expected_floor = expected_true_score = 0.0
    for counts in product(range(repeats + 1), repeat=3):
        if sum(counts) != repeats:
            continue
        weight = comb(repeats, counts[0]) * comb(repeats - counts[0], counts[1]) * np.prod(p ** np.array(counts))
        e = np.array([counts]) / repeats
        expected_floor += weight * brier_floor(e, np.array([repeats]))[0]
        expected_true_score += weight * brier_score(p[None], e)[0]
    assert expected_floor == pytest.approx((p * (1 - p)).sum() / repeats)
    assert expected_true_score == pytest.approx(expected_floor)
    assert np.isnan(brier_floor(np.array([[1.0, 0.0]]), np.array([1])))[0]


def test_a_log_replayed_by_itself_scores_perfectly_and_a_mismatched_replay_is_refused(model_logs, tmp_path):
    log = read_log([model_logs / "reported.parquet"])
    scorer = Scorer(log)
    itself = scorer.replay(log)
    assert np.all(itself.tv == 0.0) and np.all(itself.brier == 0.0)
    np.testing.assert_allclose(itself.p_topple, scorer.empirical_topple, rtol=0, atol=1e-12)
    floor = scorer.brier_floor()
    assert floor.shape == (len(log.pushes),) and np.all(floor >= 0.0)
    assert floor.max() > 0  # some pushes topple in some repeats only

    table = pq.read_table(model_logs / "reported.parquet")
    first = table.column("push_id")[0].as_py()
    keep = pa.compute.not_equal(table.column("push_id"), first)
    pq.write_table(table.filter(keep), tmp_path / "short.parquet")
    with pytest.raises(LogError, match="no usable rows for 1 of.*replay the same objects and pushes, one replay per log in the logs' order$"):
        scorer.replay(read_log([tmp_path / "short.parquet"]))
    moved = table.column("point_z").to_numpy() + np.where(table.column("push_id").to_numpy() == first, 0.01, 0.0)
    pq.write_table(_replace(table, "point_z", moved), tmp_path / "moved.parquet")
    with pytest.raises(LogError, match=r"is another push in the replay \(start pose, point or direction differ\); "
                                       "replay with the log's own seed and parameters$"):
        scorer.replay(read_log([tmp_path / "moved.parquet"]))
    # The same push is within SAME_PUSH_TOLERANCE (1e-6) in every component, as the log's own
    # repeats are, however large the component (no tolerance relative to it).
    push = log.pushes[0]
    turned = push.direction.copy()
    turned[np.argmax(np.abs(turned))] += 5e-6
    with pytest.raises(LogError, match="is another push in the replay"):
        scorer.replay(PushLog(log.objects, [replace(push, direction=turned), *log.pushes[1:]]))
    # Within 1e-6 (not 1e-8) it is the same push: a point or direction off by 5e-7 in every component.
    near = replace(push, point=push.point + 5e-7, direction=push.direction - 5e-7)
    np.testing.assert_array_equal(scorer.replay(PushLog(log.objects, [near, *log.pushes[1:]])).brier, itself.brier)
    # Past 1e-6 it is another push, however large the component: the point's largest, off by 1.2e-6.
    big = int(np.argmax(np.abs(push.point)))
    assert abs(push.point[big]) > 0.03  # where a tolerance relative to it would allow 1.3e-6 or more
    moved_point = push.point.copy()
    moved_point[big] += 1.2e-6
    with pytest.raises(LogError, match="is another push in the replay"):
        scorer.replay(PushLog(log.objects, [replace(push, point=moved_point), *log.pushes[1:]]))


def test_report_scores_a_replay_as_the_physics_reference(model_logs, tmp_path, capsys):
    out = tmp_path / "validation.json"
    reported = str(model_logs / "reported.parquet")
    assert main([reported, "--replay", reported, "--variants", "baseline", "--corpus", "", "--bootstrap", "20",
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    physics = result["references"]["physics_replay"]
    assert physics["tv_all"] == 0.0 and physics["brier"] == 0.0 and physics["ap"] == 1.0
    assert physics["repeats_min"] == result["counts"]["repeats_min"]
    assert 0.0 < result["brier_floor"] < result["variants"]["baseline"]["brier"]
    assert "Brier floor" in capsys.readouterr().out
    calibration = str(model_logs / "calibration.parquet")  # other objects: refused with its reason, exit 2
    assert main([reported, "--replay", calibration, "--corpus", "", "--bootstrap", "0", "--out", str(out)]) == 2
    assert "no usable rows" in capsys.readouterr().err


def test_report_against_other_models_pairs_them_with_the_configured_one(model_logs, tmp_path, capsys):
    from pipeline.model.config import PRESETS

    reported = str(model_logs / "reported.parquet")
    same = tmp_path / "same.toml"  # the defaults' [topple], spelled out: the same model
    same.write_text('[topple]\nvariant = "corrected"\n')
    narrow = tmp_path / "narrow.toml"  # the defaults with another side-map band: recorded as its own
    narrow.write_text('[topple]\nvariant = "corrected"\nside_map_band = [0.2, 0.8]\n')
    out = tmp_path / "validation.json"
    assert main([reported, "--variants", "corrected", "--against", "thesis", str(same), str(narrow), "--corpus", "",
                 "--bootstrap", "30", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    ours, thesis, itself = result["variants"]["corrected"], result["against"]["thesis"], result["against"][str(same)]
    assert thesis["variant"] == "robust" and thesis["corrections"] == []
    # The thesis's model scored on the very same pushes, candidates and trial streams.
    log = read_log([reported])
    scores = Scorer(log, Config().seed, Config().contacts).score(Config.from_toml(PRESETS / "thesis.toml").topple)
    assert thesis["metrics"]["brier"] == pytest.approx(float(np.mean(scores.brier)), abs=1e-12)
    assert thesis["metrics"]["brier"] != ours["brier"]
    for key in ("brier", "tv_all", "ap", "ece"):
        assert thesis["difference"][key]["difference"] == pytest.approx(ours[key] - thesis["metrics"][key], abs=1e-12)
        low, high = thesis["difference"][key]["ci"]
        assert low <= thesis["difference"][key]["difference"] <= high
        # A model against itself differs by nothing, in every resample.
        assert itself["difference"][key] == {"difference": 0.0, "ci": [0.0, 0.0]}
    # What was compared is recorded, not only its file's name.
    thesis_topple = Config.from_toml(PRESETS / "thesis.toml").topple
    assert thesis["topple"] == {k: getattr(thesis_topple, k) for k in thesis["topple"]}
    assert thesis["recalibration"]["x"] == [] and len(itself["recalibration"]["x"]) == len(Config().topple.recalibration_x) > 0
    assert thesis["recalibration"]["down_map"] == [] and itself["recalibration"]["down_map"] == list(Config().topple.down_map)
    assert result["recalibration"]["down_map"] == list(Config().topple.down_map)
    assert thesis["recalibration"]["side_map"] == [] and itself["recalibration"]["side_map"] == list(Config().topple.side_map)
    assert result["recalibration"]["side_map"] == list(Config().topple.side_map) != []
    assert result["recalibration"]["side_map_band"] == itself["recalibration"]["side_map_band"] == list(Config().topple.side_map_band)
    assert result["against"][str(narrow)]["recalibration"]["side_map_band"] == [0.2, 0.8]
    assert itself["ranking_by_direction"] == result["ranking_by_direction"]
    printed = capsys.readouterr().out
    assert "corrected - thesis (robust; paired" in printed and "\nthesis " in printed
    assert "corrected - same (corrected; paired" in printed  # a file by its stem, as in the table
    assert printed.count("or above 0 in AP or mAP, favours corrected)") == 1  # which sign is better, said once
    assert main([reported, "--variants", "corrected", "--against", "thesis", "--corpus", "",
                 "--bootstrap", "0", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "corrected - thesis" in printed and "nan" not in printed


def test_report_against_accepts_a_model_of_the_same_stroke(model_logs, tmp_path, capsys):
    reported = str(model_logs / "reported.parquet")
    stroke = tmp_path / "stroke.toml"
    stroke.write_text('[topple]\nvariant = "corrected"\ncorrections = "finger_friction,stroke"\n')
    out = tmp_path / "validation.json"
    assert main([reported, "--config", str(stroke), "--variants", "corrected", "--against", str(stroke),
                 "--corpus", "", "--bootstrap", "0", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["model"] == str(stroke) and f"model (corrected): {stroke}\n" in capsys.readouterr().out, \
        "the report says which file its corrected rows are"
    assert result["against"][str(stroke)]["corrections"] == ["finger_friction", "stroke"]
    assert result["against"][str(stroke)]["difference"]["brier"]["difference"] == 0.0


def test_report_against_refuses_unknown_models_and_a_stroke_it_cannot_read(model_logs, tmp_path, capsys):
    reported = str(model_logs / "reported.parquet")
    out = tmp_path / "validation.json"
    assert main([reported, "--against", "no_such_model", "--corpus", "", "--out", str(out)]) == 2
    assert "config file not found: no_such_model" in capsys.readouterr().err
    stroke = tmp_path / "stroke.toml"
    stroke.write_text('[topple]\nvariant = "corrected"\ncorrections = "finger_friction,stroke"\n')
    assert main([reported, "--against", str(stroke), "--corpus", "", "--out", str(out)]) == 2
    assert "stroke correction reads the log's push depths" in capsys.readouterr().err
    assert not out.exists()
    # The compared models are resolved before any log is read.
    assert main([str(tmp_path / "missing.parquet"), "--against", "no_such_model", "--corpus", "", "--out", str(out)]) == 2
    assert "no_such_model" in capsys.readouterr().err
