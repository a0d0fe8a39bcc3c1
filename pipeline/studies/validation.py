"""Validation report: the toppling model against a push-outcome log (thesis 4.4.2, table 4.3).

The pushes were executed elsewhere (``toppledb play`` in pybullet, or a real robot)
and logged with ``schema.pushlog``; this module runs no simulation.  It reads the
log against the model (``logreader``), predicts every push with each model variant
(``scoring``) and scores the predictions:

* sup-form total variation (TV), max over next poses of |P_model - P_observed|, the
  mean over all pushes and over the *informative* ones (the model or physics says
  something topples; the rest are trivially right for every model);
* average precision of "it topples" (label: observed P(topple) > 0.5, score: the
  predicted P(topple)), pooled and per object (mAP);
* a reliability diagram (predicted P(topple) in bins against the observed
  frequency) and the expected calibration error (ECE);
* the trivial predictors as reference rows: "never topples", and "constant rate"
  (the topple rate of *calibration* data, given with ``--rate`` or ``--rate-from``,
  never that of the reported log);
* per-object results with the worst objects named, bootstrap confidence intervals
  over objects, counts (rejected rows by reason);
* with ``--against``, other models (the thesis's, an earlier default) scored on the same
  pushes, and the configured model minus each, paired over objects.

    toppledb report data/logs/heldout --rate-from data/logs/calibration --out reports/validation.json --plot reports/validation.png
"""


from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..build.atomic import write_figure_atomic, write_text_atomic
from ..model.config import VARIANTS, Config, ToppleConfig
from .logreader import LogError, PushLog, read_log
from .scoring import Scorer, Scores

THESIS_TABLE_4_3 = {
    "baseline": {"tv": 0.424, "map": 0.412},
    "rotations": {"tv": 0.494, "map": 0.381},
    "robustness": {"tv": 0.247, "map": 0.568},
    "robust": {"tv": 0.211, "map": 0.589},
}
"""Thesis table 4.3: final-pose predictions against 700 physical pushes (6-fold cross-validated)."""

RELIABILITY_BINS = 10
"""Equal-width bins of predicted P(topple) for the reliability diagram and the ECE."""
TOPPLES = 0.5
"""A push "topples" (the AP label) when more than this fraction of its repeats toppled."""
BOOTSTRAP = 1000
"""Bootstrap resamples of the objects for the confidence intervals."""
CONFIDENCE = 0.95
WORST = 5
"""Objects named as the worst in a report."""
SPREAD_SHARE = 0.01
"""Share of every push's probability the ``spread_1pct`` reference moves from the main
variant's prediction to a topple that knows nothing about the push (``scoring.topple_spread``):
it makes nearly every push informative, and shows how much of a model's informative TV a
change that adds no knowledge can buy."""

