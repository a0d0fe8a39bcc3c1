"""The validation report's metrics held to independent implementations, analytic cases and invariants.

Every headline number of README.md and docs/VALIDATION.md (Brier score, sup-TV, AP, ECE, the trivial
predictors, the bootstrap intervals over objects and the paired differences) comes from the functions
tested here.  The expected values are computed here another way (scikit-learn, loops, exact
enumeration, the metric of each resampled set of objects), never copied from the code's output.
"""

import math
from dataclasses import replace
from itertools import product
from math import comb
from types import SimpleNamespace

import numpy as np
import pytest
from sklearn.metrics import average_precision_score

from pipeline.model.outcomes import StablePose
from pipeline.studies.scoring import Group, Scorer, Scores, brier_floor, brier_score, sup_tv, topple_spread
from pipeline.studies.validation import (
    BOOTSTRAP,
    CONFIDENCE,
    RELIABILITY_BINS,
    TOPPLES,
    average_precision,
    bootstrap_difference,
    bootstrap_intervals,
    bootstrap_metric_difference,
    by_direction,
    direction_classes,
    expected_calibration_error,
    informative,
    observed_topple_rate,
    per_object,
    percentile_interval,
    predictor_summary,
    push_metrics,
    ranking_by_direction,
    reliability,
)

# ---------------------------------------------------------------- average precision


def test_average_precision_is_scikit_learns_on_random_scores_with_ties_and_on_0_1_scores():
    rng = np.random.default_rng(7)
    for trial in range(120):
        n = int(rng.integers(1, 40))
        labels = rng.random(n) < rng.uniform(0.05, 0.95)
        if not labels.any():
            labels[rng.integers(n)] = True
        levels = int(rng.integers(1, 6))  # few levels: many ties
        tied = rng.integers(0, levels, n) / max(levels - 1, 1)
        for scores in (tied, rng.integers(0, 2, n).astype(float), rng.random(n)):
            assert average_precision(scores, labels) == pytest.approx(average_precision_score(labels, scores), abs=1e-12), (trial, scores, labels)
    # Order inside a tie is never credited: permuting the pushes changes nothing.
    scores, labels = np.array([1.0, 1.0, 0.0, 0.0, 1.0]), np.array([False, True, True, False, True])
    for perm in (np.arange(5), np.arange(5)[::-1], np.array([2, 0, 4, 1, 3])):
        assert average_precision(scores[perm], labels[perm]) == pytest.approx(average_precision_score(labels, scores))


def test_average_precision_edge_cases():
    assert average_precision([0.3], [True]) == 1.0
    assert average_precision([0.3, 0.2], [False, True]) == pytest.approx(0.5)
    assert math.isnan(average_precision([0.3, 0.2], [False, False]))
    # Lists and integer labels are read as arrays of floats and bools.
    assert average_precision([2, 1, 0], [0, 1, 1]) == pytest.approx(average_precision_score([0, 1, 1], [2, 1, 0]))
    # A negative score ranks below zero (no rounding into the zero tie).
    assert average_precision([-0.5, 0.0], [True, False]) == pytest.approx(0.5)


# ---------------------------------------------------------------- reliability and ECE


def _ece_by_loops(predicted, observed, n_bins):
    """ECE from its definition, bin by bin: [b / n, (b + 1) / n), the last bin closed at 1."""
    total = 0.0
    for b in range(n_bins):
        low, high = b / n_bins, (b + 1) / n_bins
        inside = [i for i, p in enumerate(predicted) if low <= p < high or (b == n_bins - 1 and p == 1.0)]
        if inside:
            gap = abs(np.mean([predicted[i] for i in inside]) - np.mean([observed[i] for i in inside]))
            total += len(inside) * gap
    return total / len(predicted)


def test_ece_of_hand_made_bins_with_predictions_of_exactly_0_and_1():
    # Bin 0 holds the exact zeros and 0.04; the last bin 0.95 and the exact ones.
    predicted = np.array([0.0, 0.0, 0.04, 0.5, 0.95, 1.0, 1.0])
    observed = np.array([0.0, 0.2, 0.1, 0.5, 0.6, 1.0, 0.8])
    result = reliability(predicted, observed, n_bins=10)
    counts = [b["count"] for b in result["bins"]]
    assert counts == [3, 0, 0, 0, 0, 1, 0, 0, 0, 3]
    first, last = result["bins"][0], result["bins"][-1]
    assert first["low"] == 0.0 and first["high"] == pytest.approx(0.1) and last["high"] == 1.0
    assert first["predicted"] == pytest.approx(0.04 / 3) and first["observed"] == pytest.approx(0.1)
    assert last["predicted"] == pytest.approx(2.95 / 3) and last["observed"] == pytest.approx(0.8)
    # |0.04/3 - 0.3/3| * 3 + |0.5 - 0.5| * 1 + |2.95/3 - 2.4/3| * 3, over 7 pushes
    expected = (abs(0.04 - 0.3) + 0.0 + abs(2.95 - 2.4)) / 7
    assert result["ece"] == pytest.approx(expected)
    assert expected_calibration_error(predicted, observed) == pytest.approx(expected)
    # All at 0 and all at 1: one bin each, the gap to what was observed.
    assert expected_calibration_error(np.zeros(3), np.array([0.0, 0.3, 0.6])) == pytest.approx(0.3)
    assert expected_calibration_error(np.ones(2), np.array([0.5, 1.0])) == pytest.approx(0.25)
    assert reliability(np.ones(2), np.array([0.5, 1.0]))["bins"][-1]["count"] == 2
    # Empty: no pushes, no ECE.
    assert math.isnan(reliability(np.array([]), np.array([]))["ece"])


