"""Refit the maps of P(topple) on push logs: the monotone map g (docs/MODEL.md C.7), or with --down, --side,
--boosted, --features the maps of C.15, C.16, C.19, C.13, or with --all-maps every map in the engine's order.

Without an option, the monotone map: the model's raw P(topple) of every logged push (``scoring.Scorer`` with the configuration's
recalibration removed) is set against the observed topple frequency.  Each method of
``pipeline.model.recalibration.METHODS`` is cross-validated with folds grouped by object
(``calibrate.grouped_folds``): fitted on the other folds' pushes, applied to the fold's.
The method with the lowest pooled held-out Brier score (``SELECT_BY``) is fitted once more on all pushes and its
knots are written as a config TOML (``toppledb dataset --config FILE``, ``toppledb report
--config FILE``).  Only corpus objects are read (``--corpus``); nothing here reads a held-out
log: ``toppledb report`` judges the result there.

    toppledb recalibrate data/logs/corpus --folds 6 --seed 0 \\
        --out reports/recalibrated_corrected.toml --json reports/recalibration.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from ..build.atomic import write_atomic
from ..build.corpus import Corpus, write_list
from ..model.boosted_map import FEATURES as BOOSTED_FEATURES
from ..model.boosted_map import FIT_PARAMS, boosted_probability, fit_trees, trees_from_dict
from ..model.config import MAP_FIELDS, NO_MAP, Config, MDPConfig, ToppleConfig, maps_unjudged_choices
from ..model.feature_map import (
    DOWN_FEATURES,
    FEATURES,
    SIDE_FEATURES,
    SIDE_Z,
    FeatureMapError,
    fit_weights,
    mapped_probability,
    pressed_down,
)
from ..model.recalibration import METHODS, RecalibrationError, fit, fit_logistic, predict
from .calibrate import CalibrationError, grouped_folds, write_outputs
from .logreader import LogError, PushLog, read_log
from .scoring import Scorer
from .validation import TOPPLES, average_precision, push_metrics, reliability

SELECT_BY = "brier"
"""Held-out metric that chooses the method: the Brier score, a proper scoring rule, which
rewards calibration and penalises lost ranking.  Not the ECE: ten bins reward flattening
the map, and isotonic's flat steps tie pushes whose order the model knew (on the corpus log
isotonic's held-out ECE was 0.004 lower than logistic's, and its AP 0.046 lower)."""


def brier(predicted: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> float:
    """Mean squared error of predicted P(topple) against each repeat's outcome, weighted by repeats.

    predicted, observed : (n,) float;  weight : (n,) repeats.  Per push, the mean over its
    repeats of (q - outcome)^2 is (q - f)^2 + f (1 - f) with f the observed frequency.
    """
    per_push = (predicted - observed) ** 2 + observed * (1 - observed)
    return float(np.average(per_push, weights=weight))


def metrics(predicted: np.ndarray, observed: np.ndarray, weight: np.ndarray, objects: np.ndarray) -> dict[str, float]:
    """ECE, Brier, AP, mAP and the mean predicted and observed rates of one set of predictions."""
    m = push_metrics(np.zeros(len(predicted)), predicted, observed, objects)
    return {"ece": m["ece"], "brier": brier(predicted, observed, weight), "ap": m["ap"], "map": m["map"],
            "predicted": float(np.mean(predicted)), "observed": float(np.mean(observed))}


def cross_validate(
    p: np.ndarray, observed: np.ndarray, weight: np.ndarray, objects: np.ndarray, object_ids: list[str], folds: int, seed: int
) -> dict:
    """Held-out predictions of every method over object-grouped folds.

    p : (n,) float, raw predicted P(topple);  observed : (n,) float;  weight : (n,) repeats
    objects : (n,) int index into ``object_ids``
    returns : {"folds": [object ids per fold], "methods": {name: pooled held-out metrics}, "identity": ...}
    """
    per_object = {name: int(np.sum(objects == i)) for i, name in enumerate(object_ids)}
    fold_objects = grouped_folds(per_object, folds, seed)
    fold_of = np.empty(len(p), dtype=int)
    for f, names in enumerate(fold_objects):
        for name in names:
            fold_of[objects == object_ids.index(name)] = f
    out = {"folds": fold_objects, "methods": {}, "per_fold": {}}
    for method in METHODS:
        held_out = np.empty(len(p))
        fold_metrics = []
        for f in range(folds):
            train, test = fold_of != f, fold_of == f
            knots = fit(method, p[train], observed[train], weight[train])
            held_out[test] = predict(p[test], knots)
            fold_metrics.append(metrics(held_out[test], observed[test], weight[test], objects[test]))
        out["methods"][method] = metrics(held_out, observed, weight, objects)
        out["per_fold"][method] = fold_metrics
    out["identity"] = metrics(p, observed, weight, objects)
    return out


def recalibrate(log: PushLog, config: Config | None = None, *, folds: int = 6, seed: int = 0,
                methods: tuple[str, ...] = METHODS) -> dict:
    """Cross-validate every method on ``log``, fit the best of ``methods`` on all of it; a
    JSON-ready record with ``chosen`` (method) and ``knots`` ({"x", "y"})."""
    unknown = set(methods) - set(METHODS)
    if not methods or unknown:
        raise RecalibrationError(f"unknown recalibration method(s) {', '.join(sorted(unknown)) or '(none given)'}; choose from {', '.join(METHODS)}")
    config = config or Config()
    started = time.perf_counter()
    scorer = Scorer(log, config.seed, config.contacts)
    raw = config.topple.without_recalibration()
    p = scorer.score(raw).p_topple
    observed, weight, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    cv = cross_validate(p, observed, weight, objects, scorer.object_ids, folds, seed)
    chosen = min(methods, key=lambda m: (cv["methods"][m][SELECT_BY], METHODS.index(m)))
    knots = fit(chosen, p, observed, weight)
    fitted = predict(p, knots)
    return {
        "variant": config.topple.variant,
        "pushes": len(p),
        "pushes_fitted": int(np.sum(p > 0)),
        "objects": len(scorer.object_ids),
        "folds": folds,
        "seed": seed,
        "select_by": SELECT_BY,
        "cross_validated": cv,
        "methods": list(methods),
        "chosen": chosen,
        "knots": {"x": list(knots.x), "y": list(knots.y)},
        "logistic": dict(zip(("a", "b"), fit_logistic(p[p > 0], observed[p > 0], weight[p > 0]))),
        "in_sample": {"raw": metrics(p, observed, weight, objects), "recalibrated": metrics(fitted, observed, weight, objects),
                      "reliability_raw": reliability(p, observed)["bins"],
                      "reliability_recalibrated": reliability(fitted, observed)["bins"]},
        "ap_unchanged": bool(np.isclose(average_precision(fitted, observed > TOPPLES), average_precision(p, observed > TOPPLES))),
        "counts": log.counts(),
        "wall_s": round(time.perf_counter() - started, 1),
    }


def metrics_by_predictor(predictions: dict[str, np.ndarray], rows: np.ndarray, observed: np.ndarray,
                         weight: np.ndarray, objects: np.ndarray) -> dict:
    """Each named predictor's ``metrics`` over ``rows`` ((n,) bool), and how many pushes those are
    ({"pushes": 0} alone when none).  predictions : name -> (n,) float, held-out P(topple)"""
    if not rows.any():
        return {"pushes": 0}
    return {**{name: metrics(predicted[rows], observed[rows], weight[rows], objects[rows]) for name, predicted in predictions.items()},
            "pushes": int(rows.sum())}


def map_record(config: Config, features: tuple[str, ...], weights: np.ndarray, pushes: int, objects: int, folds: int,
               seed: int, fold_objects: list[list[str]], started: float, **results) -> dict:
    """The JSON-ready record of a cross-validated logistic map (the feature, down and side maps):
    what was fitted, on how much, with which folds, ``results`` (its metrics and anything of its
    own) and the wall time since ``started`` (``time.perf_counter``)."""
    return {"variant": config.topple.variant, "features": list(features), "weights": [float(w) for w in weights],
            "pushes": pushes, "objects": objects, "folds": folds, "seed": seed, **results,
            "fold_objects": fold_objects, "wall_s": round(time.perf_counter() - started, 1)}


def push_folds(objects: list[str], folds: int, seed: int) -> tuple[list[list[str]], np.ndarray]:
    """Folds grouped by object over pushes from any number of logs (``grouped_folds``).

    objects : (n,) the object id of each push, every log's pushes in one list
    returns : object ids per fold;  (n,) int, the fold of each push (one per object)
    """
    counts: dict[str, int] = {}
    for name in objects:
        counts[name] = counts.get(name, 0) + 1
    fold_objects = grouped_folds(counts, folds, seed)
    return fold_objects, fold_of_pushes(objects, fold_objects)


def fold_of_pushes(objects: list[str], fold_objects: list[list[str]]) -> np.ndarray:
    """(n,) int, the fold of each push's object; every object must be in exactly one fold.

    objects : (n,) the object id of each push;  fold_objects : object ids per fold
    """
    fold_of_object: dict[str, int] = {}
    for f, members in enumerate(fold_objects):
        for name in members:
            if name in fold_of_object:
                raise RecalibrationError(f"object {name!r} is in folds {fold_of_object[name]} and {f}; a fold list holds each object once")
            fold_of_object[name] = f
    outside = sorted(set(objects) - set(fold_of_object))
    if outside:
        raise RecalibrationError(f"{len(outside)} logged object(s) in no fold: {', '.join(outside[:5])}"
                                 f"{' ...' if len(outside) > 5 else ''}")
    return np.array([fold_of_object[name] for name in objects], dtype=int)


def out_of_fold(features: np.ndarray, p: np.ndarray, lands: np.ndarray, fold_of: np.ndarray, fold_maps: list) -> np.ndarray:
    """P(topple) of each push under the boosted map of its object's fold; P kept where the model knows
    no landing (the engine keeps such a row) and where it has none (NaN).

    features : (n, F) float;  p : (n,) float, P without the boosted map;  lands : (n,) bool
    fold_of : (n,) int;  fold_maps : each fold's trees (``BoostedTrees``)
    """
    q = p.copy()
    for k, trees in enumerate(fold_maps):
        rows = (fold_of == k) & np.isfinite(p) & lands
        q[rows] = boosted_probability(features[rows], trees)
    return q


def read_fold_lists(directory: Path) -> list[list[str]]:
    """The folds an earlier ``--fold-maps DIR`` wrote: object ids of ``fold_0.csv``, ``fold_1.csv``, ...

    Two maps fitted on the same folds build corpus datasets out of fold of the same objects, so
    their policies can be played on the same trials, object by object."""
    from ..build.corpus import CorpusError, read_list

    folds = []
    while (directory / f"fold_{len(folds)}.csv").is_file():
        try:
            specs = read_list(directory / f"fold_{len(folds)}.csv", 1.0).specs
        except CorpusError as err:  # its message names the file
            raise RecalibrationError(str(err)) from None
        folds.append([spec.object_id for spec in specs])
    if len(folds) < 2:
        raise RecalibrationError(f"{directory} holds {len(folds)} fold list(s) (fold_0.csv, fold_1.csv, ...); "
                                 "cross-validation needs at least 2")
    return folds


def feature_recalibrate(logs: list[tuple[str, PushLog]], config: Config | None = None, *, folds: int = 6, seed: int = 0) -> dict:
    """Cross-validate the feature map (docs/MODEL.md C.13) over ``logs`` together, fit it on all.

    logs : (name, log) pairs, each read on its own (two logs may reuse push ids); an object's
      pushes in every log fall in one fold
    returns : a JSON-ready record with ``weights`` (one per ``FEATURES``), the pooled and per-log
      held-out metrics of the map beside the unmapped P (``identity``)
    """
    config = config or Config()
    started = time.perf_counter()
    raw = config.topple.without_recalibration()
    parts = []
    for name, log in logs:
        scorer = Scorer(log, config.seed, config.contacts)
        features, p = scorer.features(raw)
        parts.append({"name": name, "features": features, "p": p, "observed": scorer.empirical_topple,
                      "weight": scorer.repeats.astype(float), "objects": [scorer.object_ids[i] for i in scorer.object_index],
                      "counts": log.counts()})
    features = np.vstack([part["features"] for part in parts])
    p, observed, weight = (np.concatenate([part[key] for part in parts]) for key in ("p", "observed", "weight"))
    names = [name for part in parts for name in part["objects"]]
    object_ids, objects = np.unique(names, return_inverse=True)
    object_ids = object_ids.tolist()
    source = np.repeat(np.arange(len(parts)), [len(part["p"]) for part in parts])
    fold_objects, fold_of = push_folds(names, folds, seed)
    held_out, weights = cross_validated_map(features, observed, weight, fold_of, folds, np.ones(len(p), dtype=bool), "feature map")

    def both(rows: np.ndarray) -> dict:
        return metrics_by_predictor({"identity": p, "feature_map": held_out}, rows, observed, weight, objects)

    return map_record(config, FEATURES, weights, len(p), len(object_ids), folds, seed, fold_objects, started,
                      cross_validated=both(np.ones(len(p), dtype=bool)),
                      per_log=[{"log": part["name"], **both(source == i), "counts": part["counts"]} for i, part in enumerate(parts)])


def down_recalibrate(log: PushLog, config: Config | None = None, *, folds: int = 6, seed: int = 0,
                     scorer: Scorer | None = None) -> dict:
    """Cross-validate the down map (docs/MODEL.md C.15) beside the centred map, fit both on all.

    Every fold fits the centred map (C.7) on all its training pushes and the down map on the
    training pushes below ``topple.down_map_z`` (``feature_map.pressed_down``); the held-out pushes
    below it get the down map's q (0 where the model knows of no landing, as the engine has it),
    the rest the centred map's.  ``centred`` is the same folds with no down map: the comparison
    the down map is adopted by.
    returns : a JSON-ready record with ``weights`` (one per ``DOWN_FEATURES``), ``knots`` (the
      centred map on all pushes), pooled held-out metrics of both (all pushes and the down ones)
    scorer : ``Scorer(log, config.seed, config.contacts)`` made already, whose pose candidates are reused
    """
    config = config or Config()
    started = time.perf_counter()
    scorer = scorer if scorer is not None else Scorer(log, config.seed, config.contacts)
    features, p, lands = scorer.down_map_inputs(config.topple)
    observed, weight, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    # As the engine takes them: the evaluated push's direction, and only pushes with a P.
    down = pressed_down(features[:, DOWN_FEATURES.index("direction_z")], config.topple.down_map_z) & np.isfinite(p)
    if down.sum() < len(DOWN_FEATURES):
        raise RecalibrationError(f"{int(down.sum())} pushes with u_z < {config.topple.down_map_z} are too few to fit "
                                 f"{len(DOWN_FEATURES)} weights")
    fold_objects, fold_of = push_folds([scorer.object_ids[i] for i in objects], folds, seed)
    centred = np.empty(len(p))
    for f in range(folds):
        train, test = fold_of != f, fold_of == f
        centred[test] = predict(p[test], fit("centred", p[train], observed[train], weight[train]))
    held_out, weights = cross_validated_map(features, observed, weight, fold_of, folds, down, "down map")
    mapped = np.where(down, np.where(lands, held_out, 0.0), centred)  # no known landing: no topple, as the engine
    knots = fit("centred", p, observed, weight)

    def both(rows: np.ndarray) -> dict:
        return metrics_by_predictor({"identity": p, "centred": centred, "down_map": mapped}, rows, observed, weight, objects)

    return map_record(config, DOWN_FEATURES, weights, len(p), len(scorer.object_ids), folds, seed, fold_objects, started,
                      down_map_z=config.topple.down_map_z, knots={"x": list(knots.x), "y": list(knots.y)},
                      cross_validated=both(np.ones(len(p), dtype=bool)), pushes_without_landing=int(np.sum(down & ~lands)),
                      down_pushes=both(down), other_pushes=both(~down), counts=log.counts())


def cross_validated_map(features: np.ndarray, observed: np.ndarray, weight: np.ndarray, fold_of: np.ndarray, folds: int,
                        rows: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """A logistic map (``fit_weights``) fitted on ``rows`` of each fold's training pushes and
    predicting its held-out ones, then on all ``rows``.

    features : (n, F) float;  observed, weight : (n,) float;  fold_of : (n,) int in [0, folds);  rows : (n,) bool
    returns : held_out (n,) float, each row's q from the other folds (NaN outside ``rows``);
      weights (F,) float, the fit on every row.  Raises ``RecalibrationError`` when a fold leaves
      no row to fit on, ``FeatureMapError`` when the fit does not converge."""
    held_out = np.full(len(observed), np.nan)
    for f in range(folds):
        train, test = (fold_of != f) & rows, (fold_of == f) & rows
        if not train.any():
            raise RecalibrationError(f"fold {f} leaves no push to fit the {name} on; use fewer folds")
        held_out[test] = mapped_probability(features[test], fit_weights(features[train], observed[train], weight[train]))
    weights = fit_weights(features[rows], observed[rows], weight[rows])
    if not np.all(np.isfinite(weights)):
        raise FeatureMapError(f"the {name}'s fit did not converge (weights {weights.tolist()})")
    return held_out, weights


def side_recalibrate(log: PushLog, config: Config | None = None, *, folds: int = 6, seed: int = 0,
                     scorer: Scorer | None = None) -> dict:
    """Cross-validate the side map (docs/MODEL.md C.16) on top of ``config``'s other maps, fit it on all.

    Every fold fits the weights on its training pushes the map takes (``feature_map.side_rows``:
    side pushes with P inside ``topple.side_map_band``) and maps its held-out ones; the other pushes keep P.
    ``identity`` is P as the model without a side map gives it: the comparison the map is adopted by.
    returns : a JSON-ready record with ``weights`` (one per ``SIDE_FEATURES``) and pooled held-out
      metrics of both (all pushes and the mapped ones)
    scorer : ``Scorer(log, config.seed, config.contacts)`` made already, whose pose candidates are reused
    """
    config = config or Config()
    started = time.perf_counter()
    scorer = scorer if scorer is not None else Scorer(log, config.seed, config.contacts)
    features, p, side = scorer.side_map_inputs(config.topple)
    band = config.topple.side_map_band
    observed, weight, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    if side.sum() < 2 * len(SIDE_FEATURES):
        raise RecalibrationError(f"{int(side.sum())} side pushes with {band[0]} < P < {band[1]} are too few to fit "
                                 f"{len(SIDE_FEATURES)} weights")
    fold_objects, fold_of = push_folds([scorer.object_ids[i] for i in objects], folds, seed)
    held_out, weights = cross_validated_map(features, observed, weight, fold_of, folds, side, "side map")
    mapped = np.where(side, held_out, p)

    def both(rows: np.ndarray) -> dict:
        return metrics_by_predictor({"identity": p, "side_map": mapped}, rows, observed, weight, objects)

    return map_record(config, SIDE_FEATURES, weights, len(p), len(scorer.object_ids), folds, seed, fold_objects, started,
                      band=list(band), side_z=SIDE_Z, cross_validated=both(np.isfinite(p)), side_pushes=both(side),
                      counts=log.counts())


def boosted_recalibrate(log: PushLog, config: Config | None = None, *, folds: int = 6, seed: int = 0,
                        fold_objects: list[list[str]] | None = None, scorer: Scorer | None = None) -> dict:
    """Cross-validate the boosted map (docs/MODEL.md C.19) on top of ``config``'s other maps, fit it on all.

    Every fold fits trees (``boosted_map.fit_trees``, ``FIT_PARAMS``) on its training pushes and maps its
    held-out ones; a push the model knows no landing for keeps P.  ``identity`` is P as the model without a
    boosted map gives it.
    returns : a JSON-ready record with ``trees`` (``boosted_map.trees_from_dict``'s layout, fitted on every
      push), ``fold_trees`` (fold k's, fitted without the objects of ``fold_objects[k]``: what maps them
      out of fold, ``write_fold_maps``) and pooled held-out metrics of both
    fold_objects : the folds to use (``read_fold_lists``) instead of ``folds`` drawn with ``seed``
    scorer : ``Scorer(log, config.seed, config.contacts)`` made already, whose pose candidates are reused
    """
    config = config or Config()
    started = time.perf_counter()
    scorer = scorer if scorer is not None else Scorer(log, config.seed, config.contacts)
    observed, weight, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    names = [scorer.object_ids[i] for i in objects]
    if fold_objects is None:
        fold_objects, fold_of = push_folds(names, folds, seed)
    else:  # before the model scores every push: a log object in no fold is refused at once
        fold_of, folds = fold_of_pushes(names, fold_objects), len(fold_objects)
    features, p, lands = scorer.boosted_inputs(config.topple)
    rows = np.isfinite(p)
    fold_trees = []
    for f in range(folds):
        train = (fold_of != f) & rows
        if not train.any():
            raise RecalibrationError(f"fold {f} leaves no push to fit the boosted map on; use fewer folds")
        fold_trees.append(fit_trees(features[train], observed[train], scorer.repeats[train], seed))
    held_out = out_of_fold(features, p, lands, fold_of, [trees_from_dict(trees) for trees in fold_trees])
    fitted = fit_trees(features[rows], observed[rows], scorer.repeats[rows], seed)
    metrics_of = metrics_by_predictor({"identity": p, "boosted_map": held_out}, rows, observed, weight, objects)
    return {"variant": config.topple.variant, "features": list(BOOSTED_FEATURES), "fit": {**FIT_PARAMS, "random_state": seed},
            "pushes": int(rows.sum()), "objects": len(scorer.object_ids), "folds": folds, "seed": seed,
            "cross_validated": metrics_of, "fold_objects": fold_objects, "counts": log.counts(),
            "wall_s": round(time.perf_counter() - started, 1), "trees": fitted, "fold_trees": fold_trees}


def all_maps_recalibrate(log: PushLog, config: Config | None = None, *, folds: int = 6, seed: int = 0) -> dict:
    """Refit every map of P(topple) in the order the engine applies them (docs/MODEL.md C.19): the centred
    and down maps on the unmapped P (``down_recalibrate``), the side map over them (``side_recalibrate``),
    the boosted map over all three (``boosted_recalibrate``).  What three ``toppledb recalibrate`` runs,
    each on the file the last one wrote, give from the defaults or a file of [topple] values (each step here
    keeps ``config`` whole, its side map's band too, where the chain's files carry [topple] alone); the base
    model's own maps are replaced.

    Each step's cross-validation holds the earlier steps' maps at their fit on every push, so its
    held-out figures are a step's own gain, not the chain's: ``toppledb report`` on objects outside the
    log judges the chain.  The steps share the folds (the same log, seed and object order).
    returns : {"down", "side", "boosted": each step's record (``fold_trees`` dropped), "maps": the
      [topple] values fitted (``boosted_map`` is the trees, to be written to a file), and the log's
      ``variant``, ``pushes``, ``objects``, ``wall_s``}
    """
    config = config or Config()
    started = time.perf_counter()
    scorer = Scorer(log, config.seed, config.contacts)  # its pose candidates serve every step: seed and contacts stay
    down = down_recalibrate(log, config, folds=folds, seed=seed, scorer=scorer)
    maps = {**NO_MAP, "recalibration_x": tuple(down["knots"]["x"]), "recalibration_y": tuple(down["knots"]["y"]),
            "down_map": tuple(down["weights"]), "down_map_z": down["down_map_z"]}
    # Scoring reads no [mdp] value; the cut only lets a down map without the boosted map be a Config.
    cut = max(config.mdp.min_direction_z, down["down_map_z"])
    config = dataclasses.replace(config, topple=dataclasses.replace(config.topple, **maps),
                                 mdp=dataclasses.replace(config.mdp, min_direction_z=cut))
    side = side_recalibrate(log, config, folds=folds, seed=seed, scorer=scorer)
    maps.update(side_map=tuple(side["weights"]), side_map_band=tuple(side["band"]))
    config = dataclasses.replace(config, topple=dataclasses.replace(config.topple, **maps))
    boosted = boosted_recalibrate(log, config, folds=folds, seed=seed, scorer=scorer)
    boosted.pop("fold_trees")  # fitted over maps that saw every object: no fold's map is out of fold
    maps["boosted_map"] = boosted.pop("trees")
    return {"variant": config.topple.variant, "pushes": down["pushes"], "objects": down["objects"], "folds": folds,
            "seed": seed, "down": down, "side": side, "boosted": boosted, "maps": maps,
            "wall_s": round(time.perf_counter() - started, 1)}


def write_fold_maps(directory: Path, fold_trees: list[dict], fold_objects: list[list[str]], corpus: Corpus) -> list[Path]:
    """Each fold's boosted map and its objects' corpus list, to build the corpus out of fold.

    A dataset of the corpus built with the map fitted on the same objects is judged on the map's own
    training set: its planners' pushes look better there than on new objects (docs/VALIDATION.md,
    stop 44).  Fold k's objects built with fold k's map (fitted without them) are not:
    ``toppledb dataset --corpus DIR/fold_k.csv --set topple.boosted_map=DIR/fold_k.trees.json``.
    corpus : holds every object of ``fold_objects`` (``main`` reads the logs with ``corpus_only``)
    returns : the corpus lists written, fold by fold (absolute mesh paths)"""
    directory.mkdir(parents=True, exist_ok=True)
    by_id = {spec.object_id: spec for spec in corpus.specs}
    lists = []
    for k, (trees, members) in enumerate(zip(fold_trees, fold_objects)):
        write_trees_file(trees, directory / f"fold_{k}.trees.json")  # datasets built out of fold name it by path
        lists.append(directory / f"fold_{k}.csv")
        write_list([by_id[name] for name in sorted(members)], lists[-1], None)
    return lists


def format_boosted_record(result: dict) -> str:
    """``boosted_recalibrate``'s record as the table ``toppledb recalibrate --boosted`` prints."""
    lines = [f"{result['pushes']} pushes on {result['objects']} objects; {result['folds']}-fold CV grouped by object, held-out folds pooled:",
             f"{'predictor':<12} {'ECE':>6} {'Brier':>7} {'AP':>6} {'mAP':>6} {'mean pred.':>10} {'observed':>8}"]
    for name, m in result["cross_validated"].items():
        if isinstance(m, dict) and "brier" in m:
            lines.append(f"{name:<12} {m['ece']:6.3f} {m['brier']:7.4f} {m['ap']:6.3f} {m['map']:6.3f} {m['predicted']:10.3f} {m['observed']:8.3f}")
    return "\n".join(lines)