# ---------------------------------------------------------------- metrics


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision of ranking by ``scores`` against binary ``labels``.

    Tied scores form one threshold (as scikit-learn's ``average_precision_score``), so a
    0/1 score is not credited for an arbitrary order inside a tie.
    scores : (n,) float;  labels : (n,) bool
    returns : float in [0, 1]; NaN without positive labels
    """
    scores = np.asarray(scores, dtype=float)
    labels = np.asarray(labels, dtype=bool)
    if not labels.any():
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    scores, labels = scores[order], labels[order]
    # Last index of each block of equal scores: the thresholds.
    last = np.flatnonzero(np.r_[scores[1:] != scores[:-1], True])
    true_positives = np.cumsum(labels)[last]
    precision = true_positives / (last + 1)
    recall = true_positives / labels.sum()
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def reliability(predicted: np.ndarray, observed: np.ndarray, n_bins: int = RELIABILITY_BINS) -> dict:
    """Reliability diagram and expected calibration error of predicted probabilities.

    predicted : (n,) float in [0, 1], predicted P(topple) per push
    observed : (n,) float in [0, 1], observed topple frequency per push
    returns : {"bins": [{"low", "high", "count", "predicted", "observed"}, ...], "ece": float}
      ECE = sum over bins of (count / n) |mean predicted - mean observed|; empty bins count 0.
      A prediction of exactly 1 falls in the last bin.
    """
    predicted = np.asarray(predicted, dtype=float)
    observed = np.asarray(observed, dtype=float)
    which = np.clip((predicted * n_bins).astype(int), 0, n_bins - 1)
    count = np.bincount(which, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_predicted = np.bincount(which, weights=predicted, minlength=n_bins) / count
        mean_observed = np.bincount(which, weights=observed, minlength=n_bins) / count
    gap = np.where(count > 0, np.abs(mean_predicted - mean_observed), 0.0)
    ece = float(np.sum(count * gap) / len(predicted)) if len(predicted) else float("nan")
    bins = [
        {"low": b / n_bins, "high": (b + 1) / n_bins, "count": int(count[b]),
         "predicted": _number(mean_predicted[b]), "observed": _number(mean_observed[b])}
        for b in range(n_bins)
    ]
    return {"bins": bins, "ece": ece}


def expected_calibration_error(predicted: np.ndarray, observed: np.ndarray, n_bins: int = RELIABILITY_BINS) -> float:
    return reliability(predicted, observed, n_bins)["ece"]


def informative(predicted_topple: np.ndarray, observed_topple: np.ndarray) -> np.ndarray:
    """Pushes where the model or physics says something topples: (n,) bool."""
    return (np.asarray(predicted_topple) > 0) | (np.asarray(observed_topple) > 0)


def push_metrics(
    tv: np.ndarray, predicted: np.ndarray, observed: np.ndarray, groups: np.ndarray, brier: np.ndarray | None = None
) -> dict[str, float]:
    """The headline metrics of one predictor on a set of pushes.

    tv : (n,) float, sup-form TV per push;  predicted, observed : (n,) float, P(topple)
    groups : (n,) int, object of each push (for the per-object mAP)
    brier : (n,) float, multi-class Brier score per push (``scoring.Scores.brier``), or None
    returns : tv_all, tv_informative, informative (fraction of pushes), ap, map, ece, and
      brier (the mean) when given
    """
    useful = informative(predicted, observed)
    labels = observed > TOPPLES
    per_object = [average_precision(predicted[groups == g], labels[groups == g]) for g in np.unique(groups)]
    per_object = [ap for ap in per_object if not math.isnan(ap)]
    out = {
        "tv_all": float(np.mean(tv)) if len(tv) else float("nan"),
        "tv_informative": float(np.mean(tv[useful])) if useful.any() else float("nan"),
        "informative": float(np.mean(useful)) if len(tv) else float("nan"),
        "ap": average_precision(predicted, labels),
        "map": float(np.mean(per_object)) if per_object else float("nan"),
        "ece": expected_calibration_error(predicted, observed),
    }
    if brier is not None:
        out["brier"] = float(np.mean(brier)) if len(brier) else float("nan")
    return out


def bootstrap_intervals(
    tv: np.ndarray,
    predicted: np.ndarray,
    observed: np.ndarray,
    objects: np.ndarray,
    n_resamples: int = BOOTSTRAP,
    seed: int = 0,
    confidence: float = CONFIDENCE,
    brier: np.ndarray | None = None,
) -> dict[str, list[float]]:
    """Percentile bootstrap over objects: resample objects with replacement (each drawn copy
    counts as its own object) and recompute the metrics of ``push_metrics``.

    Sums per object are computed once, so a resample costs one matrix product, plus one
    sort for the pooled AP.
    objects : (n,) int, object of each push
    returns : metric -> [low, high]; NaN bounds when a metric is undefined in most resamples
    """
    rng = np.random.default_rng(seed)
    names, which = np.unique(objects, return_inverse=True)
    k = len(names)
    useful = informative(predicted, observed)
    labels = observed > TOPPLES
    bins = np.clip((predicted * RELIABILITY_BINS).astype(int), 0, RELIABILITY_BINS - 1)

    def per_object(weights: np.ndarray) -> np.ndarray:
        return np.bincount(which, weights=weights, minlength=k)

    pushes = per_object(np.ones(len(tv)))
    tv_sum, tv_useful, n_useful = per_object(tv), per_object(tv * useful), per_object(useful.astype(float))
    cell = which * RELIABILITY_BINS + bins
    bin_count = np.bincount(cell, minlength=k * RELIABILITY_BINS).reshape(k, -1)
    bin_predicted = np.bincount(cell, weights=predicted, minlength=k * RELIABILITY_BINS).reshape(k, -1)
    bin_observed = np.bincount(cell, weights=observed, minlength=k * RELIABILITY_BINS).reshape(k, -1)
    object_ap = np.array([average_precision(predicted[which == i], labels[which == i]) for i in range(k)])
    rows = [np.flatnonzero(which == i) for i in range(k)]

    keys = ("tv_all", "tv_informative", "informative", "ap", "map", "ece") + (("brier",) if brier is not None else ())
    samples: dict[str, list[float]] = {key: [] for key in keys}
    brier_sum = per_object(brier) if brier is not None else None
    for _ in range(n_resamples):
        draw = rng.integers(k, size=k)
        times = np.bincount(draw, minlength=k).astype(float)
        n = times @ pushes
        samples["tv_all"].append(times @ tv_sum / n)
        if brier_sum is not None:
            samples["brier"].append(times @ brier_sum / n)
        samples["tv_informative"].append(times @ tv_useful / (times @ n_useful) if times @ n_useful else math.nan)
        samples["informative"].append(times @ n_useful / n)
        index = np.concatenate([rows[d] for d in draw])
        samples["ap"].append(average_precision(predicted[index], labels[index]))
        drawn_ap = object_ap[draw]
        samples["map"].append(float(np.mean(drawn_ap[~np.isnan(drawn_ap)])) if (~np.isnan(drawn_ap)).any() else math.nan)
        count = times @ bin_count
        with np.errstate(invalid="ignore", divide="ignore"):
            gap = np.abs(times @ bin_predicted - times @ bin_observed) / count
        samples["ece"].append(float(np.sum(np.where(count > 0, count * gap, 0.0)) / n))
    # A metric undefined in most resamples (NaN) gets no interval.
    return {key: percentile_interval(values, confidence, fewest=int(n_resamples // 2) + 1) for key, values in samples.items()}


def percentile_interval(values, confidence: float = CONFIDENCE, fewest: int = 1) -> list[float]:
    """[low, high], the central ``confidence`` of the bootstrap draws ``values`` that are not NaN;
    NaN bounds when fewer than ``fewest`` are."""
    values = np.asarray(values, dtype=float)
    values = values[~np.isnan(values)]
    if len(values) < max(fewest, 1):
        return [math.nan, math.nan]
    tail = 100 * (1 - confidence) / 2
    return [float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))]


def bootstrap_difference(
    first: Scores,
    second: Scores,
    observed: np.ndarray,
    objects: np.ndarray,
    n_resamples: int = BOOTSTRAP,
    seed: int = 0,
    confidence: float = CONFIDENCE,
) -> dict[str, dict]:
    """Paired bootstrap over objects of ``first - second`` for the mean sup-TV over all and over
    informative pushes and the mean Brier score: both predictors see the same resampled
    objects, so the interval is that of the difference, much narrower than the two intervals
    side by side.

    returns : {"tv_all": {"difference", "ci": [low, high]}, "tv_informative": {...}, "brier": {...}}
    """
    rng = np.random.default_rng(seed)
    names, which = np.unique(objects, return_inverse=True)
    k = len(names)

    def sums(scores: Scores) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        useful = informative(scores.p_topple, observed)
        return (np.bincount(which, weights=scores.tv, minlength=k), np.bincount(which, weights=scores.tv * useful, minlength=k),
                np.bincount(which, weights=useful.astype(float), minlength=k))

    pushes = np.bincount(which, minlength=k).astype(float)
    (a_all, a_useful, a_n), (b_all, b_useful, b_n) = sums(first), sums(second)
    brier_gap = np.bincount(which, weights=first.brier - second.brier, minlength=k)

    def metrics(times: np.ndarray) -> tuple[float, float, float]:
        with np.errstate(invalid="ignore", divide="ignore"):
            return ((times @ a_all - times @ b_all) / (times @ pushes),
                    times @ a_useful / (times @ a_n) - times @ b_useful / (times @ b_n),
                    times @ brier_gap / (times @ pushes))

    point = metrics(np.ones(k))
    draws = np.array([metrics(np.bincount(rng.integers(k, size=k), minlength=k).astype(float)) for _ in range(n_resamples)])
    keys = ("tv_all", "tv_informative", "brier")
    return {key: {"difference": float(point[i]), "ci": percentile_interval(draws[:, i], confidence)} for i, key in enumerate(keys)}


def bootstrap_metric_difference(
    first: Scores,
    second: Scores,
    observed: np.ndarray,
    objects: np.ndarray,
    n_resamples: int = BOOTSTRAP,
    seed: int = 0,
    confidence: float = CONFIDENCE,
    second_observed: np.ndarray | None = None,
) -> dict[str, dict]:
    """Paired bootstrap over objects of ``first - second`` for every metric of ``push_metrics``
    (ECE, AP and mAP included): both predictors are scored on the same resampled objects, each
    drawn copy of an object counting as its own object.

    second_observed : (n,) float, the topple rates ``second`` is scored against when they are not
      ``observed`` (one predictor against two logs of the same pushes, ``judge_numerics``)
    returns : metric -> {"difference": point estimate, "ci": [low, high]}
    """
    rng = np.random.default_rng(seed)
    names, which = np.unique(objects, return_inverse=True)
    rows = [np.flatnonzero(which == i) for i in range(len(names))]

    seen = (observed, observed if second_observed is None else second_observed)

    def metrics(scores: Scores, against: np.ndarray, index: np.ndarray, copies: np.ndarray) -> dict[str, float]:
        return push_metrics(scores.tv[index], scores.p_topple[index], against[index], copies, scores.brier[index])

    def difference(draw: np.ndarray) -> dict[str, float]:
        index = np.concatenate([rows[d] for d in draw])
        copies = np.repeat(np.arange(len(draw)), [len(rows[d]) for d in draw])
        a, b = metrics(first, seen[0], index, copies), metrics(second, seen[1], index, copies)
        return {key: a[key] - b[key] for key in a}

    point = difference(np.arange(len(names)))
    draws = [difference(rng.integers(len(names), size=len(names))) for _ in range(n_resamples)]
    return {key: {"difference": float(value), "ci": percentile_interval([d[key] for d in draws], confidence)}
            for key, value in point.items()}


# ---------------------------------------------------------------- the report


def predictor_summary(scores: Scores, scorer: Scorer, *, n_resamples: int, seed: int, rows: np.ndarray | None = None) -> dict:
    """Metrics, confidence intervals and the reliability diagram of one predictor (on ``rows``, default all)."""
    rows = np.arange(len(scorer)) if rows is None else rows
    tv, predicted, observed = scores.tv[rows], scores.p_topple[rows], scorer.empirical_topple[rows]
    objects, brier = scorer.object_index[rows], scores.brier[rows]
    out = push_metrics(tv, predicted, observed, objects, brier)
    out["ci"] = bootstrap_intervals(tv, predicted, observed, objects, n_resamples, seed, brier=brier) if n_resamples else {}
    out["reliability"] = reliability(predicted, observed)["bins"]
    return out


def per_object(scores: Scores, scorer: Scorer) -> list[dict]:
    """One row per object: pushes, informative pushes, TV, AP, observed and predicted topple rates."""
    out = []
    for i, name in enumerate(scorer.object_ids):
        rows = np.flatnonzero(scorer.object_index == i)
        m = push_metrics(scores.tv[rows], scores.p_topple[rows], scorer.empirical_topple[rows], np.zeros(len(rows), int))
        out.append({
            "object_id": name, "pushes": len(rows),
            "informative_pushes": int(informative(scores.p_topple[rows], scorer.empirical_topple[rows]).sum()),
            "tv_all": m["tv_all"], "tv_informative": m["tv_informative"], "ap": m["ap"],
            "observed_topple": float(scorer.empirical_topple[rows].mean()),
            "predicted_topple": float(scores.p_topple[rows].mean()),
        })
    return out


DIRECTIONS = (("from above", -1.0, -0.7), ("oblique", -0.7, -0.3), ("side", -0.3, 0.3), ("from below", 0.3, 1.0))
"""Push directions by their vertical component u_z in the pose frame (z up): name, lowest, highest."""
BANDS = (("P = 0", 0.0, 0.0), ("0 < P < 0.25", 0.0, 0.25), ("0.25 <= P < 0.75", 0.25, 0.75), ("P >= 0.75", 0.75, 1.0))
"""Bands of predicted P(topple): name, lowest, highest (the first band is exactly 0)."""


def _within(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """low <= values < high, the top closed at 1 (the largest value a direction or a P takes)."""
    return (values >= low) & ((values < high) | (high >= 1.0))


def direction_classes(u_z: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Each of ``DIRECTIONS``' names with the (n,) bool rows whose push is in it.

    u_z : (n,) float, the push direction's vertical component in the pose frame (z up); clipped
      to [-1, 1] (a unit vector's rounding) and compared in float32, as
      ``schema.horizon.choosable_pushes`` compares it, so the classes split what the policies choose"""
    u_z = np.clip(np.asarray(u_z, dtype=float), -1.0, 1.0).astype(np.float32)
    return [(name, _within(u_z, np.float32(low), np.float32(high))) for name, low, high in DIRECTIONS]


def log_direction_classes(scorer: Scorer) -> list[tuple[str, np.ndarray]]:
    """``direction_classes`` of the scorer's logged pushes (their u_z, pose frame)."""
    return direction_classes(np.array([p.direction[2] for p in scorer.log.pushes]))


def by_direction(scores: Scores, scorer: Scorer, classes: list[tuple[str, np.ndarray]]) -> list[dict]:
    """Where the predictor is right or wrong: per push direction (``DIRECTIONS``) and band of
    predicted P(topple) (``BANDS``), the pushes, their mean predicted and mean observed topple
    rate.  Empty cells are left out."""
    predicted, observed = scores.p_topple, scorer.empirical_topple
    out = []
    for direction, in_direction in classes:
        for band, low, high in BANDS:
            in_band = (predicted == 0.0) if high == 0.0 else _within(predicted, low, high) & (predicted > 0.0)
            rows = in_direction & in_band
            if rows.any():
                out.append({"direction": direction, "band": band, "pushes": int(rows.sum()),
                            "predicted_topple": float(predicted[rows].mean()), "observed_topple": float(observed[rows].mean())})
    return out


def ranking_by_direction(scores: Scores, scorer: Scorer, classes: list[tuple[str, np.ndarray]]) -> list[dict]:
    """How well the predictor ranks the pushes of each push direction (``DIRECTIONS``) among
    themselves: pushes, average precision of "it topples" within the class, mean predicted and
    observed topple rate.  A policy choosing the best of a pose's pushes leans on the ranking,
    and a class ranked badly is where its choices go wrong.  Empty classes are left out.
    classes : ``log_direction_classes(scorer)``"""
    predicted, observed = scores.p_topple, scorer.empirical_topple
    out = []
    for direction, rows in classes:
        if rows.any():
            out.append({"direction": direction, "pushes": int(rows.sum()),
                        "ap": average_precision(predicted[rows], observed[rows] > TOPPLES),
                        "predicted_topple": float(predicted[rows].mean()), "observed_topple": float(observed[rows].mean())})
    return out


def worst_objects(objects: list[dict], n: int = WORST) -> list[str]:
    """Objects with the highest informative TV (ties: more pushes first)."""
    ranked = [o for o in objects if not math.isnan(o["tv_informative"])]
    ranked.sort(key=lambda o: (-o["tv_informative"], -o["pushes"], o["object_id"]))
    return [o["object_id"] for o in ranked[:n]]


def report(
    log: PushLog,
    config: Config = Config(),
    variants: tuple[str, ...] = VARIANTS,
    *,
    rate: float | None = None,
    rate_source: str | None = None,
    n_resamples: int = BOOTSTRAP,
    seed: int = 0,
    scorer: Scorer | None = None,
    replay: PushLog | None = None,
    against: dict[str, ToppleConfig] | None = None,
) -> dict:
    """The validation report of ``config`` on ``log`` as a JSON-ready dict.

    variants : model variants to score with ``config``'s parameters
    rate : topple rate of the *calibration* data for the constant-rate reference (omitted when None)
    replay : the log's pushes played again with other noise draws, for the ``physics_replay``
      reference (``Scorer.replay``; omitted when None)
    against : name -> another model's ``[topple]`` parameters, each scored on the same pushes,
      candidates and trial streams in its own configured variant, with the configured variant
      minus it bootstrapped over objects (``bootstrap_metric_difference``; omitted when None)
    """
    scorer = scorer or Scorer(log, config.seed, config.contacts)
    main_variant = config.topple.variant if config.topple.variant in variants else variants[-1]
    results: dict[str, dict] = {}
    objects: list[dict] = []
    directions: list[dict] = []
    ranking: list[dict] = []
    for variant in variants:
        predictions = scorer.predict(replace(config.topple, variant=variant))
        scores = scorer.score_predictions(predictions)
        results[variant] = predictor_summary(scores, scorer, n_resamples=n_resamples, seed=seed)
        if variant == main_variant:
            main_predictions, main_scores = predictions, scores
            objects = per_object(scores, scorer)
            classes = log_direction_classes(scorer)
            directions = by_direction(scores, scorer, classes)
            ranking = ranking_by_direction(scores, scorer, classes)
    recalibration = None
    applied = replace(config.topple, variant=main_variant)
    x, y = applied.applied_recalibration
    if (len(x) or applied.applied_feature_map or applied.applied_down_map or applied.applied_side_map) and main_variant in variants:
        # The configured variant without its maps (docs/MODEL.md C.7, C.13, C.15, C.16), and the paired
        # difference: mapped minus raw, on the same resampled objects.
        raw = scorer.score_variant(config.topple.without_recalibration(), main_variant)
        recalibration = {
            **({"x": list(x), "y": list(y)} if len(x) else {"feature_map": list(applied.applied_feature_map)}),
            "down_map": list(applied.applied_down_map), "down_map_z": applied.down_map_z,
            "side_map": list(applied.applied_side_map), "side_map_band": list(applied.side_map_band),
            "raw": f"{main_variant}_raw",
            "raw_metrics": predictor_summary(raw, scorer, n_resamples=n_resamples, seed=seed),
            "difference": bootstrap_metric_difference(
                main_scores, raw, scorer.empirical_topple, scorer.object_index, n_resamples, seed),
        }
    references = {"never_topples": predictor_summary(scorer.never_topples(), scorer, n_resamples=n_resamples, seed=seed)}
    if rate is not None:
        references["constant_rate"] = predictor_summary(scorer.constant_rate(rate), scorer, n_resamples=n_resamples, seed=seed)
        references["constant_rate"]["rate"] = rate
        references["constant_rate"]["rate_from"] = rate_source
    if main_variant in variants:
        # What informative TV is worth: the same model with 1 % of every push moved to a topple
        # that knows nothing about the push (docs/VALIDATION.md "Reading informative TV").
        spread = scorer.score_predictions(main_predictions, spread_share=SPREAD_SHARE)
        references["spread_1pct"] = predictor_summary(spread, scorer, n_resamples=n_resamples, seed=seed)
        references["spread_1pct"].update(share=SPREAD_SHARE, of=main_variant)
    if replay is not None:
        # The other end of the scale from never-topples: physics predicting itself.
        references["physics_replay"] = predictor_summary(scorer.replay(replay), scorer, n_resamples=n_resamples, seed=seed)
        replay_repeats = replay.counts()
        references["physics_replay"].update(files=replay.files, repeats_min=replay_repeats["repeats_min"],
                                            repeats_max=replay_repeats["repeats_max"])
    comparisons = {}
    if against and main_variant in variants:
        for name, other in against.items():
            other_scores = scorer.score(other)
            other_x, other_y = other.applied_recalibration
            comparisons[name] = {
                "variant": other.variant,
                "corrections": sorted(other.applied_corrections),
                # What calibration and recalibration change (the noise, the map), beside the
                # variant and corrections above; the rest of [topple] is in the compared file.
                "topple": {k: getattr(other, k) for k in NOISE_KEYS},
                "recalibration": {"x": list(other_x), "y": list(other_y),
                                  "feature_map": list(other.applied_feature_map),
                                  "down_map": list(other.applied_down_map), "down_map_z": other.down_map_z,
                                  "side_map": list(other.applied_side_map), "side_map_band": list(other.side_map_band)},
                "metrics": predictor_summary(other_scores, scorer, n_resamples=n_resamples, seed=seed),
                "ranking_by_direction": ranking_by_direction(other_scores, scorer, classes),
                "difference": bootstrap_metric_difference(
                    main_scores, other_scores, scorer.empirical_topple, scorer.object_index, n_resamples, seed),
            }
    floor = scorer.brier_floor()
    counts = log.counts()
    counts["objects_in_corpus"] = sum(1 for o in log.objects.values() if o.in_corpus)
    return {
        "log": log.files,
        "counts": counts,
        "rejected_examples": {k: [list(e) for e in v] for k, v in log.examples.items()},
        "topple": {k: getattr(config.topple, k) for k in NOISE_KEYS},
        "seed": config.seed,
        "n_trials": config.topple.n_trials,
        "variants": results,
        "references": references,
        "main_variant": main_variant,
        "objects": objects,
        "worst_objects": worst_objects(objects),
        "by_direction": directions,
        "ranking_by_direction": ranking,
        "brier_floor": float(np.nanmean(floor)) if np.isfinite(floor).any() else float("nan"),
        "bootstrap": {"resamples": n_resamples, "confidence": CONFIDENCE, "seed": seed, "over": "objects"},
        "thesis_table_4_3": THESIS_TABLE_4_3,
        **({"recalibration": recalibration} if recalibration else {}),
        **({"against": comparisons} if comparisons else {}),
    }


NOISE_KEYS = ("mu_table_mean", "mu_table_std", "mu_finger_mean", "mu_finger_std", "contact_std", "direction_std", "rotation_std")
"""The noise parameters of ``ToppleConfig`` that calibration searches."""


def observed_topple_rate(log: PushLog) -> float:
    """Mean observed topple rate over the pushes of a log (each push weighted once)."""
    return float(np.mean([p.topple_rate for p in log.pushes])) if log.pushes else float("nan")


# ---------------------------------------------------------------- output


def format_report(result: dict) -> str:
    """Plain-text table: one line per variant and reference predictor."""
    def cell(value):
        return "  -  " if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.3f}"

    def ci(m, key):
        low, high = m.get("ci", {}).get(key, [math.nan, math.nan])
        return "" if math.isnan(low) else f" [{low:.3f}, {high:.3f}]"

    c = result["counts"]
    lines = [
        (f"{c['pushes']} pushes ({c['repeats_min']}-{c['repeats_max']} repeats), {c['objects']} objects, "
         f"{c['rows_used']} of {c['rows']} rows used"),
    ]
    for reason, count in c["rejected_by_reason"].items():
        lines.append(f"  rejected {count} rows: {reason}")
    if "model" in result:
        lines.append(f"model ({result['main_variant']}): {result['model']}")
    rows = _rows(result)
    width = max([15] + [len(name) for name, _ in rows])
    lines.append(f"{'predictor':<{width}} {'TV inform.':>26} {'TV all':>8} {'Brier':>7} {'AP':>26} {'mAP':>7} {'ECE':>7} {'inform.':>8}")
    for name, m in rows:
        lines.append(
            f"{name:<{width}} {cell(m['tv_informative']) + ci(m, 'tv_informative'):>26} {cell(m['tv_all']):>8} "
            f"{cell(m.get('brier')):>7} {cell(m['ap']) + ci(m, 'ap'):>26} {cell(m['map']):>7} {cell(m['ece']):>7} "
            f"{cell(m['informative']):>8}"
        )
    if result.get("brier_floor") is not None:
        lines.append(f"Brier floor (the log's own repeat noise; no predictor can expect less): {cell(result['brier_floor'])}")
    lines.append(f"worst objects ({result['main_variant']}, informative TV): {', '.join(result['worst_objects'])}")
    if result.get("by_direction"):
        lines.append(f"{result['main_variant']} by push direction and predicted P(topple): pushes, predicted, observed")
        lines += [f"  {d['direction']:<11} {d['band']:<17} {d['pushes']:5d} {d['predicted_topple']:.3f} {d['observed_topple']:.3f}"
                  for d in result["by_direction"]]
    if result.get("ranking_by_direction"):
        lines.append(f"{result['main_variant']} ranking within each push direction: pushes, AP, predicted, observed")
        lines += [f"  {d['direction']:<11} {d['pushes']:5d} {cell(d['ap'])} {d['predicted_topple']:.3f} {d['observed_topple']:.3f}"
                  for d in result["ranking_by_direction"]]
    if "recalibration" in result:
        parts = [f"{key} {_difference(d)}" for key, d in result["recalibration"]["difference"].items() if key != "informative"]
        lines.append(f"recalibrated - {result['recalibration']['raw']} (paired bootstrap over objects): " + ", ".join(parts))
    for name, other in result.get("against", {}).items():
        parts = [f"{key} {_difference(d)}" for key, d in other["difference"].items() if key != "informative"]
        lines.append(f"{result['main_variant']} - {_shown(name)} ({other['variant']}; paired bootstrap over objects): "
                     + ", ".join(parts))
        if other.get("ranking_by_direction"):
            lines.append(f"{_shown(name)} ranking within each push direction: "
                         + ", ".join(f"{d['direction']} {cell(d['ap'])}" for d in other["ranking_by_direction"]))
    if "recalibration" in result or result.get("against"):
        # The lines above subtract the other model from this one; the docs' tables read a candidate
        # "against the default", the other way round, so say which sign is better here.
        lines.append(f"  (a difference below 0 in TV, Brier or ECE, or above 0 in AP or mAP, favours {result['main_variant']})")
    return "\n".join(lines)


