"""Landings spread onto the most stable poses (docs/MODEL.md C.17): the landing moves, P(topple) never."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.model.config import PRESETS, Config
from pipeline.model.landing_spread import landing_prior, spread_landings
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from tests.test_smoothing import pose_and_candidates  # noqa: F401 (fixture: random_object(3), pose 2, 80 contacts)
from tests.test_validation import model_logs  # noqa: F401 (fixture)

DROP = np.array([0.1, 0.4, 0.3, 0.05, 0.15])


def test_the_prior_is_the_k_most_probable_other_poses_in_proportion():
    prior = landing_prior(DROP, start=1, poses=3)
    # Pose 1 is the start; of the others 2 (0.3), 4 (0.15) and 0 (0.1) are the most probable.
    assert prior == pytest.approx([0.1 / 0.55, 0.0, 0.3 / 0.55, 0.0, 0.15 / 0.55])
    assert landing_prior(DROP, start=2, poses=1) == pytest.approx([0, 1, 0, 0, 0])
    assert landing_prior(DROP, start=0, poses=10) == pytest.approx(np.append(0, DROP[1:] / DROP[1:].sum()))
    # Equal probabilities: the lower index first, whatever the order they come in.
    assert landing_prior(np.array([0.2, 0.2, 0.2, 0.4]), start=3, poses=2) == pytest.approx([0.5, 0.5, 0, 0])
    # Many poses of three probabilities: the k kept are the most probable, the lower indices among equals.
    drop = np.random.default_rng(0).choice([0.1, 0.2, 0.3], size=40)
    top = np.flatnonzero(drop == 0.3)
    top = top[top != 0][:5]
    assert np.flatnonzero(landing_prior(drop, start=0, poses=5)).tolist() == top.tolist()
    # No other pose (or none with a drop probability): nowhere to spread to.
    assert not landing_prior(np.array([1.0]), start=0, poses=3).any()
    assert not landing_prior(np.array([0.0, 1.0]), start=1, poses=3).any()


def test_spreading_moves_landing_mass_only():
    rows = np.array([
        [0.2, 0.8, 0.0, 0.0, 0.0],   # topples onto 0 with 0.2
        [0.0, 1.0, 0.0, 0.0, 0.0],   # never topples
        [np.nan] * 5,                # not ok
        [0.5, 0.3, 0.0, 0.2, 0.0],   # topples 0.7, onto 0 and 3
    ])
    prior = landing_prior(DROP, 1, 3)
    spread = spread_landings(rows, 1, prior, 0.25)
    assert spread[:, 1] == pytest.approx(rows[:, 1], nan_ok=True), "P(topple) is untouched"
    assert spread[[0, 1, 3]].sum(axis=1) == pytest.approx(1.0)
    assert np.array_equal(spread[1], rows[1]) and np.isnan(spread[2]).all()
    # (C.17.2): three quarters of the row's own landing plus a quarter of its P(topple) over the prior.
    expected = 0.75 * np.where(np.arange(5) == 1, 0.0, rows[3]) + 0.25 * 0.7 * prior
    expected[1] = 0.3
    assert spread[3] == pytest.approx(expected)
    assert np.array_equal(spread_landings(rows, 1, prior, 0.0), rows, equal_nan=True)
    assert np.array_equal(spread_landings(rows, 1, np.zeros(5), 0.25), rows, equal_nan=True)
    assert spread_landings(rows, 1, prior, 1.0)[0] == pytest.approx(np.where(np.arange(5) == 1, 0.8, 0.2 * prior))


def test_the_engine_spreads_the_corrected_variant_s_landing(pose_and_candidates):  # noqa: F811
    """Every toppling row, those only the down map makes topple (borrowing their neighbours'
    landing) included; the maps and the spread commute, so the order is not what is tested."""
    obj, pose_set, pose, actions = pose_and_candidates
    base = replace(Config().topple, n_trials=40, boosted_map="")  # C.19 would make every ok row topple a little
    drop = pose_set.probabilities

    def table(t):
        return evaluate_pose(obj, pose, drop, actions, t, stream(3, obj.name, pose.index, "trials"))

    plain = table(base)
    spread = table(replace(base, landing_spread=0.25, landing_spread_poses=2))
    toppling = plain.p_topple > 0
    assert toppling.sum() >= 5 and len(pose_set.poses) >= 3, "the test needs pushes that topple and poses to spread to"
    assert np.array_equal(spread.p_topple, plain.p_topple, equal_nan=True) and np.array_equal(spread.outcomes, plain.outcomes)
    expected = spread_landings(plain.next_pose, pose.index, landing_prior(drop, pose.index, 2), 0.25)
    assert np.allclose(spread.next_pose, expected, equal_nan=True)
    assert not np.array_equal(spread.next_pose[toppling], plain.next_pose[toppling])
    unmapped = table(replace(base, down_map=()))
    born = (np.nan_to_num(unmapped.p_topple) == 0) & toppling
    assert born.sum() >= 3 and np.all(np.abs(spread.next_pose[born] - plain.next_pose[born]).max(axis=1) > 0)
    # The rows are as wide as the pose set: probabilities of another (smaller) set are refused.
    with pytest.raises(ValueError, match="drop_probabilities must be the pose set's"):
        evaluate_pose(obj, pose, drop[:pose.index], actions, base, stream(3, obj.name, pose.index, "trials"))
    # The thesis's variants apply none, whatever the field says.
    thesis = replace(Config.from_toml(PRESETS / "thesis.toml").topple, n_trials=40, landing_spread=0.25)
    assert thesis.applied_landing_spread == 0.0
    assert np.array_equal(table(thesis).next_pose, table(replace(thesis, landing_spread=0.0)).next_pose, equal_nan=True)
    assert np.array_equal(table(base).next_pose, plain.next_pose, equal_nan=True)


def test_the_setting_is_checked_kept_in_manifests_and_left_out_of_what_maps_are_fitted_on():
    configured = Config().with_overrides({"topple.landing_spread": 0.25, "topple.landing_spread_poses": 3})
    assert Config.from_dict(configured.to_dict()) == configured
    assert configured.topple.without_recalibration().landing_spread == 0.0
    assert configured.topple.counted().landing_spread == 0.0
    for key, value in (("topple.landing_spread", 1.5), ("topple.landing_spread", -0.1), ("topple.landing_spread_poses", 0)):
        with pytest.raises(ValueError, match=key.split(".")[1]):
            Config().with_overrides({key: value})


def test_the_scorer_spreads_the_landing_it_predicts(model_logs):  # noqa: F811
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    log = read_log([model_logs / "reported.parquet"])
    config = Config().with_overrides({"seed": 2, "contacts.n_contacts": CANDIDATES_PER_POSE})
    scorer = Scorer(log, seed=2, contacts=config.contacts)
    plain = scorer.predict(config.topple)
    spread = scorer.predict(replace(config.topple, landing_spread=0.3, landing_spread_poses=2))
    moved = 0
    for group, (rows, p), (spread_rows, spread_p) in zip(scorer.groups, plain, spread):
        prior = landing_prior(group.drop_probabilities, group.pose.index, 2)
        expected = spread_landings(rows[:, :-1], group.pose.index, prior, 0.3)
        assert np.allclose(spread_rows[:, :-1], expected) and np.array_equal(spread_p, p)
        moved += int(np.any(~np.isclose(spread_rows, rows)))
    assert moved >= 2, "the test needs groups whose landing moves"


def test_a_build_that_spreads_nothing_keeps_the_shard_identity_it_had_before_the_setting():
    """Off (0, or a thesis variant that ignores it), the spread changes no shard, so it is no part of
    a shard's identity: a dataset built before the setting existed can still be resumed and added to."""
    from pipeline.build.corpus import ObjectSpec
    from pipeline.build.shards import fingerprint, shard_inputs

    spec = ObjectSpec("box", "/nowhere/box.stl", 1.0, 0.2, "list:x", "0" * 64)
    default = shard_inputs(spec, Config())
    assert not {"landing_spread", "landing_spread_poses"} & set(default["config"]["topple"])
    assert shard_inputs(spec, Config().with_overrides({"topple.landing_spread_poses": 5})) == default
    spreading = shard_inputs(spec, Config().with_overrides({"topple.landing_spread": 0.25}))
    assert spreading["config"]["topple"]["landing_spread"] == 0.25 and fingerprint(spreading) != fingerprint(default)
    thesis = Config.from_toml(PRESETS / "thesis.toml")
    assert shard_inputs(spec, thesis.with_overrides({"topple.landing_spread": 0.25})) == shard_inputs(spec, thesis)


def test_the_build_spreads_every_pose_s_landing(pose_and_candidates):  # noqa: F811
    """evaluate_object (what the dataset job runs) hands the pose set's drop probabilities to the engine."""
    from pipeline.model.evaluation import evaluate_object

    obj = pose_and_candidates[0]
    config = Config().with_overrides({"contacts.n_contacts": 40, "topple.n_trials": 20, "suction.n_candidates": 10,
                                      "suction.n_samples": 3})
    plain = evaluate_object(obj, config)
    spread = evaluate_object(obj, config.with_overrides({"topple.landing_spread": 0.25}))
    drop = np.array([p.probability for p in plain.poses])
    moved = 0
    for pose, a, b in zip(plain.poses, plain.topple, spread.topple):
        expected = spread_landings(a.next_pose, pose.index, landing_prior(drop, pose.index, 3), 0.25)
        assert np.allclose(b.next_pose, expected, equal_nan=True) and np.array_equal(a.p_topple, b.p_topple, equal_nan=True)
        moved += int(not np.allclose(a.next_pose, b.next_pose, equal_nan=True))
    assert moved >= 1