def format_side_record(result: dict) -> str:
    """``side_recalibrate``'s record as the table ``toppledb recalibrate --side`` prints."""
    lines = [(f"{result['pushes']} pushes on {result['objects']} objects ({result['side_pushes']['pushes']} side pushes with "
              f"{result['band'][0]} < P < {result['band'][1]}); {result['folds']}-fold CV grouped by object, held-out folds pooled:"),
             f"{'pushes':<24} {'predictor':<10} {'ECE':>6} {'Brier':>7} {'AP':>6} {'mAP':>6} {'mean pred.':>10} {'observed':>8}"]
    for name, key in [("all", "cross_validated"), ("mapped", "side_pushes")]:
        for predictor in ("identity", "side_map"):
            m = result[key][predictor]
            lines.append(f"{name:<24} {predictor:<10} {m['ece']:>6.3f} {m['brier']:>7.4f} {m['ap']:>6.3f} {m['map']:>6.3f} "
                         f"{m['predicted']:>10.3f} {m['observed']:>8.3f}")
    lines.append("weights: " + ", ".join(f"{n} {w:+.3f}" for n, w in zip(result["features"], result["weights"])))
    return "\n".join(lines)


def format_down_record(result: dict) -> str:
    """``down_recalibrate``'s record as the table ``toppledb recalibrate --down`` prints."""
    lines = [(f"{result['pushes']} pushes on {result['objects']} objects ({result['down_pushes']['pushes']} with u_z < "
              f"{result['down_map_z']}); {result['folds']}-fold CV grouped by object, held-out folds pooled:"),
             f"{'pushes':<24} {'predictor':<10} {'ECE':>6} {'Brier':>7} {'AP':>6} {'mAP':>6} {'mean pred.':>10} {'observed':>8}"]
    for name, key in [("all", "cross_validated"), (f"u_z < {result['down_map_z']}", "down_pushes"), ("the others", "other_pushes")]:
        for predictor in ("identity", "centred", "down_map") if result[key]["pushes"] else ():
            m = result[key][predictor]
            lines.append(f"{name:<24} {predictor:<10} {m['ece']:>6.3f} {m['brier']:>7.4f} {m['ap']:>6.3f} {m['map']:>6.3f} "
                         f"{m['predicted']:>10.3f} {m['observed']:>8.3f}")
    lines.append("weights: " + ", ".join(f"{n} {w:+.3f}" for n, w in zip(result["features"], result["weights"])))
    return "\n".join(lines)


