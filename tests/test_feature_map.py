"""The feature map of P(topple) (docs/MODEL.md C.13)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pipeline.model.config import Config, ContactConfig
from pipeline.model.feature_map import (
    FEATURES,
    FeatureMapError,
    check_weights,
    fit_weights,
    landing_rows,
    logit,
    map_rows,
    mapped_probability,
    push_features,
)
from pipeline.model.outcomes import Actions
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.neighbourhood import neighbour_mean
from schema.vocabulary import STATUS_OK
from tests.test_smoothing import pose_and_candidates  # noqa: F401 (fixture: random_object(3), pose 2, 80 contacts)
from tests.test_validation import model_logs  # noqa: F401 (fixture)

X = np.array([1.0, 0.0, 0.0])
IDENTITY = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0)
"""q = sigmoid(logit P): P itself wherever P is inside the logit's clip."""


def _rows(p_leave, landing_pose=1, n_poses=3, start=0):
    """Rows leaving ``start`` with probability p_leave, all to ``landing_pose``."""
    rows = np.zeros((len(p_leave), n_poses))
    rows[:, start] = 1.0 - np.asarray(p_leave)
    rows[:, landing_pose] = p_leave
    return rows


def test_the_identity_weights_give_p_back_and_rows_stay_distributions():
    points = np.array([[0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]], dtype=float)
    directions = np.array([X, X, X])
    rows = _rows([0.3, 0.6, 0.9])
    rows[1] = [0.4, 0.3, 0.3]  # a push that lands in two poses
    mapped, p = map_rows(rows, 0, points, directions, np.array([2.0, 3.0, 4.0]), 2.5, IDENTITY)
    assert np.allclose(mapped, rows) and np.allclose(p, [0.3, 0.6, 0.9])
    doubled, p2 = map_rows(rows, 0, points, directions, np.array([2.0, 3.0, 4.0]), 2.5, (np.log(4.0), 1.0, 0, 0, 0, 0))
    assert np.all(p2 > [0.3, 0.6, 0.9]) and np.allclose(doubled.sum(axis=1), 1.0)
    # The landing is kept in proportion: push 1 still splits its topples evenly between poses 1 and 2.
    assert doubled[1, 1] == pytest.approx(doubled[1, 2]) and doubled[1, 0] == pytest.approx(1 - p2[1])


