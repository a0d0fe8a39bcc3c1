"""The landing trusted by its pose's drop probability (candidate LT): (LT.1), its fit, and the planners over it."""

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.landing_trust import BANDS, landing_bands, trust_terms, trusted_rows
from pipeline.studies.landing_trust import TrustData, TrustError, fit_shares, object_datasets, out_of_fold, predictions, study, trust_data
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)

DROP = np.array([0.5, 0.3, 0.04, 0.16])
"""Drop probabilities: pose 2 in the rarest band, pose 3 in (0.1, 0.2], poses 0 and 1 above."""


def test_bands_close_on_the_right():
    assert landing_bands(np.array([0.0, 0.05, 0.0501, 0.1, 0.2, 0.21, 1.0])).tolist() == [0, 0, 1, 1, 2, 3, 3]
    assert len(BANDS) + 1 == 4


def test_a_landing_in_a_rare_pose_moves_its_untrusted_share_to_the_other_poses_by_drop_probability():
    rows = np.array([[0.4, 0.0, 0.6, 0.0]])  # from pose 0, lands in pose 2 (drop 0.04, band 0)
    trusted = trusted_rows(rows, 0, DROP, np.array([0.5, 0.0, 0.0, 0.0]))
    # 0.3 moves, spread over poses 1, 2, 3 as 0.3 : 0.04 : 0.16 of their 0.5.
    np.testing.assert_allclose(trusted, [[0.4, 0.3 * 0.6, 0.3 + 0.3 * 0.08, 0.3 * 0.32]])
    # A share of a band the row does not land in moves nothing.
    np.testing.assert_allclose(trusted_rows(rows, 0, DROP, np.array([0.0, 1.0, 1.0, 1.0])), rows)


def test_the_trust_keeps_every_rows_stay_and_sum_and_leaves_rows_that_are_not_ok():
    rng = np.random.default_rng(0)
    rows = rng.dirichlet(np.ones(4), 20)
    rows[3] = np.nan
    for pose in range(4):
        rows[5] = np.eye(4)[pose]  # never topples
        for shares in (np.array([0.5, 0.2, 0.1, 0.0]), np.ones(4), rng.uniform(0, 1, 4)):
            trusted = trusted_rows(rows, pose, DROP, shares)
            ok = ~np.isnan(rows).any(axis=1)
            assert np.isnan(trusted[~ok]).all()
            np.testing.assert_allclose(trusted[ok, pose], rows[ok, pose])
            np.testing.assert_allclose(trusted[ok].sum(axis=1), 1.0)
            assert (trusted[ok] >= -1e-12).all()
            np.testing.assert_allclose(trusted[5], rows[5])
        # Every share 1: each row's topples land by the prior alone.
        leaving = 1 - rows[ok, pose]
        prior = np.where(np.arange(4) == pose, 0.0, DROP) / (1 - DROP[pose])
        expected = leaving[:, None] * prior
        expected[:, pose] = rows[ok, pose]
        np.testing.assert_allclose(trusted_rows(rows, pose, DROP, np.ones(4))[ok], expected)
    assert trusted_rows(rows, 0, DROP, np.zeros(4)) is rows


def test_with_no_other_pose_to_land_in_nothing_moves_and_bad_shares_are_refused():
    rows = np.array([[0.5, 0.5, 0.0]])
    np.testing.assert_allclose(trusted_rows(rows, 0, np.array([1.0, 0.0, 0.0]), np.ones(4)), rows)
    for bad in (np.array([0.5, 0.5, 0.5]), np.array([-0.1, 0, 0, 0]), np.array([0, 0, 1.5, 0])):
        with pytest.raises(ValueError, match="one per band"):
            trusted_rows(rows, 0, DROP[:3], bad)


def test_the_rows_are_linear_in_the_shares():
    rows = np.random.default_rng(1).dirichlet(np.ones(4), 6)
    terms = trust_terms(rows, 1, DROP)
    np.testing.assert_allclose(terms.sum(axis=1), 0.0, atol=1e-12)  # P(topple) never moves
    shares = np.array([0.3, 0.6, 0.1, 0.9])
    np.testing.assert_allclose(trusted_rows(rows, 1, DROP, shares), rows + terms @ shares)


