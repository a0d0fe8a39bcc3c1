"""Smoothing the transition rows over a pose's candidate pushes (docs/MODEL.md C.12)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from shapes import candidate_pushes, random_object

from pipeline.model.config import Config, ContactConfig
from pipeline.model.outcomes import Actions
from pipeline.model.poses import stable_poses
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import Push, read_log
from pipeline.studies.scoring import Scorer, with_probes
from schema.neighbourhood import neighbour_mean
from schema.vocabulary import STATUS_FINGER_COLLISION, STATUS_OK
from tests.test_validation import model_logs  # noqa: F401 (fixture)

RADIUS, ANGLE = 0.02, 0.5


def _topple(radius: float, variant: str = "corrected", n_trials: int = 40):
    return replace(Config().topple.without_recalibration(), smoothing_radius=radius, smoothing_angle=ANGLE, variant=variant, n_trials=n_trials)


@pytest.fixture(scope="module")
def pose_and_candidates():
    obj = random_object(3)
    pose_set = stable_poses(obj)
    # Pose 2: 26 of its pushes topple under the default model (pose 0, on which these tests were
    # written, has none once tip_path stops its few stalling tips, MODEL.md C.14).
    pose = pose_set.poses[2]
    return obj, pose_set, pose, candidate_pushes(obj, pose, 80, 3)


def _evaluate(setup, topple, actions=None, candidates=None):
    obj, pose_set, pose, pool = setup
    return evaluate_pose(obj, pose, pose_set.probabilities, pool if actions is None else actions, topple,
                         stream(3, obj.name, pose.index, "trials"), candidates=candidates)


def test_a_row_past_the_pool_is_averaged_over_the_pool_and_itself_only():
    x = np.array([1.0, 0.0, 0.0])
    points = np.array([[0, 0, 0], [0.01, 0, 0], [0.005, 0, 0], [0.006, 0, 0]], dtype=float)
    directions = np.array([x, x, x, x])
    values = np.array([0.2, 0.4, 0.9, 0.0])
    mean, count = neighbour_mean(points, directions, values, pool=2)
    # The pool (0, 1) never sees the probes 2 and 3; each probe sees the pool and itself, not the other probe.
    assert mean[0] == pytest.approx(0.3) and count[0] == 2
    assert mean[2] == pytest.approx((0.2 + 0.4 + 0.9) / 3) and count[2] == 3
    assert mean[3] == pytest.approx((0.2 + 0.4 + 0.0) / 3) and count[3] == 3
    everyone, _ = neighbour_mean(points, directions, values)
    assert everyone[0] == pytest.approx(np.mean(values)), "without a pool every row is everyone's neighbour"



def test_a_probe_that_is_not_ok_has_no_mean_and_an_ok_one_skips_the_candidates_that_are_not():
    x = np.array([1.0, 0.0, 0.0])
    points, directions = np.zeros((4, 3)), np.array([x, x, x, x])
    values = np.array([0.2, np.nan, np.nan, 0.6])  # candidates 0 (ok) and 1 (not); probes 2 (not) and 3 (ok)
    mean, count = neighbour_mean(points, directions, values, pool=2)
    assert mean[0] == pytest.approx(0.2) and count[0] == 1
    assert np.isnan(mean[1]) and np.isnan(mean[2]) and count[1] == count[2] == 0
    assert mean[3] == pytest.approx(0.4) and count[3] == 2

def test_smoothed_rows_are_the_neighbourhood_means_of_the_counted_rows(pose_and_candidates):
    counted = _evaluate(pose_and_candidates, _topple(0.0))
    smoothed = _evaluate(pose_and_candidates, _topple(RADIUS))
    actions = pose_and_candidates[3]
    ok = actions.status == STATUS_OK
    expected, count = neighbour_mean(actions.points, actions.directions, counted.next_pose, RADIUS, ANGLE)
    assert np.allclose(smoothed.next_pose[ok], expected[ok])
    assert np.all(np.isnan(smoothed.next_pose[~ok]))
    assert np.allclose(smoothed.next_pose[ok].sum(axis=1), 1.0), "means of distributions are distributions"
    assert np.allclose(smoothed.p_topple[ok], 1.0 - smoothed.next_pose[ok, pose_and_candidates[2].index])
    assert (count[ok] > 1).any() and not np.allclose(smoothed.p_topple[ok], counted.p_topple[ok]), "the test must smooth something"
    assert np.array_equal(smoothed.outcomes, counted.outcomes), "the trials themselves are untouched"
    assert np.array_equal(smoothed.mean_force, counted.mean_force, equal_nan=True)
    # A radius no candidate is within averages each push with itself alone.
    alone = _evaluate(pose_and_candidates, _topple(1e-12))
    far = count[ok] > 0
    assert np.allclose(alone.next_pose[ok][far], counted.next_pose[ok][far])


def test_the_thesis_variants_never_smooth(pose_and_candidates):
    robust = _evaluate(pose_and_candidates, _topple(0.0, "robust"))
    asked = _evaluate(pose_and_candidates, _topple(RADIUS, "robust"))
    assert np.array_equal(robust.next_pose, asked.next_pose, equal_nan=True)
    assert _topple(RADIUS, "robust").applied_smoothing == 0.0 and _topple(RADIUS).applied_smoothing == RADIUS


def test_probes_leave_the_candidates_rows_and_are_smoothed_over_them(pose_and_candidates):
    pool = pose_and_candidates[3]
    ok = np.flatnonzero(pool.status == STATUS_OK)
    # Two probes at the contact of the ok candidate likeliest to topple, turned by 0.1 rad each
    # way: near it, and near each other.
    base = ok[np.argmax(_evaluate(pose_and_candidates, _topple(0.0)).p_topple[ok])]
    turn = np.array([[math.cos(0.1), -math.sin(0.1), 0], [math.sin(0.1), math.cos(0.1), 0], [0, 0, 1]])
    probe_directions = np.array([pool.directions[base] @ turn.T, pool.directions[base] @ turn])
    with_probes = Actions(
        points=np.vstack([pool.points, pool.points[[base, base]]]),
        normals=np.vstack([pool.normals, pool.normals[[base, base]]]),
        directions=np.vstack([pool.directions, probe_directions / np.linalg.norm(probe_directions, axis=1, keepdims=True)]),
        status=np.concatenate([pool.status, [STATUS_OK, STATUS_OK]]).astype(pool.status.dtype),
        max_height=pool.max_height,
    )
    n = len(pool.status)
    alone = _evaluate(pose_and_candidates, _topple(RADIUS))
    probed = _evaluate(pose_and_candidates, _topple(RADIUS), with_probes, candidates=n)
    assert np.array_equal(probed.next_pose[:n], alone.next_pose, equal_nan=True), "probes draw after the candidates"
    counted = _evaluate(pose_and_candidates, _topple(0.0), with_probes, candidates=n)
    assert not np.allclose(counted.next_pose[n], counted.next_pose[n + 1]), "the test needs probes that differ"
    for probe in (n, n + 1):
        rows = np.vstack([counted.next_pose[:n], counted.next_pose[probe]])
        points = np.vstack([with_probes.points[:n], with_probes.points[probe]])
        directions = np.vstack([with_probes.directions[:n], with_probes.directions[probe]])
        expected, count = neighbour_mean(points, directions, rows, RADIUS, ANGLE, rows=[n])
        assert count[0] >= 2 and np.allclose(probed.next_pose[probe], expected[0])



def test_a_probe_of_a_pose_with_no_ok_candidate_keeps_its_counted_row(pose_and_candidates):
    pool = pose_and_candidates[3]
    first = np.flatnonzero(pool.status == STATUS_OK)[0]
    n = len(pool.status)
    blocked = Actions(
        points=np.vstack([pool.points, pool.points[[first]]]),
        normals=np.vstack([pool.normals, pool.normals[[first]]]),
        directions=np.vstack([pool.directions, pool.directions[[first]]]),
        status=np.append(np.full(n, STATUS_FINGER_COLLISION), STATUS_OK).astype(pool.status.dtype),
        max_height=pool.max_height,
    )
    smoothed = _evaluate(pose_and_candidates, _topple(RADIUS), blocked, candidates=n)
    counted = _evaluate(pose_and_candidates, _topple(0.0), blocked, candidates=n)
    assert np.all(np.isnan(smoothed.next_pose[:n])), "no candidate is evaluated"
    assert np.allclose(smoothed.next_pose[n], counted.next_pose[n]), "the probe is averaged over itself alone"


def test_logged_pushes_that_are_no_ok_candidate_are_appended_as_probes():
    x, y = np.eye(3)[:2]
    pool = Actions(points=np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0]]), normals=-np.array([x, x, x]),
                   directions=np.array([x, x, x]), max_height=1,
                   status=np.array([STATUS_OK, STATUS_OK, STATUS_FINGER_COLLISION], dtype=np.int8))
    pushes = [Push("box", i, 0, np.array(point), direction, np.array([0])) for i, (point, direction) in enumerate([
        ([0.01 + 5e-7, 0, 0], x),  # candidate 1, within SAME_PUSH_TOLERANCE
        ([0.02, 0, 0], x),  # candidate 2, which is not ok: a probe
        ([0.01, 0, 0], y),  # candidate 1's contact pushed another way: a probe
        ([0.0, 0, 0], x),  # candidate 0
    ])]
    logged = Actions(points=np.array([p.point for p in pushes]), normals=-np.array([x, x, y, x]),
                     directions=np.array([p.direction for p in pushes]), status=np.full(4, STATUS_OK, dtype=np.int8))
    probed = with_probes(pool, logged, pushes)
    assert probed.candidates == 3 and probed.index.tolist() == [1, 3, 4, 0]
    assert np.array_equal(probed.actions.points, np.vstack([pool.points, logged.points[[1, 2]]]))
    assert np.array_equal(probed.actions.directions, np.vstack([pool.directions, logged.directions[[1, 2]]]))
    assert probed.actions.status.tolist() == [STATUS_OK, STATUS_OK, STATUS_FINGER_COLLISION, STATUS_OK, STATUS_OK]
    assert probed.actions.max_height == pool.max_height
    # A pose with no ok candidate: every logged push is a probe, in the log's order.
    none_ok = with_probes(replace(pool, status=np.full(3, STATUS_FINGER_COLLISION, dtype=np.int8)), logged, pushes)
    assert none_ok.index.tolist() == [3, 4, 5, 6] and len(none_ok.actions.status) == 7


@pytest.fixture(scope="module")
def box_log(model_logs):  # noqa: F811 (fixture)
    """test_validation's model-made log on three boxes: its pushes are candidates of seed 2."""
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    return read_log([path]), ContactConfig(n_contacts=CANDIDATES_PER_POSE), path