def test_a_push_that_never_toppled_lands_where_its_neighbours_do_else_where_the_pose_does():
    points = np.array([[0, 0, 0], [0.01, 0, 0], [0.2, 0, 0], [0.4, 0, 0]], dtype=float)
    directions = np.array([X, X, X, X])
    rows = np.array([[0.5, 0.0, 0.5], [1.0, 0, 0], [0.8, 0.2, 0.0], [1.0, 0, 0]])
    landing = landing_rows(rows, 0, points, directions)
    assert np.allclose(landing[0], [0, 0, 1]), "its own landing"
    assert np.allclose(landing[1], [0, 0, 1]), "its neighbour's (push 0, 1 cm away)"
    assert np.allclose(landing[3], [0, 2 / 7, 5 / 7]), "no neighbour toppled: where the pose's topples land"
    # Its own landing wins over a neighbour that lands elsewhere.
    pair = landing_rows(np.array([[0.5, 0.5, 0.0], [0.5, 0.0, 0.5]]), 0, points[:2], directions[:2])
    assert np.allclose(pair, [[0, 1, 0], [0, 0, 1]])
    weights = (-2.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # q = sigmoid(-2) for every push
    mapped, p = map_rows(rows, 0, points, directions, np.array([1.0, np.nan, 1.0, np.nan]), 1.0, weights)
    q = 1 / (1 + np.exp(2.0))
    assert np.allclose(p, q) and np.allclose(mapped[1], [1 - q, 0, q]) and np.allclose(mapped.sum(axis=1), 1.0)


def test_a_pose_nothing_leaves_keeps_its_rows_and_rows_that_are_not_ok_stay_nan():
    points, directions = np.zeros((3, 3)), np.array([X, X, X])
    rows = _rows([0.0, 0.0, 0.0])
    rows[2] = np.nan
    mapped, p = map_rows(rows, 0, points, directions, np.full(3, np.nan), 1.0, (3.0, 0, 0, 0, 0, 0))
    assert np.array_equal(mapped[:2], rows[:2]) and np.all(p[:2] == 0), "nowhere to land: no topple"
    assert np.all(np.isnan(mapped[2])) and np.isnan(p[2])


def test_features_follow_their_definitions():
    directions = np.array([X, [0, 0, -1.0], [0, 0.6, 0.8]])
    f = push_features(np.array([0.0, 0.5, np.nan]), np.array([0.25, 0.5, 0.1]), np.array([np.nan, 4.9, 1.0]), 2.45, directions)
    assert list(f[0]) == pytest.approx([1, logit(0.0), logit(0.25), 0.0, 1.0, 0.0])
    assert list(f[1]) == pytest.approx([1, 0.0, 0.0, np.log(2.0), 0.0, -1.0])
    assert np.all(np.isnan(f[2])), "an action that is not ok has no features"
    assert f.shape[1] == len(FEATURES)


def test_fit_weights_recovers_the_weights_that_made_the_outcomes():
    rng = np.random.default_rng(0)
    n = 20000
    features = np.column_stack([np.ones(n), rng.normal(0, 2, n), rng.normal(0, 2, n), rng.normal(0, 1, n),
                                rng.integers(0, 2, n), rng.uniform(-1, 1, n)])
    truth = np.array([-0.5, 0.4, 0.8, -0.3, 0.6, 1.0])
    repeats = np.full(n, 10.0)
    observed = rng.binomial(10, mapped_probability(features, truth)) / 10
    fitted = fit_weights(features, observed, repeats)
    assert np.allclose(fitted, truth, atol=0.06)


def test_the_bias_is_not_shrunk_and_a_probe_lends_no_landing_to_the_pose():
    rng = np.random.default_rng(1)
    features = np.column_stack([np.ones(400), np.zeros((400, len(FEATURES) - 1))])
    observed = rng.uniform(0.8, 1.0, 400)
    fitted = fit_weights(features, observed, np.full(400, 10.0))
    assert fitted[0] == pytest.approx(logit(observed.mean()), abs=1e-8), "the bias alone fits the mean rate exactly"
    # Candidates 0 and 1 never topple; probe 2 (far from both) does: candidate 1 has nowhere to land.
    points = np.array([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]], dtype=float)
    rows = np.array([[1.0, 0, 0], [1.0, 0, 0], [0.5, 0.5, 0]])
    landing = landing_rows(rows, 0, points, np.array([X, X, X]), pool=2)
    assert np.all(landing[:2] == 0) and np.allclose(landing[2], [0, 1, 0])


def test_bad_weights_are_refused_with_the_field_named():
    check_weights(())
    with pytest.raises(FeatureMapError, match="topple.feature_map needs 6 finite weights"):
        check_weights((1.0, 2.0))
    with pytest.raises(ValueError, match="feature_map"):
        Config().with_overrides({"topple.feature_map": "1,2,3"})
    with pytest.raises(ValueError, match="two maps"):
        Config().with_overrides({"topple.feature_map": "0,1,0,0,0,0", "topple.recalibration_x": "0,1",
                                 "topple.recalibration_y": "0,1"})
    with pytest.raises(ValueError, match="recalibration_x= --set topple.recalibration_y="):
        Config().with_overrides({"topple.feature_map": "0,1,0,0,0,0"})  # the defaults carry a map
    emptied = Config().with_overrides({"topple.feature_map": "0,1,0,0,0,0", "topple.recalibration_x": "",
                                       "topple.recalibration_y": ""}).topple
    assert emptied.applied_feature_map == IDENTITY and emptied.applied_recalibration == ((), ())
    topple = replace(Config().topple.without_recalibration(), feature_map=IDENTITY)
    assert topple.applied_feature_map == IDENTITY and topple.needs_candidates
    assert replace(topple, variant="robust").applied_feature_map == ()
    assert topple.without_recalibration().feature_map == () and topple.counted().feature_map == ()