def test_the_planners_over_trusted_rows_turn_from_a_landing_in_a_rare_pose():
    from pipeline.model.config import MDPConfig
    from pipeline.studies.robust_policy import prior_plan, value_iteration_actions

    # From pose 0 (V_s 0.2): push 0 lands in the rare pose 2 (V_s 0.9), push 1 in the common pose 1 (V_s 0.8).
    v_s = np.array([0.2, 0.8, 0.9, 0.0])
    drop = np.array([0.5, 0.35, 0.03, 0.12])
    rows = [np.array([[0.1, 0.0, 0.9, 0.0], [0.1, 0.9, 0.0, 0.0]]), *(np.eye(4)[x][None, :] for x in (1, 2, 3))]
    choosable = [np.ones(len(r), dtype=bool) for r in rows]
    mdp = MDPConfig(choice_radius=0.0)
    assert value_iteration_actions(v_s, rows, mdp, choosable)[0] == 0
    trusted = [trusted_rows(r, x, drop, np.array([0.5, 0.25, 0.15, 0.03])) for x, r in enumerate(rows)]
    actions, _, _ = prior_plan(v_s, trusted, mdp, choosable, 3)
    assert actions["prior_vi"][0] == actions["prior_belief_vi"][0] == 1
    # A trust that only doubts the common band leaves the choice where it was.
    doubted = [trusted_rows(r, x, drop, np.array([0.0, 0.0, 0.0, 0.5])) for x, r in enumerate(rows)]
    assert prior_plan(v_s, doubted, mdp, choosable, 3)[0]["prior_vi"][0] == 0


def synthetic(shares: np.ndarray, objects: int = 12, seed: int = 0) -> TrustData:
    """Pushes whose observed frequencies are exactly (LT.1) of their rows at ``shares``."""
    rng = np.random.default_rng(seed)
    parts = {k: [] for k in ("row", "terms", "observed", "prior", "stay", "band")}
    names, sizes = [], []
    for n in range(objects):
        drop = rng.dirichlet(np.ones(5) * 0.7)
        for pose in range(5):
            rows = rng.dirichlet(np.ones(5) * 0.3, 4)
            terms = trust_terms(rows, pose, drop)
            for r, t in zip(rows, terms):
                parts["row"].append(np.append(r, 0.0))
                parts["terms"].append(np.vstack([t, np.zeros(4)]))
                parts["observed"].append(np.append(r + t @ shares, 0.0))
                parts["prior"].append(np.zeros(6))
                parts["stay"].append(np.arange(6) == pose)
                parts["band"].append(np.where(np.arange(6) == pose, -1, np.append(landing_bands(drop), -1)))
                names.append(f"object_{n}")
                sizes.append(6)
    flat = {k: np.concatenate(v) for k, v in parts.items()}
    return TrustData(flat["row"], flat["terms"], flat["observed"], flat["prior"], flat["stay"], flat["band"],
                     np.concatenate([[0], np.cumsum(sizes)]), np.array(names), np.full(len(names), 8), Counter())


def test_the_fit_recovers_the_shares_that_made_the_observations():
    truth = np.array([0.6, 0.3, 0.1, 0.0])
    data = synthetic(truth)
    np.testing.assert_allclose(fit_shares(data), truth, atol=1e-9)
    scores = {k: ((v - data.observed) ** 2).sum() for k, v in predictions(data, fit_shares(data)).items()}
    assert scores["trust"] == pytest.approx(0.0, abs=1e-12) and scores["rows"] > 0
    # Out of fold each fold's fit finds the same shares, and the trust beats the rows on every push.
    folds = [[f"object_{n}" for n in range(k, 12, 3)] for k in range(3)]
    oof = out_of_fold(data, folds)
    assert [f["pushes"] for f in oof["folds"]] == [80, 80, 80]
    for fold in oof["folds"]:
        np.testing.assert_allclose(fold["shares"], truth, atol=1e-9)
    assert oof["brier"]["trust_out_of_fold"] == pytest.approx(0.0, abs=1e-12)
    assert oof["trust_minus_rows_interval"][1] < 0


def test_shares_are_bounded_and_a_band_nothing_lands_in_gets_none():
    data = synthetic(np.array([1.0, 0.3, 0.1, 0.0]))
    data.observed = data.row + data.terms @ np.array([1.0, 0.3, 0.1, 0.0]) * 1.5  # would take shares above 1
    assert (fit_shares(data) <= 1.0 + 1e-12).all() and (fit_shares(data) >= 0).all()
    data = synthetic(np.array([0.4, 0.2, 0.0, 0.0]))
    data.terms[:, 3] = 0.0  # nothing lands in band 3
    assert fit_shares(data)[3] == 0.0