def _shown(name: str) -> str:
    """How a model compared with --against is named in tables: as given, a file by its stem
    (reports/x.toml: x)."""
    return Path(name).stem if name.endswith(".toml") else name


def _difference(d: dict) -> str:
    """A paired difference with its interval ("+0.012 [+0.004, +0.020]"); without resamples
    (``--bootstrap 0``) the interval is NaN and only the difference is shown."""
    low, high = d.get("ci") or (None, None)
    if d["difference"] is None or math.isnan(d["difference"]):  # a metric the log cannot define (AP without a topple)
        return "-"
    if low is None or high is None or math.isnan(low) or math.isnan(high):  # None: read back from JSON
        return f"{d['difference']:+.3f}"
    return f"{d['difference']:+.3f} [{low:+.3f}, {high:+.3f}]"


def _rows(result: dict) -> list[tuple[str, dict]]:
    """(name, metrics) of every predictor of a report: the variants, the configured variant
    without its recalibration when it has one (``<variant>_raw``), the models compared with
    ``--against`` (``_shown``), then the references."""
    raw = [(result["recalibration"]["raw"], result["recalibration"]["raw_metrics"])] if "recalibration" in result else []
    against = [(_shown(name), other["metrics"]) for name, other in result.get("against", {}).items()]
    return list(result["variants"].items()) + raw + against + list(result["references"].items())