def test_ece_is_its_definition_bin_by_bin_on_random_predictions():
    rng = np.random.default_rng(3)
    for _ in range(50):
        n = int(rng.integers(1, 30))
        predicted = np.where(rng.random(n) < 0.2, rng.integers(0, 2, n).astype(float), rng.random(n))
        observed = rng.random(n)
        for n_bins in (1, 4, RELIABILITY_BINS):
            assert expected_calibration_error(predicted, observed, n_bins) == pytest.approx(
                _ece_by_loops(predicted, observed, n_bins), abs=1e-12)
        bins = reliability(predicted, observed)["bins"]
        assert [b["low"] for b in bins] == pytest.approx(np.arange(RELIABILITY_BINS) / RELIABILITY_BINS)
        assert sum(b["count"] for b in bins) == n


# ---------------------------------------------------------------- Brier score and its floor


def test_brier_score_of_a_distribution_against_itself_and_the_floor():
    """A distribution against itself scores 0; against the outcomes of R repeats its expectation is
    the floor's, and a replay of R' repeats drawn from the same distribution expects the floor times
    1 + R / R' (two samples' noise), exactly, over every way the repeats can fall."""
    p = np.array([0.5, 0.3, 0.2, 0.0])
    assert brier_score(p[None], p[None])[0] == 0.0
    assert brier_score(np.eye(4)[:1], np.eye(4)[1:2])[0] == 2.0  # the largest: all mass moved

    def outcomes(repeats):
        """(probability, frequencies) of every way ``repeats`` draws from p can fall."""
        out = []
        for counts in product(range(repeats + 1), repeat=len(p)):
            if sum(counts) == repeats:
                ways, left = 1, repeats
                for c in counts:
                    ways, left = ways * comb(left, c), left - c
                out.append((ways * np.prod(p ** np.array(counts)), np.array(counts) / repeats))
        return out

    log, replay = outcomes(4), outcomes(2)
    assert sum(w for w, _ in log) == pytest.approx(1.0)
    floor = sum(w * brier_floor(e[None], np.array([4]))[0] for w, e in log)
    true_score = sum(w * brier_score(p[None], e[None])[0] for w, e in log)
    replay_score = sum(w * v * brier_score(f[None], e[None])[0] for w, e in log for v, f in replay)
    assert floor == pytest.approx((p * (1 - p)).sum() / 4)
    assert true_score == pytest.approx(floor)
    assert replay_score == pytest.approx(floor * (1 + 4 / 2))
    # The floor per push: sum e (1 - e) / (R - 1); NaN for one repeat, 0 for repeats that agree.
    e = np.array([[0.5, 0.5, 0.0], [1.0, 0.0, 0.0], [0.25, 0.25, 0.5], [1.0, 0.0, 0.0]])
    floors = brier_floor(e, np.array([2, 3, 4, 1]))
    np.testing.assert_allclose(floors[:3], [0.5 / 1, 0.0, (0.1875 * 2 + 0.25) / 3])
    assert math.isnan(floors[3])
    assert brier_floor(e[:1], [2.0])[0] == pytest.approx(0.5)  # repeats as a list of floats


def test_brier_score_rows_and_broadcast():
    predicted = np.array([[0.6, 0.4, 0.0]])
    empirical = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, 0.5], [0.6, 0.4, 0.0]])
    expected = [sum((a - b) ** 2 for a, b in zip(predicted[0], row)) for row in empirical]
    np.testing.assert_allclose(brier_score(predicted, empirical), expected)
    np.testing.assert_allclose(brier_score(np.repeat(predicted, 3, axis=0), empirical), expected)


# ---------------------------------------------------------------- sup-TV