@pytest.fixture(scope="module")
def oracle_log(dataset, tmp_path_factory):  # noqa: F811 (fixture)
    from pipeline.studies.oracle_policy import experiment

    log = tmp_path_factory.mktemp("trust") / "log"
    experiment(dataset, 40, seed=2, repeats=2, ks=(3,), workers=1, log=log)
    return log


def test_each_logged_push_is_read_against_the_row_the_planner_saw(dataset, oracle_log):  # noqa: F811 (fixture)
    from pipeline.model.config import Config
    from pipeline.studies.logreader import read_log
    from pipeline.studies.policy_experiment import ACTION_SPAN
    from pipeline.studies.robust_policy import next_pose_rows, read_candidates
    from schema.reader import Dataset

    log = read_log([oracle_log], Config())
    data = trust_data(log, object_datasets([dataset]))
    assert len(data.objects) == len(log.pushes) > 0 and not data.rejected
    opened = Dataset.open(dataset)
    rows = {o: next_pose_rows(opened, o, [len(c.q) for c in read_candidates(opened, o)]) for o in set(data.objects)}
    for i, push in enumerate(log.pushes):
        pose, action = divmod(push.push_id, ACTION_SPAN)
        span = slice(data.start[i], data.start[i + 1])
        np.testing.assert_allclose(data.row[span], np.append(rows[push.object_id][pose][action], 0.0))
        np.testing.assert_allclose(data.observed[span], push.empirical(len(rows[push.object_id])))
        assert data.stay[span].tolist() == (np.arange(data.start[i + 1] - data.start[i]) == pose).tolist()
    # The bands share out every push's landing: the rows' leaving mass, and physics' topples into the pose set.
    from pipeline.studies.landing_trust import band_summary

    bands = band_summary(data)
    assert sum(b["predicted_mass"] for b in bands) == pytest.approx(float((1 - data.row[data.stay]).sum()))
    observed_outside = data.observed[data.start[1:] - 1].sum()  # each push's last bucket
    assert sum(b["observed_mass"] for b in bands) == pytest.approx(float((1 - data.observed[data.stay]).sum() - observed_outside))
    result = study([str(oracle_log)], [dataset], None, Config())
    assert result["pushes"] == len(log.pushes) and all(0 <= s <= 1 for s in result["shares"])
    assert result["shares_fitted"] and result["brier"]["trust"] <= result["brier"]["rows"] + 1e-12
    assert result["trust_minus_rows"] == pytest.approx(result["brier"]["trust"] - result["brier"]["rows"])
    # Given shares are scored as they are: none moves nothing, and the fitted ones score what the fit scored.
    none = study([str(oracle_log)], [dataset], None, Config(), [0.0, 0.0, 0.0, 0.0])
    assert not none["shares_fitted"] and none["brier"]["trust"] == none["brier"]["rows"] == result["brier"]["rows"]
    again = study([str(oracle_log)], [dataset], None, Config(), result["shares"])
    assert again["brier"] == result["brier"]
    for bad in ([0.5, 0.5, 0.5], [0.0, 0.0, 1.2, 0.0]):
        with pytest.raises(TrustError, match="one per band"):
            study([str(oracle_log)], [dataset], None, Config(), bad)
    with pytest.raises(TrustError, match="give one or the other"):
        study([str(oracle_log)], [dataset], Path("folds"), Config(), [0.0, 0.0, 0.0, 0.0])


def test_objects_outside_the_datasets_are_counted_and_an_object_in_two_is_refused(dataset, oracle_log, tmp_path):  # noqa: F811
    import shutil
    from dataclasses import replace

    from pipeline.model.config import Config
    from pipeline.studies.landing_trust import main
    from pipeline.studies.logreader import read_log

    log = read_log([oracle_log], Config())
    datasets = object_datasets([dataset])
    # One push moved to an object no dataset holds: counted under its reason, the others read.
    moved = replace(log.pushes[0], object_id="elsewhere")
    data = trust_data(replace(log, pushes=[moved, *log.pushes[1:]]), datasets)
    assert data.rejected == {"object in none of the datasets": 1} and len(data.objects) == len(log.pushes) - 1
    with pytest.raises(TrustError, match="no push of the log"):
        trust_data(log, {})
    shutil.copytree(dataset, tmp_path / "copy")
    with pytest.raises(TrustError, match="give each object's dataset once"):
        object_datasets([dataset, tmp_path / "copy"])
    assert main([str(oracle_log), "--datasets", str(tmp_path / "missing")]) == 2