def plot(result: dict, path: str | Path) -> None:
    """Reliability diagram per variant, and TV / AP per predictor with bootstrap intervals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    ax = axes[0]
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls="--")
    for name, m in _rows(result)[: len(_rows(result)) - len(result["references"])]:
        bins = [b for b in m["reliability"] if b["count"]]
        ax.plot([b["predicted"] for b in bins], [b["observed"] for b in bins], marker="o", label=f"{name} (ECE {m['ece']:.3f})")
    ax.set_xlabel("predicted P(topple)")
    ax.set_ylabel("observed topple frequency")
    ax.set_title("reliability")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    rows = _rows(result)
    x = np.arange(len(rows))
    for ax, key, title in ((axes[1], "tv_informative", "sup-TV, informative pushes (lower is better)"),
                           (axes[2], "ap", "AP of 'it topples' (higher is better)")):
        values = np.array([np.nan if m[key] is None else m[key] for _, m in rows], dtype=float)
        ci = np.array([m.get("ci", {}).get(key, [np.nan, np.nan]) for _, m in rows], dtype=float)
        err = np.abs(np.vstack([values - ci[:, 0], ci[:, 1] - values]))
        colors = ["tab:blue"] * (len(rows) - len(result["references"])) + ["tab:grey"] * len(result["references"])
        ax.bar(x, values, color=colors, yerr=np.nan_to_num(err), capsize=3)
        ax.set_xticks(x, [name.replace("_", " ") for name, _ in rows], fontsize=8, rotation=30, ha="right")
        ax.set_ylim(0, 1)
        ax.set_title(title, fontsize=10)
    c = result["counts"]
    fig.suptitle(f"Model vs push log: {c['objects']} objects, {c['pushes']} pushes, {c['repeats_max']} repeats; "
                 f"bars: {int(100 * CONFIDENCE)}% bootstrap over objects")
    fig.tight_layout()
    write_figure_atomic(path, fig, dpi=100)
    plt.close(fig)


def to_json(value):
    """NaN and infinities become null so the output is strict JSON; numpy scalars become numbers."""
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def _number(value: float) -> float | None:
    return None if not math.isfinite(float(value)) else float(value)


def config_from_args(args: argparse.Namespace) -> Config:
    """``--config`` then ``--set``, through the dataset command's rules (one-line errors)."""
    from ..cli import make_config

    return make_config(argparse.Namespace(config=args.config, overrides=args.overrides, seed=args.seed))