def test_sup_tv_is_a_metric_in_0_1_the_largest_bucket_gap_and_at_most_the_event_total_variation():
    """sup-TV (docs/VALIDATION.md: max over next poses, plus the outside bucket, of |P_model - P_observed|):
    symmetric, in [0, 1], 0 only for equal rows, the triangle inequality; at most the total variation
    over events (half the L1 distance), and equal to it for two buckets."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        b = int(rng.integers(2, 7))
        p, q, r = (rng.dirichlet(np.full(b, 0.5), size=3) for _ in range(3))
        by_loop = [max(abs(p[i, j] - q[i, j]) for j in range(b)) for i in range(3)]
        np.testing.assert_allclose(sup_tv(p, q), by_loop, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(sup_tv(p, q), sup_tv(q, p))
        assert np.all(sup_tv(p, q) >= 0) and np.all(sup_tv(p, q) <= 1)
        assert np.all(sup_tv(p, r) <= sup_tv(p, q) + sup_tv(q, r) + 1e-15)
        assert np.all(sup_tv(p, p) == 0)
        events = 0.5 * np.abs(p - q).sum(axis=1)  # sup over events A of |P(A) - Q(A)|
        assert np.all(sup_tv(p, q) <= events + 1e-15)
        if b == 2:
            np.testing.assert_allclose(sup_tv(p, q), events, atol=1e-15)
    # The extremes: all mass moved is 1, whatever the number of buckets.
    assert sup_tv(np.eye(5)[:1], np.eye(5)[3:4])[0] == 1.0
    # A (1, B) prediction is scored against every row.
    np.testing.assert_allclose(sup_tv(np.array([[0.5, 0.5, 0.0]]), np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])), [0.5, 1.0])


# ---------------------------------------------------------------- informative pushes and push_metrics


def test_informative_is_either_says_it_topples():
    np.testing.assert_array_equal(informative([0.0, 0.1, 0.0, 0.2, 0.0], [0.0, 0.0, 0.4, 0.3, 1e-9]),
                                  [False, True, True, True, True])


def test_push_metrics_by_their_definitions():
    rng = np.random.default_rng(5)
    n = 40
    objects = rng.integers(0, 4, n)
    tv, brier = rng.random(n), 2 * rng.random(n)
    predicted = np.where(rng.random(n) < 0.3, 0.0, rng.random(n))
    observed = np.where(rng.random(n) < 0.3, 0.0, rng.integers(0, 5, n) / 4)
    observed[objects == 3] = 0.0  # an object without a topple has no AP, and no part in mAP
    m = push_metrics(tv, predicted, observed, objects, brier)
    useful = [i for i in range(n) if predicted[i] > 0 or observed[i] > 0]
    labels = observed > TOPPLES
    assert m["tv_all"] == pytest.approx(tv.mean())
    assert m["tv_informative"] == pytest.approx(tv[useful].mean())
    assert m["informative"] == pytest.approx(len(useful) / n)
    assert m["ap"] == pytest.approx(average_precision_score(labels, predicted))
    per_object_ap = [average_precision_score(labels[objects == g], predicted[objects == g]) for g in range(3)]
    assert m["map"] == pytest.approx(np.mean(per_object_ap))
    assert m["ece"] == pytest.approx(_ece_by_loops(predicted, observed, RELIABILITY_BINS))
    assert m["brier"] == pytest.approx(brier.mean())
    assert "brier" not in push_metrics(tv, predicted, observed, objects)
    # A push that toppled in exactly half its repeats is not labelled "topples".
    half = push_metrics(np.zeros(2), np.array([0.9, 0.1]), np.array([0.5, 0.75]), np.zeros(2, int))
    assert half["ap"] == pytest.approx(0.5)
    # Nothing informative, nothing at all.
    none = push_metrics(np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2, int), np.zeros(2))
    assert math.isnan(none["tv_informative"]) and none["informative"] == 0.0 and math.isnan(none["map"])
    empty = push_metrics(np.array([]), np.array([]), np.array([]), np.array([], int), np.array([]))
    assert all(math.isnan(empty[k]) for k in ("tv_all", "tv_informative", "informative", "ap", "map", "ece", "brier"))


# ---------------------------------------------------------------- the bootstrap over objects


def _objects_data(rng, k=7):
    """Pushes on ``k`` objects of unequal push counts, one object that never topples."""
    counts = rng.integers(1, 9, k)
    objects = np.repeat(rng.permutation(np.arange(10, 10 + 3 * k, 3)), counts)  # ids neither 0.. nor sorted
    n = len(objects)
    predicted = np.where(rng.random(n) < 0.3, 0.0, rng.random(n))
    observed = np.where(rng.random(n) < 0.3, 0.0, rng.integers(0, 5, n) / 4)
    # The reliability bins at both ends miscalibrated in turn (observed 1 in bins 0 and 8, 0 in bins 1
    # and 9), so that joining two neighbouring bins changes the ECE.
    which = np.clip((predicted * RELIABILITY_BINS).astype(int), 0, RELIABILITY_BINS - 1)
    observed = np.where(np.isin(which, (0, 8)), 1.0, np.where(np.isin(which, (1, 9)), 0.0, observed))
    observed[objects == objects[0]] = 0.0
    return rng.random(n), predicted, observed, objects, 2 * rng.random(n)


def _resampled(objects, n_resamples, seed):
    """Each resample's pushes and the copy each belongs to, drawn as the bootstrap draws objects:
    k of the sorted object ids with replacement, one ``integers(k, size=k)`` per resample."""
    rng = np.random.default_rng(seed)
    names = np.unique(objects)
    rows = [np.flatnonzero(objects == name) for name in names]
    for _ in range(n_resamples):
        draw = rng.integers(len(names), size=len(names))
        yield np.concatenate([rows[d] for d in draw]), np.repeat(np.arange(len(draw)), [len(rows[d]) for d in draw])


def test_bootstrap_intervals_are_the_percentiles_of_the_metrics_of_resampled_objects():
    """Every interval is that of ``push_metrics`` recomputed on resampled *objects* (each drawn copy its
    own object), not on resampled pushes."""
    rng = np.random.default_rng(1)
    tv, predicted, observed, objects, brier = _objects_data(rng)
    n_resamples = 60
    ci = bootstrap_intervals(tv, predicted, observed, objects, n_resamples, seed=4, brier=brier)
    draws = [push_metrics(tv[i], predicted[i], observed[i], copies, brier[i]) for i, copies in _resampled(objects, n_resamples, 4)]
    assert set(ci) == set(draws[0])
    for key in ci:
        values = np.array([d[key] for d in draws])
        values = values[~np.isnan(values)]
        expected = np.percentile(values, [2.5, 97.5]) if len(values) > n_resamples // 2 else [math.nan, math.nan]
        np.testing.assert_allclose(ci[key], expected, rtol=0, atol=1e-12, err_msg=key)
    assert "brier" not in bootstrap_intervals(tv, predicted, observed, objects, 5)
    # Another confidence is another pair of percentiles.
    narrow = bootstrap_intervals(tv, predicted, observed, objects, n_resamples, seed=4, confidence=0.5)
    tv_draws = [d["tv_all"] for d in draws]
    np.testing.assert_allclose(narrow["tv_all"], np.percentile(tv_draws, [25, 75]), atol=1e-12)


def test_bootstrap_over_objects_keeps_an_object_whole():
    """One object with many pushes at TV 1, nine with one push at 0: a draw holds the big object's
    pushes all or none, so the lowest draws are 0 (it was not drawn) and the highest far above what
    resampling pushes would give."""
    tv = np.r_[np.ones(90), np.zeros(9)]
    objects = np.r_[np.zeros(90, int), np.arange(1, 10)]
    predicted = observed = np.zeros(len(tv))
    ci = bootstrap_intervals(tv, predicted, observed, objects, 400, seed=0)
    assert ci["tv_all"][0] == 0.0  # 0.9 ** 10 of the draws leave the big object out
    assert ci["tv_all"][1] > 0.95  # several copies of it (the pushes' own bootstrap: 0.96 at most)
    # A draw's mean is that of whole objects: 90 m / (90 m + 10 - m) for m copies of the big one.
    possible = {0.0} | {90 * m / (90 * m + 10 - m) for m in range(1, 11)}
    assert min(abs(ci["tv_all"][1] - v) for v in possible) < 1e-12


def test_bootstrap_interval_covers_the_true_mean_as_often_as_it_claims():
    """Objects whose pushes share most of their TV (object level ~ N(0.3, 0.1), push noise 0.02): the
    95 % interval over objects covers the true mean 0.3 in about 95 % of datasets; resampling the
    pushes would cover it in about half."""
    rng = np.random.default_rng(2024)
    k, pushes, datasets = 30, 8, 120
    covered = 0
    for d in range(datasets):
        objects = np.repeat(np.arange(k), pushes)
        tv = rng.normal(0.3, 0.1, k)[objects] + rng.normal(0.0, 0.02, len(objects))
        zero = np.zeros(len(tv))
        low, high = bootstrap_intervals(tv, zero, zero, objects, 200, seed=d)["tv_all"]
        covered += low <= 0.3 <= high
    assert 0.86 <= covered / datasets <= 1.0


def test_bootstrap_is_determined_by_its_seed():
    rng = np.random.default_rng(9)
    tv, predicted, observed, objects, brier = _objects_data(rng)
    one = bootstrap_intervals(tv, predicted, observed, objects, 50, seed=3, brier=brier)
    assert bootstrap_intervals(tv, predicted, observed, objects, 50, seed=3, brier=brier) == one
    assert bootstrap_intervals(tv, predicted, observed, objects, 50, seed=8, brier=brier)["tv_all"] != one["tv_all"]
    first, second = Scores(tv, predicted, brier), Scores(tv[::-1].copy(), predicted[::-1].copy(), brier[::-1].copy())
    for paired in (bootstrap_difference, bootstrap_metric_difference):
        a = paired(first, second, observed, objects, 40, seed=3)
        assert paired(first, second, observed, objects, 40, seed=3) == a
        assert paired(first, second, observed, objects, 40, seed=8)["tv_all"]["ci"] != a["tv_all"]["ci"]
    # The default: BOOTSTRAP resamples at CONFIDENCE, seed 0.
    assert bootstrap_intervals(tv, predicted, observed, objects) == bootstrap_intervals(tv, predicted, observed, objects, BOOTSTRAP, 0, CONFIDENCE)
    for paired in (bootstrap_difference, bootstrap_metric_difference):
        assert paired(first, second, observed, objects, 40) == paired(first, second, observed, objects, 40, 0, CONFIDENCE)


def test_percentile_interval_drops_nan_and_needs_enough_draws():
    values = [3.0, math.nan, 1.0, 2.0, 4.0, math.nan]
    assert percentile_interval(values, 0.5) == pytest.approx(np.percentile([1, 2, 3, 4], [25, 75]).tolist())
    assert percentile_interval(values) == pytest.approx(np.percentile([1, 2, 3, 4], [2.5, 97.5]).tolist())
    assert percentile_interval(values, 0.5, fewest=4) == pytest.approx([1.75, 3.25])
    assert all(math.isnan(v) for v in percentile_interval(values, 0.5, fewest=5))
    assert all(math.isnan(v) for v in percentile_interval([math.nan, math.nan]))
    assert all(math.isnan(v) for v in percentile_interval([], fewest=0))
    assert percentile_interval([2.0], fewest=0) == [2.0, 2.0]
    assert percentile_interval([2.0]) == [2.0, 2.0]  # one draw is enough by default


def test_a_metric_defined_in_at_most_half_the_resamples_gets_no_interval():
    """Pooled AP is defined in a resample only when it draws the one object with a topple: with 4
    resamples, 3 defined give an interval, 2 do not (more than half are needed)."""
    objects = np.repeat(np.arange(3), 2)
    predicted = np.array([0.9, 0.2, 0.4, 0.1, 0.3, 0.6])
    observed = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    tv = np.linspace(0.1, 0.6, 6)
    found = {}
    for seed in range(200):
        defined = sum(bool(observed[i].max() > TOPPLES) for i, _ in _resampled(objects, 4, seed))
        found.setdefault(defined, seed)
    assert {2, 3} <= set(found)
    enough = bootstrap_intervals(tv, predicted, observed, objects, 4, seed=found[3])
    assert not any(math.isnan(v) for v in enough["ap"]) and not any(math.isnan(v) for v in enough["map"])
    too_few = bootstrap_intervals(tv, predicted, observed, objects, 4, seed=found[2])
    assert all(math.isnan(v) for v in too_few["ap"] + too_few["map"])
    assert not any(math.isnan(v) for v in too_few["tv_all"])


def test_metrics_raise_no_warnings_on_empty_bins_resamples_and_logs():
    """Empty reliability bins, resamples without an informative push or a topple, an empty log and
    a push of one repeat are NaN or 0 where documented, silently: the report prints no RuntimeWarning."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert reliability(np.array([0.05, 0.95]), np.array([0.0, 1.0]))["bins"][4]["count"] == 0
        assert math.isnan(reliability(np.array([]), np.array([]))["ece"])
        empty = push_metrics(np.array([]), np.array([]), np.array([]), np.array([], int), np.array([]))
        assert all(math.isnan(empty[k]) for k in ("tv_all", "tv_informative", "informative", "map", "brier"))
        assert math.isnan(push_metrics(np.zeros(2), np.zeros(2), np.zeros(2), np.arange(2))["tv_informative"])
        assert math.isnan(observed_topple_rate(SimpleNamespace(pushes=[])))
        # R = 1 is NaN whatever the frequencies say.
        assert np.isnan(brier_floor(np.array([[0.5, 0.5], [1.0, 0.0]]), np.array([1, 1]))).all()
        # Objects 1 and 2 have no informative push and no topple: resamples of them only have neither.
        objects = np.array([0, 0, 1, 2])
        observed = np.array([1.0, 0.0, 0.0, 0.0])
        predicted = np.array([0.7, 0.0, 0.0, 0.0])
        tv = np.array([0.3, 0.0, 0.0, 0.0])
        ci = bootstrap_intervals(tv, predicted, observed, objects, 50, seed=0)
        assert ci["tv_all"][0] == 0.0
        first, second = Scores(tv, predicted, tv), Scores(tv, np.zeros(4), tv)
        paired = bootstrap_difference(first, second, observed, objects, 50, seed=0)
        assert paired["tv_informative"]["ci"][0] <= paired["tv_informative"]["ci"][1]


