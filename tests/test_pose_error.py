"""The pose-level part of P(topple)'s error (pipeline/studies/pose_error.py): each statistic
against its definition written out pair by pair, and on synthetic errors whose pose and object
parts are known."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.studies.pose_error import (
    after_another,
    leave_one_out_shift,
    main,
    other_group_covariance,
    pair_covariance,
    summarise,
)


def _pairs(group: np.ndarray, same: np.ndarray | None = None):
    """Every ordered pair (i, j), i != j, in one group (or, given ``same``, in one ``same`` but not one group)."""
    n = len(group)
    for i in range(n):
        for j in range(n):
            if i != j and ((group[i] == group[j]) if same is None else (same[i] == same[j] and group[i] != group[j])):
                yield i, j


def _small(seed: int):
    rng = np.random.default_rng(seed)
    group = rng.integers(0, 6, 40)
    outer = group // 2  # two poses per object
    p = rng.random(40)
    observed = rng.integers(0, 5, 40) / 4.0
    return p, observed, group, outer


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_covariances_are_their_pairwise_definitions(seed):
    p, observed, group, outer = _small(seed)
    r = observed - p
    same = [r[i] * r[j] for i, j in _pairs(group)]
    assert pair_covariance(r, group) == pytest.approx(np.mean(same) - r.mean() ** 2, abs=1e-12)
    other = [r[i] * r[j] for i, j in _pairs(group, outer)]
    assert other_group_covariance(r, group, outer) == pytest.approx(np.mean(other) - r.mean() ** 2, abs=1e-12)


def test_a_hand_worked_covariance_and_no_pairs():
    # Group 0 holds 1 and 3: its pairs give 1 * 3 twice; the mean residual is 3.
    assert pair_covariance(np.array([1.0, 3.0, 5.0]), np.array([0, 0, 1])) == pytest.approx(3.0 - 9.0)
    assert np.isnan(pair_covariance(np.array([1.0, 2.0]), np.array([0, 1])))
    assert np.isnan(other_group_covariance(np.array([1.0, 2.0]), np.array([0, 1]), np.array([0, 1])))


def test_synthetic_errors_show_their_pose_and_object_parts():
    """Residual = object part + pose part + push noise: the same-pose covariance finds both parts'
    variances, other poses of the object only the object's."""
    rng = np.random.default_rng(3)
    objects, poses_each, pushes_each = 400, 3, 6
    pose = np.repeat(np.arange(objects * poses_each), pushes_each)
    obj = pose // poses_each
    r = rng.normal(0, 0.1, objects)[obj] + rng.normal(0, 0.2, objects * poses_each)[pose] + rng.normal(0, 0.3, len(pose))
    assert pair_covariance(r, pose) == pytest.approx(0.01 + 0.04, abs=0.008)
    assert other_group_covariance(r, pose, obj) == pytest.approx(0.01, abs=0.004)


def test_leave_one_out_reads_only_the_other_pushes():
    r = np.array([0.2, -0.4, 0.9, 0.3, 0.6, -0.3])
    group = np.array([0, 0, 1, 2, 2, 2])
    # alone in its group: no shift; two: the other's residual; three: the mean of the other two
    assert leave_one_out_shift(r, group) == pytest.approx([-0.4, 0.2, 0.0, 0.15, 0.0, 0.45])


@pytest.mark.parametrize("seed", [0, 4])
def test_after_another_is_its_pairwise_definition(seed):
    p, observed, group, _ = _small(seed)
    p[:3] = [0.3, 0.6, 1.0]  # the bands' edges: 0.3 opens the second band, 1 closes the last
    rows = after_another(p, observed, group)
    for row, (low, high) in zip(rows, [(0.0, 0.3), (0.3, 0.6), (0.6, 1.0)]):
        pairs = [(a, b) for a, b in _pairs(group) if low <= p[a] and (p[a] < high or (high == 1.0 and p[a] <= 1.0))]
        assert row["band"] == [low, high] and row["pairs"] == len(pairs)
        for name, weight in (("failed", lambda a: 1 - observed[a]), ("toppled", lambda a: observed[a])):
            w = np.array([weight(a) for a, _ in pairs])
            b = np.array([b for _, b in pairs])
            assert row[name]["predicted"] == pytest.approx(np.sum(w * p[b]) / w.sum())
            assert row[name]["toppled"] == pytest.approx(np.sum(w * observed[b]) / w.sum())


def test_a_band_without_pushes_has_no_rates_and_a_light_one_has():
    rows = after_another(np.array([0.1, 0.2]), np.array([0.5, 1.0]), np.array([0, 0]))
    assert rows[0]["pairs"] == 2 and rows[2]["pairs"] == 0 and np.isnan(rows[2]["failed"]["predicted"])
    # only the first push ever fails, half the time: the second is all the failed weight there is
    assert rows[0]["failed"] == {"predicted": 0.2, "toppled": 1.0}


