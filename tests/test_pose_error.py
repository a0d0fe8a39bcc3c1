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
    resampled,
    summarise,
)

K = 2.1
"""The after-failure power of the tables' belief, as the default's."""


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
    c = r - r.mean()  # about the overall mean; the groups' sizes differ, so this is not E[r_i r_j] - mean^2
    same = [c[i] * c[j] for i, j in _pairs(group)]
    assert pair_covariance(r, group) == pytest.approx(np.mean(same), abs=1e-12)
    other = [c[i] * c[j] for i, j in _pairs(group, outer)]
    assert other_group_covariance(r, group, outer) == pytest.approx(np.mean(other), abs=1e-12)


def test_a_hand_worked_covariance_no_pairs_and_no_pushes():
    # The mean is 4: centred, group 0 holds -3 and -1, whose two ordered pairs give 3 each.
    assert pair_covariance(np.array([1.0, 3.0, 8.0]), np.array([0, 0, 1])) == pytest.approx(3.0)
    assert np.isnan(pair_covariance(np.array([1.0, 2.0]), np.array([0, 1])))
    assert np.isnan(other_group_covariance(np.array([1.0, 2.0]), np.array([0, 1]), np.array([0, 1])))
    assert np.isnan(pair_covariance([], [])) and np.isnan(other_group_covariance([], [], []))


def test_a_pose_in_two_objects_is_refused():
    with pytest.raises(ValueError, match="lies in two outer groups"):
        other_group_covariance(np.array([1.0, 2.0, 3.0]), np.array([0, 0, 1]), np.array([0, 1, 1]))


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


@pytest.mark.parametrize(("seed", "others_from"), [(0, 0.0), (4, 0.0), (4, 0.5)])
def test_after_another_is_its_pairwise_definition(seed, others_from):
    p, observed, group, _ = _small(seed)
    p[:3] = [0.3, 0.6, 1.0]  # the bands' edges: 0.3 opens the second band, 1 closes the last
    rows = after_another(p, observed, group, K, others_from=others_from)
    for row, (low, high) in zip(rows, [(0.0, 0.3), (0.3, 0.6), (0.6, 1.0)]):
        pairs = [(a, b) for a, b in _pairs(group)
                 if low <= p[a] and (p[a] < high or (high == 1.0 and p[a] <= 1.0)) and p[b] >= others_from]
        assert row["band"] == [low, high] and row["pairs"] == len(pairs)
        for name, weight in (("failed", lambda a: 1 - observed[a]), ("toppled", lambda a: observed[a])):
            w = np.array([weight(a) for a, _ in pairs])
            b = np.array([b for _, b in pairs])
            assert row[name]["predicted"] == pytest.approx(np.sum(w * p[b]) / w.sum())
            assert row[name]["believed"] == pytest.approx(np.sum(w * p[b] ** K) / w.sum())
            assert row[name]["toppled"] == pytest.approx(np.sum(w * observed[b]) / w.sum())


def test_a_band_without_pushes_has_no_rates_and_a_light_one_has():
    rows = after_another(np.array([0.1, 0.2]), np.array([0.5, 1.0]), np.array([0, 0]), 2.0)
    assert rows[0]["pairs"] == 2 and rows[2]["pairs"] == 0 and np.isnan(rows[2]["failed"]["predicted"])
    # only the first push ever fails, half the time: the second is all the failed weight there is
    assert rows[0]["failed"] == pytest.approx({"predicted": 0.2, "believed": 0.04, "toppled": 1.0})