def test_paired_differences_are_the_difference_of_the_metrics_on_the_same_resampled_objects():
    rng = np.random.default_rng(6)
    tv, predicted, observed, objects, brier = _objects_data(rng, k=9)
    other_predicted = np.clip(predicted + rng.normal(0, 0.3, len(tv)), 0, 1) * (rng.random(len(tv)) < 0.8)
    first = Scores(tv, predicted, brier)
    second = Scores(rng.random(len(tv)), other_predicted, 2 * rng.random(len(tv)))
    n_resamples = 50

    def metrics(scores, index, copies):
        return push_metrics(scores.tv[index], scores.p_topple[index], observed[index], copies, scores.brier[index])

    everything = (np.arange(len(tv)), np.searchsorted(np.unique(objects), objects))
    point = {k: v - metrics(second, *everything)[k] for k, v in metrics(first, *everything).items()}
    draws = [{k: v - metrics(second, i, c)[k] for k, v in metrics(first, i, c).items()}
             for i, c in _resampled(objects, n_resamples, 2)]

    every = bootstrap_metric_difference(first, second, observed, objects, n_resamples, seed=2)
    assert set(every) == set(point)
    three = bootstrap_difference(first, second, observed, objects, n_resamples, seed=2)
    assert set(three) == {"tv_all", "tv_informative", "brier"}
    for key, result in [*every.items(), *three.items()]:
        values = np.array([d[key] for d in draws])
        values = values[~np.isnan(values)]
        assert result["difference"] == pytest.approx(point[key], abs=1e-12, nan_ok=True), key
        np.testing.assert_allclose(result["ci"], np.percentile(values, [2.5, 97.5]), rtol=0, atol=1e-12, err_msg=key)
    narrow = bootstrap_difference(first, second, observed, objects, n_resamples, seed=2, confidence=0.5)
    np.testing.assert_allclose(narrow["brier"]["ci"], np.percentile([d["brier"] for d in draws], [25, 75]), atol=1e-12)
    narrow = bootstrap_metric_difference(first, second, observed, objects, n_resamples, seed=2, confidence=0.5)
    np.testing.assert_allclose(narrow["ece"]["ci"], np.percentile([d["ece"] for d in draws], [25, 75]), atol=1e-12)