def comparison_models(names: list[str], config: Config) -> dict[str, ToppleConfig]:
    """``--against``'s models: name (as given) -> its ``[topple]`` parameters.

    Only ``[topple]`` is compared: the log is read, and candidates are made, with ``config``'s
    poses and contacts, so both models predict the very same pushes.  A model whose stroke
    (docs/MODEL.md C.10) decides which rows it can score is refused unless ``config`` reads
    the log with that stroke too.
    """
    from ..cli import UsageError, make_config

    models = {}
    for name in names:
        other = make_config(argparse.Namespace(config=name, overrides=[], seed=None)).topple
        if "stroke" in other.applied_corrections and not (
            "stroke" in config.topple.applied_corrections and other.stroke == config.topple.stroke
        ):
            raise UsageError(f"--against {name}: its stroke correction reads the log's push depths; "
                             "score it as --config, or compare with a model of the same stroke")
        models[name] = other
    return models


def main(argv: list[str] | None = None) -> int:
    """``toppledb report LOG...``: score model variants against push logs and write the report."""
    from ..build.corpus import CorpusError, load_corpus
    from ..cli import UsageError, refused_outputs

    parser = argparse.ArgumentParser(prog="toppledb report", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="push-log Parquet files or directories")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="model parameters (default: the dataset's defaults; --config thesis for the thesis's)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS), help="variants to score (default: all)")
    rate = parser.add_mutually_exclusive_group()
    rate.add_argument("--rate", type=float, help="topple rate of the calibration data, for the constant-rate reference")
    rate.add_argument("--rate-from", nargs="+", metavar="LOG", help="calibration log(s) to take that rate from")
    parser.add_argument("--replay", nargs="+", metavar="LOG",
                        help="the same pushes played with other noise draws (`toppledb play --noise-draws 1`), "
                             "scored as the physics_replay reference")
    parser.add_argument("--against", nargs="+", default=[], metavar="PRESET|FILE.toml",
                        help="other models to score on the same pushes, each compared with this one paired over objects "
                             "(their [topple] section: variant, corrections, noise, map), e.g. --against thesis")
    parser.add_argument("--corpus", default="default", help="calibration corpus, to count reported objects inside it (default: %(default)s)")
    parser.add_argument("--exclude-corpus", action="store_true", help="reject rows of corpus objects (a held-out report)")
    parser.add_argument("--bootstrap", type=int, default=BOOTSTRAP, help="resamples over objects (default: %(default)s; 0: none)")
    parser.add_argument("--seed", type=int, default=None, help="model trial streams and bootstrap seed (default: the config's)")
    parser.add_argument("--out", type=Path, default=Path("data/reports/validation.json"), help="JSON report (default: %(default)s)")
    parser.add_argument("--plot", type=Path, default=None, metavar="PNG", help="also draw the report")
    args = parser.parse_args(argv)
    if refused_outputs(args.out, figures=(args.plot,)):
        return 2

    started = time.perf_counter()
    try:
        config = config_from_args(args)
        # The compared models first: a bad name fails before minutes of log reading.
        against = comparison_models(args.against, config)
        corpus = load_corpus(args.corpus, config.mesh.default_mass) if args.corpus else None
        log = read_log(args.logs, config, corpus, exclude_corpus=args.exclude_corpus)
        if not log.pushes:
            raise UsageError(f"no usable pushes in {' '.join(args.logs)} ({log.rows} rows; rejected: {dict(log.rejected)})")
        rate_value, rate_source = args.rate, None
        if args.rate_from:
            calibration = read_log(args.rate_from, config)
            rate_value, rate_source = observed_topple_rate(calibration), " ".join(args.rate_from)
        if rate_value is not None and not 0.0 <= rate_value <= 1.0:
            raise UsageError(f"--rate must be in [0, 1], got {rate_value}")
        replay = read_log(args.replay, config, corpus, exclude_corpus=args.exclude_corpus) if args.replay else None
        result = report(log, config, tuple(args.variants), rate=rate_value, rate_source=rate_source,
                        n_resamples=args.bootstrap, seed=config.seed, replay=replay, against=against)
    except (UsageError, CorpusError, LogError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    result["wall_s"] = round(time.perf_counter() - started, 1)
    # Which file the variant's rows are: a table row reads "corrected" whatever --config gave.
    result["model"] = " ".join(filter(None, [str(args.config or "the defaults"), *(f"--set {o}" for o in args.overrides)]))
    print(format_report(result))
    write_text_atomic(args.out, json.dumps(to_json(result), indent=1, allow_nan=False) + "\n")
    print(f"report: {args.out} ({result['wall_s']} s)")
    if args.plot:
        plot(result, args.plot)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