def test_the_oracle_gains_where_poses_err_together_and_the_trivial_predictors_are_shown():
    rng = np.random.default_rng(5)
    pose = np.repeat(np.arange(300), 8)
    p = rng.uniform(0.2, 0.8, len(pose))
    observed = np.clip(p + rng.normal(0, 0.25, 300)[pose] + rng.normal(0, 0.05, len(pose)), 0, 1)
    result = summarise(p, observed, pose, pose // 3, K, n_resamples=100)
    residual = observed - p
    assert result["mean_residual"] == pytest.approx(residual.mean())
    assert result["residual_variance"] == pytest.approx(residual.var())
    assert result["same_pose_covariance"] == pair_covariance(residual, pose)
    assert result["same_object_other_pose_covariance"] == other_group_covariance(residual, pose, pose // 3)
    assert result["after_another"] == after_another(p, observed, pose, K)
    assert result["after_another_others_from_0.6"] == after_another(p, observed, pose, K, others_from=0.6)
    # a pose part exists (its variance 0.0625 before the clip to [0, 1]): its interval excludes 0 and holds the estimate
    low, high = result["intervals"]["same_pose_covariance"]
    assert 0.03 < low < result["same_pose_covariance"] < high < 0.0625
    assert result["intervals"]["oracle_gain"][1] < 0
    brier = result["brier"]
    oracle = np.clip(p + leave_one_out_shift(residual, pose), 0, 1)  # a probability, clipped at both ends
    assert brier["pose_oracle"] == pytest.approx(np.mean((oracle - observed) ** 2))
    assert brier["pose_oracle"] < 0.5 * brier["model"]
    assert brier["never_topples"] == pytest.approx(np.mean(observed ** 2))
    assert brier["constant_rate"] == pytest.approx(np.var(observed))
    assert (result["pushes"], result["poses"], result["objects"]) == (2400, 300, 100)
    # without a pose part the oracle only adds noise
    observed = np.clip(p + rng.normal(0, 0.05, len(pose)), 0, 1)
    result = summarise(p, observed, pose, pose // 3, K, n_resamples=0)
    assert result["brier"]["pose_oracle"] > result["brier"]["model"]
    assert abs(result["same_pose_covariance"]) < 0.001
    assert result["intervals"]["oracle_gain"] is None
    with pytest.raises(ValueError, match="no pushes"):
        summarise([], [], [], [], K)


def test_a_resample_copies_whole_objects_each_with_poses_of_its_own():
    group = np.array([0, 0, 1, 2, 2, 2, 3])
    outer = np.array([0, 0, 0, 1, 1, 1, 2])
    rows, new_group, copy = resampled(group, outer, np.random.default_rng(0))
    assert len(set(copy)) == 3  # as many copies as objects
    for c in set(copy):
        mine = rows[copy == c]
        assert len(set(outer[mine])) == 1 and sorted(mine) == list(np.flatnonzero(outer == outer[mine[0]]))
    # a pose's pushes stay together within a copy, and two copies never share a pose label
    assert len(set(zip(copy, group[rows]))) == len(set(new_group))


def test_an_unknown_config_is_a_usage_error(capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path), "--config", "no_such_preset"])
    assert exit_.value.code == 2
    assert "config file not found: no_such_preset" in capsys.readouterr().err


@pytest.fixture(scope="module")
def box_log(tmp_path_factory):
    """(log path, mesh specs): a log of two boxes made by the model itself (pipeline.studies.synthetic_log)."""
    import pyarrow.parquet as pq
    import trimesh

    from pipeline.model.config import Config
    from pipeline.studies.synthetic_log import MeshSpec, model_log

    root = tmp_path_factory.mktemp("pose_error")
    specs = []
    for i, size in enumerate([(0.05, 0.08, 0.15), (0.06, 0.06, 0.12)]):
        trimesh.creation.box(size).export(root / f"box{i}.stl")
        specs.append(MeshSpec(f"box{i}", str(root / f"box{i}.stl"), 1.0, 0.25))
    pq.write_table(model_log(specs, Config(), pushes_per_pose=3, repeats=4, seed=1), root / "log.parquet")
    return root / "log.parquet", specs


def test_the_pushes_of_a_log_are_read_as_the_scorer_predicts_them(box_log):
    """Every usable push read, grouped by (object, pose), with the P the scorer predicts by the
    configuration's own model (its seed and contacts) and the log's own topple rate."""
    from pipeline.build.corpus import Corpus, ObjectSpec
    from pipeline.model.config import Config
    from pipeline.studies.logreader import read_log
    from pipeline.studies.pose_error import read_pushes
    from pipeline.studies.scoring import Scorer

    path, specs = box_log
    config = Config().with_overrides({"seed": 7, "contacts.n_contacts": 300})
    p, observed, group, obj = read_pushes([str(path)], config)
    scorer = Scorer(read_log([path], config), seed=7, contacts=config.contacts)
    expected = np.full(len(scorer), np.nan)
    for members, (_, predicted) in zip(scorer.groups, scorer.predict(config.topple)):
        expected[members.rows] = predicted
    usable = np.isfinite(expected)
    assert len(p) == usable.sum() > 0
    assert p == pytest.approx(expected[usable]) and observed == pytest.approx(scorer.empirical_topple[usable])
    default_seed_p = read_pushes([str(path)], Config().with_overrides({"contacts.n_contacts": 300}))[0]
    assert not np.allclose(default_seed_p, p)  # the seed's trials, not the default's
    pushes = [push for push, ok in zip(scorer.log.pushes, usable) if ok]
    keys = [(push.object_id, push.pose) for push in pushes]
    # one group per (object, pose), one object index per object
    assert len(set(zip(keys, group))) == len(set(keys)) == len(set(group))
    assert len(set(zip([k[0] for k in keys], obj))) == len(set(obj)) == 2
    assert group.dtype.kind == obj.dtype.kind == "i"
    # Given a corpus, its objects' pushes only (the study reads calibration data).
    corpus = Corpus("test", [ObjectSpec("box0", specs[0].path, 1.0, 0.25, "file", "")])
    p0, observed0, _, obj0 = read_pushes([str(path)], config, corpus)
    box0 = np.array([key[0] == "box0" for key in keys])
    assert 0 < len(p0) == box0.sum() < len(p) and len(set(obj0)) == 1
    assert p0 == pytest.approx(p[box0]) and observed0 == pytest.approx(observed[box0])


def test_the_command_writes_strict_json_and_refuses_a_log_with_no_corpus_push(box_log, tmp_path, capsys):
    import json

    path, _ = box_log
    out = tmp_path / "pose_error.json"
    fewer = tmp_path / "fewer_contacts.toml"  # the default model on fewer contacts: a third of the scoring time
    fewer.write_text("[contacts]\nn_contacts = 300\n")
    assert main([str(path), "--config", str(fewer), "--corpus", "none", "--bootstrap", "20", "--json", str(out)]) == 0
    result = json.loads(out.read_text(), parse_constant=lambda name: pytest.fail(f"{name} in the JSON"))
    assert result == json.loads(capsys.readouterr().out)
    assert result["objects"] == 2 and result["after_failure_power"] == 2.1
    assert len(result["intervals"]["same_pose_covariance"]) == 2
    # the boxes are not in the default corpus, which the study reads by default
    with pytest.raises(SystemExit) as exit_:
        main([str(path)])
    assert exit_.value.code == 2 and "no usable push" in capsys.readouterr().err