# ---------------------------------------------------------------- the report's summaries


class _Scorer(SimpleNamespace):
    """What the report's summaries read of a ``Scorer``: objects, observed topple rates, the push count."""

    def __len__(self):
        return len(self.object_index)


def test_predictor_summary_is_push_metrics_intervals_and_reliability_on_its_rows():
    rng = np.random.default_rng(12)
    tv, predicted, observed, objects, brier = _objects_data(rng)
    index = np.searchsorted(np.unique(objects), objects)
    scorer = _Scorer(object_index=index, empirical_topple=observed)
    scores = Scores(tv, predicted, brier)
    summary = predictor_summary(scores, scorer, n_resamples=30, seed=5)
    metrics = push_metrics(tv, predicted, observed, index, brier)
    assert {k: summary[k] for k in metrics} == pytest.approx(metrics, nan_ok=True)
    assert summary["ci"] == bootstrap_intervals(tv, predicted, observed, index, 30, 5, brier=brier)
    assert summary["reliability"] == reliability(predicted, observed)["bins"]
    assert predictor_summary(scores, scorer, n_resamples=0, seed=5)["ci"] == {}
    rows = np.flatnonzero(rng.random(len(tv)) < 0.6)
    some = predictor_summary(scores, scorer, n_resamples=30, seed=5, rows=rows)
    assert some["brier"] == pytest.approx(brier[rows].mean()) and some["tv_all"] == pytest.approx(tv[rows].mean())
    assert some["ci"] == bootstrap_intervals(tv[rows], predicted[rows], observed[rows], index[rows], 30, 5, brier=brier[rows])
    assert sum(b["count"] for b in some["reliability"]) == len(rows)