# Review (stop 50): what mutation testing found unchecked.

def test_a_row_that_is_not_ok_gets_no_terms_and_a_bad_share_count_is_named():
    rows = np.array([[np.nan] * 4, [0.4, 0.0, 0.6, 0.0]])
    terms = trust_terms(rows, 0, DROP)
    assert (terms[0] == 0).all() and np.abs(terms[1]).sum() > 0
    with pytest.raises(ValueError, match="the untrusted shares are 4 numbers in"):
        trusted_rows(rows, 0, DROP, np.array([0.5, 0.5, 0.5]))


def tiny() -> TrustData:
    """Two pushes by hand: three poses plus outside, drop 0.6, 0.3, 0.1 (bands 3, 3, 1)."""
    drop = np.array([0.6, 0.3, 0.1])
    rows = [np.array([0.5, 0.2, 0.3]), np.array([0.1, 0.7, 0.2])]  # from poses 0 and 1
    observed = [np.array([0.25, 0.5, 0.0, 0.25]), np.array([0.0, 0.5, 0.5, 0.0])]
    parts = {k: [] for k in ("row", "terms", "observed", "prior", "stay", "band")}
    for pose, (row, seen) in enumerate(zip(rows, observed)):
        parts["row"].append(np.append(row, 0.0))
        parts["terms"].append(np.vstack([trust_terms(row[None], pose, drop)[0], np.zeros(4)]))
        parts["observed"].append(seen)
        prior = np.where(np.arange(3) == pose, 0.0, drop)
        parts["prior"].append(np.append(prior / prior.sum(), 0.0))
        parts["stay"].append(np.arange(4) == pose)
        parts["band"].append(np.where(np.arange(4) == pose, -1, [3, 3, 1, -1]))
    flat = {k: np.concatenate(v) for k, v in parts.items()}
    return TrustData(flat["row"], flat["terms"], flat["observed"], flat["prior"], flat["stay"], flat["band"],
                     np.array([0, 4, 8]), np.array(["a", "b"]), np.array([4, 2]), {})


def test_the_scores_and_the_trivial_predictors_by_hand():
    from pipeline.studies.landing_trust import band_summary, brier_per_push

    data = tiny()
    np.testing.assert_allclose(brier_per_push(data, data.row), [0.0625 + 0.09 + 0.09 + 0.0625, 0.01 + 0.04 + 0.09])
    got = predictions(data, np.zeros(4))
    assert set(got) == {"rows", "trust", "prior_landing", "never_topples", "constant_rate"}
    np.testing.assert_allclose(got["trust"], data.row)
    np.testing.assert_allclose(got["never_topples"], [1, 0, 0, 0, 0, 1, 0, 0])
    # The log topples 0.75 and 0.5 of its plays: a rate of 0.625, landing by the prior.
    np.testing.assert_allclose(got["constant_rate"], [0.375, 0.625 * 0.75, 0.625 * 0.25, 0, 0.625 * 6 / 7, 0.375, 0.625 / 7, 0])
    # Every share 1: the leaving mass (0.5 and 0.3) lands by the prior alone.
    np.testing.assert_allclose(got["prior_landing"], [0.5, 0.5 * 0.75, 0.5 * 0.25, 0, 0.3 * 6 / 7, 0.7, 0.3 / 7, 0])
    assert band_summary(data) == [
        {"band": 0, "predicted_mass": 0.0, "observed_mass": 0.0, "pushes": 0},
        {"band": 1, "predicted_mass": pytest.approx(0.5), "observed_mass": 0.5, "pushes": 2},
        {"band": 2, "predicted_mass": 0.0, "observed_mass": 0.0, "pushes": 0},
        {"band": 3, "predicted_mass": pytest.approx(0.3), "observed_mass": 0.5, "pushes": 2}]