def test_the_engine_maps_the_smoothed_rows_with_the_pushes_own_features(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    topple = replace(Config().topple.without_recalibration(), n_trials=40)
    weights = (-0.4, 0.5, 0.6, -0.2, -1.0, 0.7)

    def table(t):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"))

    plain, mapped = table(topple), table(replace(topple, feature_map=weights))
    ok = actions.status == STATUS_OK
    p = plain.p_topple
    assert (p[ok] > 0).any()
    near, _ = neighbour_mean(actions.points, actions.directions, p)
    f = push_features(p, near, plain.mean_force, obj.mass * topple.gravity, actions.directions)
    q = mapped_probability(f, weights)
    assert np.allclose(mapped.p_topple[ok], q[ok]), "this pose has topples, so every ok push has somewhere to land"
    assert np.allclose(mapped.next_pose[ok].sum(axis=1), 1.0) and np.all(np.isnan(mapped.next_pose[~ok]))
    assert np.array_equal(mapped.outcomes, plain.outcomes)


def test_probes_are_mapped_over_the_candidates_and_leave_their_rows(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, pool = pose_and_candidates
    topple = replace(Config().topple.without_recalibration(), n_trials=40, feature_map=(-0.4, 0.5, 0.6, -0.2, -1.0, 0.7))
    ok = np.flatnonzero(pool.status == STATUS_OK)
    n = len(pool.status)
    counted = evaluate_pose(obj, pose, pose_set.probabilities, pool, topple.counted(), stream(3, obj.name, pose.index, "trials"))
    best = ok[np.argmax(counted.p_topple[ok])]
    probes = [best, best]  # the likeliest push asked about twice: two probes, each other's neighbours but for the pool
    asked = Actions(points=np.vstack([pool.points, pool.points[probes]]), normals=np.vstack([pool.normals, pool.normals[probes]]),
                    directions=np.vstack([pool.directions, pool.directions[probes]]),
                    status=np.concatenate([pool.status, pool.status[probes]]).astype(pool.status.dtype), max_height=pool.max_height)

    def table(actions, t, candidates=None):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"), candidates=candidates)

    alone, probed = table(pool, topple), table(asked, topple, candidates=n)
    assert np.array_equal(probed.next_pose[:n], alone.next_pose, equal_nan=True), "probes change no candidate's row"
    raw = table(asked, topple.without_recalibration(), candidates=n)
    near, _ = neighbour_mean(asked.points, asked.directions, raw.p_topple, pool=n)
    q = mapped_probability(push_features(raw.p_topple, near, raw.mean_force, obj.mass * topple.gravity, asked.directions),
                           topple.feature_map)
    assert np.allclose(probed.p_topple[n:], q[n:]), "a probe's neighbourhood is the candidates and itself"
    everyone, _ = neighbour_mean(asked.points, asked.directions, raw.p_topple)
    assert not np.allclose(near[n:], everyone[n:]), "the test needs probes whose pool matters"


def test_folds_keep_an_object_in_one_fold_across_logs():
    from pipeline.studies.recalibrate import push_folds

    names = ["a", "b", "c", "a", "d", "e", "f", "b", "a"]  # two logs' pushes, one list
    fold_objects, fold_of = push_folds(names, 3, 0)
    for name in set(names):
        assert len({int(fold_of[i]) for i, n in enumerate(names) if n == name}) == 1
    assert sorted(sum(fold_objects, [])) == sorted(set(names))


def test_the_scorer_gives_features_of_logged_candidates_and_the_fit_is_written(model_logs, tmp_path):  # noqa: F811
    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    contacts = ContactConfig(n_contacts=CANDIDATES_PER_POSE)
    topple = Config().topple.without_recalibration()
    scorer = Scorer(log, seed=2, contacts=contacts)  # the log's pushes are candidates of seed 2
    features, p = scorer.features(replace(topple, feature_map=IDENTITY))
    assert np.allclose(p, scorer.score(topple).p_topple), "features come from the model with no map"
    assert np.all(np.isfinite(features)) and np.allclose(features[:, 1], logit(p))
    # A logged push that is a candidate is scored as the dataset's row of it: with a map too.
    weights = (-0.4, 0.5, 0.6, -0.2, -1.0, 0.7)
    mapped = replace(topple, feature_map=weights)
    predictions = scorer.predict(mapped)
    for group, (_, p_topple) in zip(scorer.groups, predictions):
        pool = scorer.pose_candidates(group)
        obj = log.objects[group.object_id].model
        table = evaluate_pose(obj, group.pose, group.drop_probabilities, pool.actions, mapped, stream(2, obj.name, group.pose.index, "trials"))
        assert np.allclose(p_topple, table.p_topple[pool.index])
    out, record = tmp_path / "fm.toml", tmp_path / "fm.json"
    code = main([str(path), str(path), "--features", "--corpus", "none", "--folds", "3", "--set", "contacts.n_contacts="
                 f"{CANDIDATES_PER_POSE}", "--seed", "2", "--set", "seed=2", "--out", str(out), "--json", str(record)])
    assert code == 0
    result = json.loads(record.read_text())
    written = Config.from_toml(out).topple
    assert list(written.feature_map) == result["weights"] and written.smoothing_radius == topple.smoothing_radius
    assert result["pushes"] == 2 * len(log.pushes), "each log read on its own, both used"
    twice = np.vstack([features, features])
    assert np.allclose(result["weights"], fit_weights(twice, np.tile(scorer.empirical_topple, 2), np.tile(scorer.repeats, 2)))


# ---------------------------------------------------------------- mutation-testing gaps (stop 71)


def test_the_maps_logit_is_clipped_at_its_own_floor():
    from pipeline.model.feature_map import LOGIT_FLOOR

    assert logit(np.array([0.0, 1.0])) == pytest.approx(np.log(LOGIT_FLOOR / (1 - LOGIT_FLOOR)) * np.array([1.0, -1.0]))


def test_pose_features_take_n_over_the_neighbourhoods_limits():
    from pipeline.model.feature_map import pose_features
    from schema.neighbourhood import RADIUS

    # Pushes 0 and 1 within RADIUS of each other, push 2 five radii away: its N is its own P.
    points = np.array([[0, 0, 0], [0.5 * RADIUS, 0, 0], [5.5 * RADIUS, 0, 0]])
    p = np.array([0.2, 0.4, 0.9])
    f = pose_features(p, points, np.array([X, X, X]), np.full(3, np.nan), 1.0)
    assert np.allclose(f[:, 2], logit(np.array([0.3, 0.3, 0.9])))
    assert np.allclose(pose_features(p, points, np.array([X, X, X]), np.full(3, np.nan), 1.0, rows=np.array([2, 0])), f[[2, 0]])


def test_no_weights_give_the_rows_back_bit_for_bit():
    rows = _rows([0.9, 0.3])  # 1 - (1 - 0.1) is not 0.1 in floats
    mapped, p = map_rows(rows, 0, np.zeros((2, 3)), np.array([X, X]), np.full(2, np.nan), 1.0, ())
    assert np.array_equal(mapped, rows) and np.array_equal(p, 1 - rows[:, 0])


def test_map_rows_takes_n_over_the_pool_when_given_no_neighbours():
    # Candidates 0 and 1 far apart; probes 2 and 3 within a centimetre of each other, past the pool.
    points = np.array([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [0.605, 0, 0]])
    rows = _rows([0.2, 0.4, 0.6, 0.8])
    n_only = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # q = N
    _, pooled = map_rows(rows, 0, points, np.array([X] * 4), np.full(4, np.nan), 1.0, n_only, pool=2)
    _, everyone = map_rows(rows, 0, points, np.array([X] * 4), np.full(4, np.nan), 1.0, n_only)
    assert np.allclose(pooled, [0.2, 0.4, 0.6, 0.8]), "a probe's neighbourhood is the pool and itself"
    assert np.allclose(everyone[2:], 0.7)


def test_a_pool_with_no_ok_push_lends_no_landing_and_warns_of_nothing():
    import warnings

    rows = np.array([[np.nan] * 3, [0.5, 0.5, 0.0]])  # the one candidate is not ok; the probe topples
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mapped, p = map_rows(rows, 0, np.array([[0, 0, 0], [0.3, 0, 0]]), np.array([X, X]), np.full(2, np.nan), 1.0,
                             IDENTITY, pool=1)
        landing = landing_rows(np.array([[np.nan] * 3, [1.0, 0, 0]]), 0, np.zeros((2, 3)), np.array([X, X]), pool=1)
    assert np.all(np.isnan(mapped[0])) and np.allclose(mapped[1], [0.5, 0.5, 0.0]) and p[1] == pytest.approx(0.5)
    assert np.all(np.isnan(landing[0])) and np.array_equal(landing[1], [0.0, 0.0, 0.0])


def test_fitted_weights_are_where_the_ridged_likelihood_is_flat():
    """The gradient of the binomial log-likelihood less RIDGE x total weight x |w|^2 / 2 (the bias
    unpenalised) vanishes at the fit, here where the feature separates the pushes and only the ridge
    keeps its weight finite."""
    from pipeline.model.feature_map import RIDGE

    x = np.linspace(-1, 1, 10)
    features = np.column_stack([np.ones(10), x, x**2, np.zeros((10, 3))])
    observed, repeats = (x > 0).astype(float), np.arange(1.0, 11.0)
    w = fit_weights(features, observed, repeats)
    q = mapped_probability(features, w)
    penalty = RIDGE * repeats.sum() * np.r_[0.0, np.ones(5)]
    gradient = features.T @ (repeats * (observed - q)) - penalty * w
    assert np.all(np.isfinite(w)) and np.max(np.abs(gradient)) < 1e-8
    assert 5 < w[1] < 100, "finite, yet large: the ridge is small"