def test_per_object_rows_are_each_objects_own_metrics():
    tv = np.array([0.1, 0.3, 0.0, 0.5, 0.2, 0.4])
    predicted = np.array([0.8, 0.2, 0.0, 0.9, 0.1, 0.0])
    observed = np.array([1.0, 0.0, 0.0, 0.0, 0.75, 0.0])
    objects = np.array([0, 0, 0, 2, 2, 1])
    scorer = _Scorer(object_ids=["a", "b", "c"], object_index=objects, empirical_topple=observed)
    rows = per_object(Scores(tv, predicted, np.zeros(6)), scorer)
    assert [r["object_id"] for r in rows] == ["a", "b", "c"]
    a, b, c = rows
    assert (a["pushes"], a["informative_pushes"], b["pushes"], b["informative_pushes"], c["informative_pushes"]) == (3, 2, 1, 0, 2)
    assert a["tv_all"] == pytest.approx(0.4 / 3) and a["tv_informative"] == pytest.approx(0.2)
    assert a["ap"] == 1.0 and c["ap"] == pytest.approx(0.5) and math.isnan(b["ap"])
    assert math.isnan(b["tv_informative"]) and b["tv_all"] == pytest.approx(0.4)
    assert a["observed_topple"] == pytest.approx(1 / 3) and a["predicted_topple"] == pytest.approx(1.0 / 3)
    assert c["observed_topple"] == pytest.approx(0.375) and c["predicted_topple"] == pytest.approx(0.5)