def test_the_fit_uses_only_the_pushes_asked_and_each_fold_is_scored_by_the_others_fit():
    truth, other = np.array([0.6, 0.3, 0.1, 0.0]), np.array([0.1, 0.0, 0.5, 0.4])
    data = synthetic(truth)
    b = np.isin(data.objects, [f"object_{n}" for n in range(0, 12, 3)])  # fold 0's objects land by other shares
    data.observed[b[data.bucket_push]] = (data.row + data.terms @ other)[b[data.bucket_push]]
    np.testing.assert_allclose(fit_shares(data, b), other, atol=1e-9)
    np.testing.assert_allclose(fit_shares(data, ~b), truth, atol=1e-9)
    # Small landings still count: the fit does not drop a band by the size of its terms.
    scaled = synthetic(truth)
    scaled.terms *= 1e-4
    scaled.observed = scaled.row + scaled.terms @ truth
    np.testing.assert_allclose(fit_shares(scaled), truth, atol=1e-6)
    # A fold with no pushes (fold 1 here) is skipped, the others still scored.
    folds = [[f"object_{n}" for n in range(0, 12, 3)], ["nobody"], [f"object_{n}" for n in range(12) if n % 3]]
    oof = out_of_fold(data, folds)
    assert [f["fold"] for f in oof["folds"]] == [0, 2] and [f["pushes"] for f in oof["folds"]] == [80, 160]
    np.testing.assert_allclose(oof["folds"][0]["shares"], fit_shares(data, ~b))
    np.testing.assert_allclose(oof["folds"][1]["shares"], fit_shares(data, b))
    fold_of_bucket = b[data.bucket_push]
    trust = np.where(fold_of_bucket, data.row + data.terms @ fit_shares(data, ~b), data.row + data.terms @ fit_shares(data, b))
    from pipeline.studies.landing_trust import brier_per_push

    rows, trusted = brier_per_push(data, data.row).mean(), brier_per_push(data, trust).mean()
    prior = brier_per_push(data, data.row + data.terms @ np.ones(4)).mean()
    assert set(oof["brier"]) == {"rows", "prior_landing", "never_topples", "constant_rate", "trust_out_of_fold"}
    assert oof["brier"]["trust_out_of_fold"] == pytest.approx(trusted) and oof["brier"]["rows"] == pytest.approx(rows)
    assert oof["trust_minus_rows"] == pytest.approx(trusted - rows)
    assert oof["prior_landing_minus_rows"] == pytest.approx(prior - rows)
    low, high = oof["trust_minus_rows_interval"]
    assert low <= trusted - rows <= high
    low, high = oof["prior_landing_minus_rows_interval"]
    assert low <= prior - rows <= high


def test_each_push_carries_its_start_poses_terms_prior_and_bands(dataset, oracle_log):  # noqa: F811 (fixture)
    from pipeline.model.config import Config
    from pipeline.model.landing_spread import landing_prior
    from pipeline.studies.logreader import read_log
    from schema.reader import Dataset

    log = read_log([oracle_log], Config())
    data = trust_data(log, object_datasets([dataset]))
    poses = Dataset.open(dataset).table("poses", columns=["object_id", "pose", "probability"]).to_pydict()
    for i, push in enumerate(log.pushes):
        drop = np.array([d for _, d in sorted((p, d) for o, p, d in zip(poses["object_id"], poses["pose"], poses["probability"])
                                              if o == push.object_id)])
        span = slice(data.start[i], data.start[i + 1])
        row = data.row[span][:-1]
        np.testing.assert_allclose(data.terms[span], np.vstack([trust_terms(row[None], push.pose, drop)[0], np.zeros(4)]))
        np.testing.assert_allclose(data.prior[span], np.append(landing_prior(drop, push.pose, len(drop)), 0.0))
        expected = np.append(landing_bands(drop), -1)
        expected[push.pose] = -1
        assert data.band[span].tolist() == expected.tolist()