def test_the_oracle_gains_where_poses_err_together_and_the_trivial_predictors_are_shown():
    rng = np.random.default_rng(5)
    pose = np.repeat(np.arange(300), 8)
    p = rng.uniform(0.2, 0.8, len(pose))
    observed = np.clip(p + rng.normal(0, 0.25, 300)[pose] + rng.normal(0, 0.05, len(pose)), 0, 1)
    result = summarise(p, observed, pose, pose // 3)
    residual = observed - p
    assert result["mean_residual"] == pytest.approx(residual.mean())
    assert result["residual_variance"] == pytest.approx(residual.var())
    assert result["same_pose_covariance"] == pair_covariance(residual, pose)
    assert result["same_object_other_pose_covariance"] == other_group_covariance(residual, pose, pose // 3)
    assert result["after_another"] == after_another(p, observed, pose)
    brier = result["brier"]
    oracle = np.clip(p + leave_one_out_shift(residual, pose), 0, 1)  # a probability, clipped at both ends
    assert brier["pose_oracle"] == pytest.approx(np.mean((oracle - observed) ** 2))
    assert brier["pose_oracle"] < 0.5 * brier["model"]
    assert brier["never_topples"] == pytest.approx(np.mean(observed ** 2))
    assert brier["constant_rate"] == pytest.approx(np.var(observed))
    assert (result["pushes"], result["poses"], result["objects"]) == (2400, 300, 100)
    # without a pose part the oracle only adds noise
    observed = np.clip(p + rng.normal(0, 0.05, len(pose)), 0, 1)
    result = summarise(p, observed, pose, pose // 3)
    assert result["brier"]["pose_oracle"] > result["brier"]["model"]
    assert abs(result["same_pose_covariance"]) < 0.001


def test_an_unknown_config_is_a_usage_error(capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path), "--config", "no_such_preset"])
    assert exit_.value.code == 2
    assert "config file not found: no_such_preset" in capsys.readouterr().err


def test_the_pushes_of_a_log_are_read_as_the_scorer_predicts_them(tmp_path):
    """Two boxes' log made by the model itself: every push read, grouped by (object, pose), with
    the scorer's P and the log's own topple rate."""
    import pyarrow.parquet as pq
    import trimesh

    from pipeline.model.config import Config
    from pipeline.studies.logreader import read_log
    from pipeline.studies.pose_error import read_pushes
    from pipeline.studies.scoring import Scorer
    from pipeline.studies.synthetic_log import MeshSpec, model_log

    specs = []
    for i, size in enumerate([(0.05, 0.08, 0.15), (0.06, 0.06, 0.12)]):
        trimesh.creation.box(size).export(tmp_path / f"box{i}.stl")
        specs.append(MeshSpec(f"box{i}", str(tmp_path / f"box{i}.stl"), 1.0, 0.25))
    pq.write_table(model_log(specs, Config(), pushes_per_pose=3, repeats=4, seed=1), tmp_path / "log.parquet")
    p, observed, group, obj = read_pushes([str(tmp_path / "log.parquet")], Config())
    scorer = Scorer(read_log([tmp_path / "log.parquet"], Config()))
    expected = np.full(len(scorer), np.nan)
    for members, (_, predicted) in zip(scorer.groups, scorer.predict(Config().topple)):
        expected[members.rows] = predicted
    usable = np.isfinite(expected)
    assert len(p) == usable.sum() > 0
    assert p == pytest.approx(expected[usable]) and observed == pytest.approx(scorer.empirical_topple[usable])
    pushes = [push for push, ok in zip(scorer.log.pushes, usable) if ok]
    keys = [(push.object_id, push.pose) for push in pushes]
    # one group per (object, pose), one object index per object
    assert len(set(zip(keys, group))) == len(set(keys)) == len(set(group))
    assert len(set(zip([k[0] for k in keys], obj))) == len(set(obj)) == 2
    assert group.dtype.kind == obj.dtype.kind == "i"
    # Given a corpus, its objects' pushes only (the study reads calibration data).
    from pipeline.build.corpus import Corpus, ObjectSpec

    corpus = Corpus("test", [ObjectSpec("box0", specs[0].path, 1.0, 0.25, "file", "")])
    p0, observed0, _, obj0 = read_pushes([str(tmp_path / "log.parquet")], Config(), corpus)
    box0 = np.array([key[0] == "box0" for key in keys])
    assert 0 < len(p0) == box0.sum() < len(p) and len(set(obj0)) == 1
    assert p0 == pytest.approx(p[box0]) and observed0 == pytest.approx(observed[box0])