def test_the_scorer_reads_a_logged_candidate_from_the_smoothed_candidate_set(box_log):
    log, contacts, _ = box_log
    topple = _topple(RADIUS)
    scorer = Scorer(log, seed=2, contacts=contacts)  # the log's pushes are candidates of seed 2
    predictions = scorer.predict(topple)
    for group, (predicted, p_topple) in zip(scorer.groups, predictions):
        pool = scorer.pose_candidates(group)
        assert pool.candidates == len(pool.actions.status) and np.all(pool.index < pool.candidates), "all are candidates"
        obj = log.objects[group.object_id].model
        table = evaluate_pose(obj, group.pose, group.drop_probabilities, pool.actions, topple, stream(2, obj.name, group.pose.index, "trials"))
        assert np.allclose(predicted[:, :-1], table.next_pose[pool.index]) and np.all(predicted[:, -1] == 0)
        assert np.allclose(p_topple, table.p_topple[pool.index])
    # Made with another seed, the candidates are other points: every logged push is a probe.
    other = Scorer(log, seed=1, contacts=contacts)
    for group in other.groups:
        pool = other.pose_candidates(group)
        assert np.array_equal(pool.index, pool.candidates + np.arange(len(group.rows)))
    scores = other.score(topple)
    assert np.all(np.isfinite(scores.brier)) and np.all((scores.p_topple >= 0) & (scores.p_topple <= 1))
    # Without smoothing the scorer evaluates the logged pushes alone and never builds candidates.
    plain = Scorer(log, seed=2, contacts=contacts)
    plain.score(_topple(0.0))
    assert plain._candidates == {}