def test_pushes_the_datasets_cannot_place_are_counted_each_under_its_reason(dataset, oracle_log):  # noqa: F811 (fixture)
    from dataclasses import replace

    from pipeline.model.config import Config
    from pipeline.studies.logreader import read_log
    from pipeline.studies.policy_experiment import ACTION_SPAN

    log = read_log([oracle_log], Config())
    datasets = object_datasets([dataset])
    first, second = log.pushes[0], log.pushes[1]
    poses = datasets[first.object_id].table("poses", columns=["object_id", "pose", "n_actions"]).to_pydict()
    (n_actions,) = [n for o, x, n in zip(poses["object_id"], poses["pose"], poses["n_actions"]) if o == first.object_id and x == first.pose]
    bad = [replace(first, object_id="elsewhere"), replace(second, object_id="nowhere"),
           replace(first, push_id=first.pose * ACTION_SPAN + ACTION_SPAN - 1),  # no such action
           replace(first, push_id=first.pose * ACTION_SPAN + n_actions),  # one past the pose's last action
           replace(second, push_id=(second.pose + 1) * ACTION_SPAN)]  # another start pose
    data = trust_data(replace(log, pushes=[*bad, *log.pushes]), datasets)
    assert data.rejected == {"object in none of the datasets": 2, "push id names no ok push of its start pose": 3}
    assert len(data.objects) == len(log.pushes)
    # Objects whose dataset holds other stable poses than the log's (here none): all their pushes set aside, the others read.
    twins = {name: log.objects[first.object_id] for name in ("twin_a", "twin_b")}
    moved = [replace(p, object_id=name) for name in twins for p in log.pushes]
    data = trust_data(replace(log, pushes=[*moved, *log.pushes], objects={**log.objects, **twins}),
                      {**datasets, **{name: datasets[first.object_id] for name in twins}})
    assert data.rejected == {"the dataset's stable poses differ from the log's": 2 * len(log.pushes)}
    assert len(data.objects) == len(log.pushes)


def test_the_study_out_of_fold_prints_and_writes_its_record(dataset, oracle_log, tmp_path, capsys):  # noqa: F811 (fixture)
    import json

    from pipeline.studies.landing_trust import main

    lines = (dataset.parent / "corpus.csv").read_text().splitlines()
    folds = tmp_path / "folds"
    folds.mkdir()
    for k, line in enumerate(lines[1:]):
        (folds / f"fold_{k}.csv").write_text(f"{lines[0]}\n{line}\n")
    out = tmp_path / "trust.json"
    assert main([str(oracle_log), "--datasets", str(dataset), "--folds", str(folds), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    assert set(result) == {"logs", "datasets", "bands", "pushes", "objects", "plays", "rejected_pushes", "log_rejected_rows",
                           "shares", "shares_fitted", "by_band", "brier", "trust_minus_rows", "trust_minus_rows_interval",
                           "out_of_fold"}
    assert result["logs"] == [str(oracle_log)] and result["datasets"] == [str(dataset)] and result["bands"] == list(BANDS)
    assert result["objects"] == 1 and result["plays"] >= result["pushes"] > 0 and result["rejected_pushes"] == {}
    assert [b["band"] for b in result["by_band"]] == [0, 1, 2, 3]
    (fold,) = result["out_of_fold"]["folds"]  # the log's one object's; the other fold has no push
    assert fold["fold"] in (0, 1) and fold["pushes"] == result["pushes"]
    assert f"{result['pushes']} pushes ({result['plays']} plays) on 1 objects" in printed
    assert "untrusted share per band (drop probability <= 0.05, 0.1, 0.2, above): " in printed
    assert "out of fold, next-pose Brier: rows " in printed and "trust minus rows " in printed and f"  fold {fold['fold']} (" in printed
    assert f"trust minus rows {result['out_of_fold']['trust_minus_rows']:+.4f}" in printed
    # A bad input is one line on stderr, naming what is wrong.
    assert main([str(oracle_log), "--datasets", str(dataset), "--folds", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "holds 0 fold list(s)" in err and len(err.strip().splitlines()) == 1
    assert main([str(oracle_log), "--datasets", str(tmp_path / "missing")]) == 2
    assert str(tmp_path / "missing") in capsys.readouterr().err


def test_bad_folds_are_named_before_the_log_is_read_and_an_unwritable_record_is_one_line(dataset, oracle_log, tmp_path, capsys):  # noqa: F811
    from pipeline.studies.landing_trust import main

    assert main([str(tmp_path / "no_log"), "--datasets", str(dataset), "--folds", str(tmp_path / "no_folds")]) == 2
    assert "holds 0 fold list(s)" in capsys.readouterr().err
    (tmp_path / "a_file").write_text("")
    assert main([str(oracle_log), "--datasets", str(dataset), "--json", str(tmp_path / "a_file" / "trust.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot write ") and len(err.strip().splitlines()) == 1


def test_a_dataset_whose_poses_lack_the_drop_probabilities_is_refused(dataset, tmp_path):  # noqa: F811
    import shutil

    import pyarrow.parquet as pq

    from schema.reader import CONSOLIDATED

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    poses = copy / CONSOLIDATED["poses"]
    pq.write_table(pq.read_table(poses).drop_columns(["probability"]), poses)
    with pytest.raises(TrustError, match=r"poses.parquet: unreadable: .*probability"):
        object_datasets([copy])