def test_by_direction_bands_at_their_limits():
    """Bands [0], (0, 0.25), [0.25, 0.75), [0.75, 1]: each limit in the band above it, 1 in the top one."""
    predicted = np.array([0.0, 1e-12, 0.2499, 0.25, 0.7499, 0.75, 1.0])
    observed = np.linspace(0.0, 0.6, 7)
    scorer = SimpleNamespace(empirical_topple=observed)
    classes = [("side", np.ones(7, bool)), ("nowhere", np.zeros(7, bool))]
    cells = {c["band"]: c for c in by_direction(Scores(np.zeros(7), predicted, np.zeros(7)), scorer, classes)}
    assert {band: c["pushes"] for band, c in cells.items()} == {"P = 0": 1, "0 < P < 0.25": 2, "0.25 <= P < 0.75": 2, "P >= 0.75": 2}
    assert all(c["direction"] == "side" for c in cells.values())
    assert cells["P >= 0.75"]["predicted_topple"] == pytest.approx(0.875) and cells["P >= 0.75"]["observed_topple"] == pytest.approx(0.55)
    assert cells["0 < P < 0.25"]["observed_topple"] == pytest.approx(0.15)
    # The direction classes at their limits: -0.7 is oblique, -0.3 side, 0.3 from below, and 1 and -1 (and
    # a unit vector's rounding past them) in the end classes.
    names = [[name for name, rows in direction_classes(np.array([u])) if rows[0]] for u in
             (-1.0000001, -0.7, -0.3, 0.3, 1.0, 1.0000001, -0.71, 0.29)]
    assert names == [["from above"], ["oblique"], ["side"], ["from below"], ["from below"], ["from below"], ["from above"], ["side"]]


def test_ranking_by_direction_is_the_classes_own_ap():
    predicted = np.array([0.9, 0.1, 0.5, 0.6, 0.2])
    observed = np.array([0.5, 0.75, 1.0, 0.0, 0.6])
    scorer = SimpleNamespace(empirical_topple=observed)
    classes = [("one", np.array([True, True, True, False, False])), ("none", np.zeros(5, bool)),
               ("two", np.array([False, False, False, True, True]))]
    rows = ranking_by_direction(Scores(np.zeros(5), predicted, np.zeros(5)), scorer, classes)
    assert [r["direction"] for r in rows] == ["one", "two"]
    assert rows[0]["ap"] == pytest.approx(average_precision_score([False, True, True], [0.9, 0.1, 0.5]))
    assert rows[1]["ap"] == pytest.approx(0.5) and rows[1]["pushes"] == 2
    assert rows[0]["predicted_topple"] == pytest.approx(0.5) and rows[0]["observed_topple"] == pytest.approx(0.75)


def test_observed_topple_rate_weights_each_push_once():
    log = SimpleNamespace(pushes=[SimpleNamespace(topple_rate=r) for r in (0.0, 1.0, 0.25, 0.25)])
    assert observed_topple_rate(log) == pytest.approx(0.375)
    assert math.isnan(observed_topple_rate(SimpleNamespace(pushes=[])))


# ---------------------------------------------------------------- the trivial predictors and Scores


def _pose(index, final, blocked):
    edges = len(final)
    return StablePose(index=index, down=np.array([0.0, 0.0, -1.0]), probability=0.0, transform=np.eye(4), height=0.1,
                      com_height=0.05, base_edges=np.zeros((edges, 2, 3)), edge_final_pose=np.array(final),
                      edge_blocked=np.array(blocked, bool), apex_angle=np.zeros(edges), edge_rolled_pose=np.array(final),
                      edge_momentum_pose=np.array(final), edge_onward_pose=np.array(final))