def test_a_negative_radius_is_refused_and_the_fields_round_trip(tmp_path):
    with pytest.raises(ValueError, match="smoothing_radius"):
        Config().with_overrides({"topple.smoothing_radius": -0.01})
    with pytest.raises(ValueError, match="smoothing_angle"):
        Config().with_overrides({"topple.smoothing_angle": 0.0})
    path = tmp_path / "smooth.toml"
    path.write_text("[topple]\nsmoothing_radius = 0.01\nsmoothing_angle = 0.35\n")
    config = Config.from_toml(path)
    assert (config.topple.smoothing_radius, config.topple.smoothing_angle) == (0.01, 0.35)
    assert config.to_dict()["topple"]["smoothing_radius"] == 0.01


def test_the_noise_is_calibrated_on_the_counts_and_the_map_fitted_on_the_smoothed_table():
    topple = replace(_topple(RADIUS), recalibration_x=(0.0, 1.0), recalibration_y=(0.0, 0.8))
    fitted_on = topple.without_recalibration()
    assert fitted_on.recalibration_x == () and fitted_on.applied_smoothing == RADIUS
    searched = topple.counted()
    assert searched.recalibration_x == () and searched.applied_smoothing == 0.0
    assert (searched.mu_table_mean, searched.smoothing_angle) == (topple.mu_table_mean, topple.smoothing_angle)


def test_a_map_fitted_on_a_smoothed_table_is_written_exactly_and_with_its_smoothing(box_log, tmp_path):
    from pipeline.studies.recalibrate import main

    _, _, path = box_log
    out, record = tmp_path / "map.toml", tmp_path / "map.json"
    code = main([str(path), "--corpus", "none", "--folds", "3", "--set", f"topple.smoothing_radius={RADIUS}",
                 "--set", f"topple.smoothing_angle={ANGLE}", "--out", str(out), "--json", str(record)])
    assert code == 0
    written = Config.from_toml(out).topple
    assert (written.smoothing_radius, written.smoothing_angle) == (RADIUS, ANGLE), "the map keeps the smoothing it was fitted on"
    fitted = json.loads(record.read_text())["knots"]
    assert list(written.recalibration_x) == fitted["x"] and list(written.recalibration_y) == fitted["y"], "knots written exactly"


def test_knots_closer_than_six_digits_survive_the_toml(tmp_path):
    from pipeline.studies.calibrate import write_toml

    x = (0.0, 0.012345671, 0.012345678, 1.0)  # equal to 6 significant digits
    write_toml(tmp_path / "k.toml", {"recalibration_x": x, "recalibration_y": (0.0, 0.1, 0.2, 0.9)}, ["test"])
    assert Config.from_toml(tmp_path / "k.toml").topple.recalibration_x == x