def format_feature_record(result: dict) -> str:
    lines = [(f"{result['pushes']} pushes on {result['objects']} objects; {result['folds']}-fold CV grouped by object, "
              f"held-out folds pooled (identity: P as the model gives it, unfitted):"),
             f"{'pushes':<28} {'predictor':<12} {'ECE':>6} {'Brier':>7} {'AP':>6} {'mAP':>6} {'mean pred.':>10} {'observed':>8}"]
    for name, cell in [("pooled", result["cross_validated"])] + [(cell["log"], cell) for cell in result["per_log"]]:
        for predictor in ("identity", "feature_map"):
            m = cell[predictor]
            lines.append(f"{name[-28:]:<28} {predictor:<12} {m['ece']:>6.3f} {m['brier']:>7.4f} {m['ap']:>6.3f} {m['map']:>6.3f} "
                         f"{m['predicted']:>10.3f} {m['observed']:>8.3f}")
    lines.append("weights: " + ", ".join(f"{f} {w:+.4f}" for f, w in zip(result["features"], result["weights"])))
    return "\n".join(lines)


def format_record(result: dict) -> str:
    cv = result["cross_validated"]
    lines = [(f"{result['pushes']} pushes on {result['objects']} objects ({result['pushes_fitted']} with P(topple) > 0 are fitted); "
              f"{result['folds']}-fold CV grouped by object, held-out folds pooled:"),
             f"{'method':<10} {'ECE':>6} {'Brier':>7} {'AP':>6} {'mAP':>6} {'mean pred.':>10} {'observed':>8}"]
    for name, m in [("identity", cv["identity"])] + list(cv["methods"].items()):
        lines.append(f"{name:<10} {m['ece']:>6.3f} {m['brier']:>7.4f} {m['ap']:>6.3f} {m['map']:>6.3f} {m['predicted']:>10.3f} {m['observed']:>8.3f}")
    lines.append(f"chosen by held-out {result['select_by']}: {result['chosen']} ({len(result['knots']['x'])} knots)")
    return "\n".join(lines)