def _hand_scorer():
    """A ``Scorer`` of two objects, three start poses, built by hand (no meshes): what the trivial
    predictors and ``_scores`` read of it."""
    empirical_a = np.array([[1.0, 0.0, 0.0, 0.0], [0.5, 0.25, 0.0, 0.25]])      # object a, pose 0: 2 pushes
    empirical_b = np.array([[0.0, 1.0, 0.0, 0.0, 0.0]])                        # object a, pose 1 (no edge: keeps its mass)
    empirical_c = np.array([[0.0, 0.0, 1.0], [0.0, 0.5, 0.5], [1.0, 0.0, 0.0]])  # object b, pose 1
    groups = [
        Group("a", _pose(0, [1, 2, 0, 1], [False, False, False, True]), np.full(3, 1 / 3), None, np.array([0, 3]), empirical_a),
        Group("a", _pose(1, [1, 0], [False, True]), np.full(4, 0.25), None, np.array([4]), empirical_b),
        Group("b", _pose(1, [0, 0], [False, False]), np.full(2, 0.5), None, np.array([1, 2, 5]), empirical_c),
    ]
    scorer = Scorer.__new__(Scorer)
    scorer.log, scorer.groups = SimpleNamespace(pushes=[None] * 6), groups
    return scorer


def test_topple_spread_spreads_over_the_unblocked_edges_leading_elsewhere():
    a, b, c = _hand_scorer().groups
    # Pose 0's edges lead to 1, 2, 0 (itself: not a topple) and 1 (blocked): 1/2 on each of 1 and 2.
    np.testing.assert_allclose(topple_spread(a), [0.0, 0.5, 0.5, 0.0])
    np.testing.assert_allclose(topple_spread(b), [0.0, 1.0, 0.0, 0.0, 0.0])  # its only edge is blocked
    np.testing.assert_allclose(topple_spread(c), [1.0, 0.0, 0.0])  # two edges onto pose 0: all on it
    two_to_one = _pose(0, [1, 1, 2], [False, False, False])
    np.testing.assert_allclose(topple_spread(replace(a, pose=two_to_one)), [0.0, 2 / 3, 1 / 3, 0.0])  # per edge


def test_trivial_predictors_and_their_scores_against_the_empirical_distribution():
    scorer = _hand_scorer()
    rate = 0.3
    for scores, r in ((scorer.constant_rate(rate), rate), (scorer.never_topples(), 0.0)):
        assert scores.tv.shape == scores.brier.shape == scores.p_topple.shape == (6,)
        for group in scorer.groups:
            stays = np.eye(group.n_poses + 1)[group.pose.index]
            predicted = (1 - r) * stays + r * topple_spread(group)
            for row, e in zip(group.rows, group.empirical):
                assert scores.tv[row] == pytest.approx(np.abs(predicted - e).max())
                assert scores.brier[row] == pytest.approx(((predicted - e) ** 2).sum())
                assert scores.p_topple[row] == pytest.approx(1 - predicted[group.pose.index])
    constant = scorer.constant_rate(rate)
    # Rows are the log's: push 4 (pose without a free edge) keeps P(topple) 0; the others topple with 0.3.
    np.testing.assert_allclose(constant.p_topple, [rate, rate, rate, rate, 0.0, rate])
    np.testing.assert_allclose(scorer.never_topples().p_topple, 0.0)
    np.testing.assert_allclose(scorer.never_topples().tv, [0.0, 1.0, 0.5, 0.5, 0.0, 1.0])


def test_score_predictions_scores_each_groups_rows_and_mixes_in_the_spread():
    scorer = _hand_scorer()
    rng = np.random.default_rng(0)
    predictions = []
    for group in scorer.groups:
        predicted = rng.dirichlet(np.ones(group.n_poses + 1), size=len(group.rows))
        predictions.append((predicted, 1 - predicted[:, group.pose.index]))
    plain, mixed = scorer.score_predictions(predictions), scorer.score_predictions(predictions, spread_share=0.2)
    for group, (predicted, p) in zip(scorer.groups, predictions):
        np.testing.assert_allclose(plain.tv[group.rows], sup_tv(predicted, group.empirical))
        np.testing.assert_allclose(plain.brier[group.rows], brier_score(predicted, group.empirical))
        np.testing.assert_allclose(plain.p_topple[group.rows], p)
        spread = topple_spread(group)
        moved = 0.8 * predicted + 0.2 * spread
        np.testing.assert_allclose(mixed.tv[group.rows], sup_tv(moved, group.empirical))
        np.testing.assert_allclose(mixed.brier[group.rows], brier_score(moved, group.empirical))
        np.testing.assert_allclose(mixed.p_topple[group.rows], 1 - moved[:, group.pose.index])


def test_brier_floor_of_a_scorer_follows_its_rows():
    scorer = _hand_scorer()
    scorer.repeats = np.array([1, 2, 4, 4, 3, 2])
    floor = scorer.brier_floor()
    for group in scorer.groups:
        for row, e in zip(group.rows, group.empirical):
            expected = (e * (1 - e)).sum() / (scorer.repeats[row] - 1) if scorer.repeats[row] > 1 else math.nan
            assert floor[row] == pytest.approx(expected, nan_ok=True)