def kept_maps(topple: ToppleConfig) -> dict:
    """The [topple] map values a fit on top of the model's maps writes back unchanged (--side, --boosted):
    every map field, the down map's cut and the side map's band, which belong to their weights."""
    return {**{name: getattr(topple, name) for name in MAP_FIELDS}, "down_map_z": topple.down_map_z,
            "side_map_band": topple.side_map_band}


def ece_brier(m: dict) -> str:
    """A predictor's held-out metrics (``metrics``) as the TOML comments give them: "ECE / Brier"."""
    return f"{m['ece']:.3f} / {m['brier']:.4f}"


def with_and_without(cv: dict, name: str, folds: int, seed: int | str) -> str:
    """The TOML comment line of a map fitted on top of the others: held-out ECE and Brier without and with it.

    seed : the folds' seed, or where they were read from"""
    drawn = f"seed {seed}" if isinstance(seed, int) else f"the folds of {seed}"
    return (f"{folds}-fold CV grouped by object ({drawn}), held-out ECE / Brier: without it "
            f"{ece_brier(cv['identity'])}, with it {ece_brier(cv[name])}")


IN_SAMPLE_UNDER = ("note: {under}, so the 'identity' row, the model without the map fitted here, is scored on pushes its "
                   "maps were fitted on and can read better than it does on new objects; judge the file with toppledb report "
                   "on objects outside the log")
"""Printed where a map is cross-validated over maps fitted on the same pushes: its folds refit the map, not
the maps under it (on a log of value iteration's pushes, stop 66, the boosted map read 0.1035 -> 0.1179 in
Brier this way, and helped on held-out objects; docs/VALIDATION.md)."""


def trees_path(out: Path) -> Path:
    """Where a fitted boosted map goes beside the config TOML ``out`` (suffix .trees.json), absolute.  The TOML
    names it by its file name, which ``Config.from_toml`` reads beside the TOML, so the two move together.
    To ship a map with the package, copy it into pipeline/model/presets/."""
    return out.with_suffix(".trees.json").resolve()


def write_trees(trees: dict, out: Path) -> str:
    """Write a fitted boosted map to ``trees_path(out)`` (``write_trees_file``).  returns : the path written"""
    path = trees_path(out)
    write_trees_file(trees, path)
    return str(path)


def write_trees_file(trees: dict, path: Path) -> None:
    """A boosted map's trees as compact JSON at ``path``, atomically and never over a file there
    (``FileExistsError``): config files and datasets' parameters name trees by path."""
    write_atomic(path, lambda temp: temp.write_text(json.dumps(trees, separators=(",", ":"))), exclusive=True)


def main(argv: list[str] | None = None) -> int:
    """``toppledb recalibrate LOG...``: fit g on corpus pushes, write a config TOML and a JSON record."""
    from ..build.corpus import CorpusError, load_corpus
    from ..cli import UsageError, refused_outputs
    from .validation import config_from_args

    parser = argparse.ArgumentParser(prog="toppledb recalibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="push logs (Parquet files or directories) on corpus objects")
    parser.add_argument("--folds", type=int, default=6, help="cross-validation folds, grouped by object (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the folds and the model's trials (default: %(default)s)")
    parser.add_argument("--corpus", default="default", help="fit only on this corpus's objects ('none': any object; default: %(default)s)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="the model to recalibrate (default: the defaults); its own recalibration is ignored")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--out", type=Path, default=Path("data/reports/recalibrated.toml"), help="config TOML to write (default: %(default)s)")
    parser.add_argument("--json", type=Path, default=Path("data/reports/recalibration.json"), help="full record (default: %(default)s)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS, metavar="METHOD",
                        help=f"monotone maps cross-validation chooses among (all are scored): {' '.join(METHODS)} (default: all)")
    parser.add_argument("--features", action="store_true",
                        help="fit the feature map (docs/MODEL.md C.13) instead of a monotone map; each LOG is read on its own")
    parser.add_argument("--down", action="store_true",
                        help="fit the centred map and, for pushes with u_z < topple.down_map_z, the down map (docs/MODEL.md C.15)")
    parser.add_argument("--side", action="store_true",
                        help="fit the side map (docs/MODEL.md C.16) on top of the model's other maps, which are kept")
    parser.add_argument("--boosted", action="store_true",
                        help=("fit the boosted map (docs/MODEL.md C.19) on top of the model's other maps, which are kept; "
                              "its trees go to OUT with the suffix .trees.json, which the TOML names"))
    parser.add_argument("--all-maps", action="store_true",
                        help=("refit every map in the engine's order: the centred and down maps, the side map over them, "
                              "the boosted map over all three (what --down, --side, --boosted in turn give); "
                              "its trees go to OUT with the suffix .trees.json"))
    parser.add_argument("--fold-maps", type=Path, metavar="DIR",
                        help=("with --boosted: also write each fold's map (fitted without its objects) and its objects' "
                              "corpus list to DIR, to build the corpus out of fold (fold_K.trees.json, fold_K.csv)"))
    parser.add_argument("--folds-from", type=Path, metavar="DIR",
                        help=("with --boosted: the folds an earlier --fold-maps DIR wrote, instead of drawing them "
                              "(--folds and --seed's folds are ignored), so two maps' corpus datasets out of fold hold the same objects"))
    args = parser.parse_args(argv)
    if refused_outputs(args.out, args.json, directories=(args.fold_maps,)):
        return 2

    try:
        if args.features + args.down + args.side + args.boosted + args.all_maps > 1:
            raise UsageError("--features, --down, --side, --boosted and --all-maps fit different maps; choose one")
        for option, given in (("--fold-maps", args.fold_maps), ("--folds-from", args.folds_from)):
            if given is not None and args.all_maps:
                # Out of fold means no map under the fold's trees saw the fold's objects either.
                raise UsageError(f"{option} is for the boosted map fitted alone (--boosted): under --all-maps it sits on "
                                 "maps fitted on every object, so no fold's map would be out of fold")
            if given is not None and not args.boosted:
                raise UsageError(f"{option} {'writes' if option == '--fold-maps' else 'gives'} the boosted map's folds; give --boosted")
        # Config files and datasets name trees by path: new trees under the name would change what every
        # one written with the old gives.  Checked here too, before minutes of fitting (write_trees refuses as well).
        if (args.boosted or args.all_maps) and trees_path(args.out).exists():
            raise UsageError(f"{trees_path(args.out)} exists: a config file that names it would give another model if it "
                             "were replaced; remove it, or write to another --out")
        if args.fold_maps is not None and any(args.fold_maps.glob("fold_*.trees.json")):
            raise UsageError(f"{args.fold_maps} holds fold maps already, which datasets built out of fold name by path; "
                             "remove them, or write to another directory")
        config = config_from_args(args)
        if config.topple.variant != "corrected":
            raise UsageError(f"only the corrected variant applies a recalibration, the model is {config.topple.variant!r}")
        corpus = None if args.corpus == "none" else load_corpus(args.corpus, config.mesh.default_mass)
        if args.fold_maps is not None and corpus is None:
            raise UsageError("--fold-maps writes corpus lists: give a --corpus, not 'none'")
        # The folds are checked before any log is read (reading the logs takes minutes).
        given = None if args.folds_from is None else read_fold_lists(args.folds_from)
        if given is not None and args.fold_maps is not None:  # a fold list is written from the corpus
            unknown = sorted({name for members in given for name in members} - {spec.object_id for spec in corpus.specs})
            if unknown:
                raise UsageError(f"{args.folds_from}'s folds hold {len(unknown)} object(s) not in corpus {args.corpus!r}: "
                                 f"{', '.join(unknown[:5])}{' ...' if len(unknown) > 5 else ''}")
        # A feature map is fitted on several logs at once (drawn pushes and a policy's), read one
        # by one: two logs may number their pushes alike.
        groups = [[path] for path in args.logs] if args.features else [args.logs]
        logs = []
        for paths in groups:
            log = read_log(paths, config, corpus, corpus_only=corpus is not None)
            if not log.pushes:
                raise UsageError(f"no usable pushes in {' '.join(paths)} ({log.rows} rows; rejected: {dict(log.rejected)})")
            logs.append((" ".join(paths), log))
        if args.features:
            result = feature_recalibrate(logs, config, folds=args.folds, seed=args.seed)
        elif args.down:
            result = down_recalibrate(logs[0][1], config, folds=args.folds, seed=args.seed)
        elif args.side:
            result = side_recalibrate(logs[0][1], config, folds=args.folds, seed=args.seed)
        elif args.all_maps:
            result = all_maps_recalibrate(logs[0][1], config, folds=args.folds, seed=args.seed)
        elif args.boosted:
            result = boosted_recalibrate(logs[0][1], config, folds=args.folds, seed=args.seed, fold_objects=given)
            result["folds_from"] = None if args.folds_from is None else str(args.folds_from)
            fold_trees = result.pop("fold_trees")
            if args.fold_maps is not None:
                result["fold_lists"] = [str(p) for p in write_fold_maps(args.fold_maps, fold_trees, result["fold_objects"], corpus)]
        else:
            result = recalibrate(logs[0][1], config, folds=args.folds, seed=args.seed, methods=tuple(args.methods))
    except (UsageError, CorpusError, LogError, CalibrationError, RecalibrationError, FeatureMapError, FileExistsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ImportError as err:  # the boosted map's fit needs scikit-learn, which only the pipeline extra installs
        print(f"error: {err.name or err}: not installed; pip install \"toppledb[pipeline]\"", file=sys.stderr)
        return 2
    logs_line = f"logs: {' '.join(args.logs)}; {result['pushes']} pushes on {result['objects']} objects, variant {result['variant']}"
    if args.features:
        print(format_feature_record(result))
        pooled = result["cross_validated"]
        comments = [
            "toppledb recalibrate --features: feature map of P(topple) fitted on push logs (docs/MODEL.md C.13)",
            logs_line,
            (f"{args.folds}-fold CV grouped by object (seed {args.seed}), held-out ECE / Brier: identity "
             f"{ece_brier(pooled['identity'])}, feature map "
             f"{ece_brier(pooled['feature_map'])}"),
        ]
        fitted_map = {"feature_map": tuple(result["weights"])}
    elif args.down:
        print(format_down_record(result))
        cv = result["cross_validated"]
        comments = [
            ("toppledb recalibrate --down: centred map of P(topple), and the down map for pushes with "
             f"u_z < {result['down_map_z']} (docs/MODEL.md C.7, C.15)"),
            logs_line,
            (f"{args.folds}-fold CV grouped by object (seed {args.seed}), held-out ECE / Brier: identity "
             f"{ece_brier(cv['identity'])}, centred {ece_brier(cv['centred'])}, "
             f"centred and down map {ece_brier(cv['down_map'])}"),
        ]
        # The cut travels with the weights fitted below it, whatever the defaults become.
        fitted_map = {"recalibration_x": tuple(result["knots"]["x"]), "recalibration_y": tuple(result["knots"]["y"]),
                      "down_map": tuple(result["weights"]), "down_map_z": result["down_map_z"]}
    elif args.side:
        print(format_side_record(result))
        cv = result["cross_validated"]
        comments = ["toppledb recalibrate --side: the side map of P(topple) (docs/MODEL.md C.16), the model's other maps kept",
                    logs_line, with_and_without(cv, "side_map", args.folds, args.seed)]
        fitted_map = {**kept_maps(config.topple), "side_map": tuple(result["weights"]), "side_map_band": tuple(result["band"])}
    elif args.all_maps:
        steps = [("centred and down maps", "down", format_down_record), ("side map", "side", format_side_record),
                 ("boosted map", "boosted", format_boosted_record)]
        for n, (name, key, format_step) in enumerate(steps, 1):
            print(f"{n}. the {name}\n{format_step(result[key])}")
        maps = result.pop("maps")
        trees = maps.pop("boosted_map")
        down_cv, side_cv, boosted_cv = (result[key]["cross_validated"] for key in ("down", "side", "boosted"))
        comments = [("toppledb recalibrate --all-maps: every map of P(topple) refitted in turn, centred and down, side, "
                     "boosted (docs/MODEL.md C.7, C.15, C.16, C.19)"),
                    logs_line,
                    (f"{args.folds}-fold CV grouped by object (seed {args.seed}), each step over the steps before it, "
                     "held-out ECE / Brier:"),
                    (f"  centred and down: unmapped {ece_brier(down_cv['identity'])}, "
                     f"mapped {ece_brier(down_cv['down_map'])}"),
                    (f"  side: without {ece_brier(side_cv['identity'])}, "
                     f"with {ece_brier(side_cv['side_map'])}"),
                    (f"  boosted: without {ece_brier(boosted_cv['identity'])}, "
                     f"with {ece_brier(boosted_cv['boosted_map'])}"),
                    "  (the side and boosted steps' 'without' holds the maps under them in-sample; toppledb report judges the file)"]
        fitted_map = maps
    elif args.boosted:
        print(format_boosted_record(result))
        cv = result["cross_validated"]
        trees = result.pop("trees")
        comments = ["toppledb recalibrate --boosted: the boosted map of P(topple) (docs/MODEL.md C.19), the model's other maps kept",
                    logs_line, with_and_without(cv, "boosted_map", result["folds"],
                                                args.seed if args.folds_from is None else str(args.folds_from))]
        fitted_map = kept_maps(config.topple)
    else:
        print(format_record(result))
        cv = result["cross_validated"]
        comments = [
            "toppledb recalibrate: monotone map of P(topple) fitted on push logs (docs/MODEL.md C.7)",
            logs_line,
            (f"method {result['chosen']}, chosen among {' '.join(result['methods'])} by {args.folds}-fold CV grouped by object (seed {args.seed}) on held-out "
             f"{result['select_by']}; held-out ECE / Brier: "
             + ", ".join(f"{m} {ece_brier(v)}" for m, v in [("identity", cv["identity"])] + list(cv["methods"].items()))),
        ]
        fitted_map = {"recalibration_x": tuple(result["knots"]["x"]), "recalibration_y": tuple(result["knots"]["y"])}
    if args.all_maps:
        print(IN_SAMPLE_UNDER.format(under="steps 2 and 3 score the maps under them as fitted on every push of this log"))
    elif (args.side or args.boosted) and args.config:
        print(IN_SAMPLE_UNDER.format(under=f"if the maps of {args.config} were fitted on these logs, they are scored here in-sample"))
    if args.all_maps or args.boosted:
        try:
            result["trees_file"] = write_trees(trees, args.out)
            fitted_map["boosted_map"] = Path(result["trees_file"]).name  # beside the TOML, wherever both go
        except FileExistsError as err:  # another run wrote it since the check
            print(f"error: {err}", file=sys.stderr)
            return 2
    topple = config.topple
    # A map belongs to the probabilities it was fitted on, so the file carries the model they
    # come from: every [topple] value of the base model that is not the default's (its noise,
    # from a ``toppledb calibrate`` file, say) and the smoothing (MODEL.md C.12).  The fitted map
    # replaces any map of the base model or the defaults: every map field is written.
    default = ToppleConfig()
    # The variant and the corrections always: the file must stay the same model when the
    # defaults change (they did when stuck_finger joined them).
    # The side map's band belongs to its weights: it travels only with them (the --side branch above).
    base = {f.name: getattr(topple, f.name) for f in dataclasses.fields(topple)
            if f.name not in (*NO_MAP, "side_map_band")
            and (f.name in ("variant", "corrections") or getattr(topple, f.name) != getattr(default, f.name))}
    if args.config or args.overrides:
        source = " ".join(filter(None, [str(args.config or "the defaults"), *(f"--set {o}" for o in args.overrides)]))
        comments.append(f"base model: {source}; its variant, corrections and [topple] values that differ from the "
                        "defaults are written here, its other sections are not")
    # A boosted map sits on the maps under it (C.19): any other fit replaces them, so it goes too.
    fitted = {**base, "smoothing_radius": topple.smoothing_radius, "smoothing_angle": topple.smoothing_angle, **NO_MAP,
              **fitted_map}
    # The file's other sections are the defaults', whatever the base model's were: if they would
    # choose pushes its down map maps as no rule judged, the file plans on the others.
    model = dataclasses.replace(ToppleConfig(), **fitted)
    mdp = None
    if maps_unjudged_choices(model, MDPConfig()):
        mdp = {"min_direction_z": model.down_map_z}
        comments.append("[mdp]: value iteration chooses no push the down map maps, as the boosted map is not over it")
    write_outputs(args.out, fitted, comments, args.json, result, mdp)
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
