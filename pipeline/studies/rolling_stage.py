"""Candidate RS (stop 59): a second map over the default's P(topple), fitted with shapes that roll.

The default's boosted map (docs/MODEL.md C.19) learned the model's errors on the corpus's random shapes, which
rarely roll. On the rolling set (``pipeline.studies.rolling_set``: generated rods, prisms, frusta, bottles,
capsules, coarse ellipsoids) the default predicts topples too rarely, most of all for pushes from above onto rods
lying on their side (informative TV 0.246, AP 0.637, ECE 0.083). This asks whether the remedy is data: a second
map, boosted trees over the same 24 features plus the default's own P as a logit, fitted on the corpus's log and
the rolling set's log together, so that it can learn where the rolling shapes differ without forgetting the corpus.

    python -m pipeline.studies.rolling_stage --fit data/logs/corpus data/logs/rolling \\
        --judge data/logs/household --out F.json

fits RS on the ``--fit`` logs, reports its object-grouped cross-validation there (folds by object), and scores
the default and RS on each ``--judge`` log with the validation report's metrics and paired differences over
objects. RS replaces a push's P(topple) by its own q and scales the row's leaving part to q, keeping where it
lands; unlike C.19, a push whose row has no leaving part (P = 0) keeps its row (``staged_p``).

This is a study, not an engine map: its trees live in the process that fits them. Only if it passed its rule
(``reports/household_rule_s59.md``) would it have become a map the engine applies; it did not (stop 59: on the
household set Brier -0.010 [-0.023, +0.002], on the 498 fresh objects +0.004; ``reports/rolling_stage_s59.json``,
docs/VALIDATION.md "The household set").
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..build.corpus import DEFAULT_LIST, read_list
from ..model.boosted_map import FEATURES, fitted_logit
from ..model.config import Config
from ..model.recalibration import rows_toppling
from .logreader import read_log
from .recalibrate import push_folds
from .scoring import Scorer, Scores
from .validation import BOOTSTRAP, bootstrap_metric_difference, predictor_summary, to_json

FIT_PARAMS = {"max_iter": 100, "learning_rate": 0.05, "max_leaf_nodes": 8, "min_samples_leaf": 40, "l2_regularization": 1.0}
"""The trees' settings, smaller than C.19's because the data are: the first and best of three tried in a scratch
cross-validation on the corpus's and the rolling set's logs (5 folds by object, q on every push), before any
judging log was read. Brier of P out of fold, rolling / corpus: these 0.0625 / 0.0400; 200 trees of 8 leaves, 80
rows a leaf, learning rate 0.03: 0.0640 / 0.0422; 50 trees of 4 leaves, 80 rows a leaf: 0.0727 / 0.0423."""
FOLDS = 5


@dataclass
class LogPushes:
    """One log read and evaluated by the default: its scorer, the default's predictions and scores, RS's inputs.

    predictions : per group, as ``Scorer.predict`` gives them;  default : their ``Scores`` (P(topple) in log order)
    features : (n, len(FEATURES) + 1) float, C.19's inputs and the default's P as a logit (last column)
    """

    name: str
    scorer: Scorer
    predictions: list[tuple[np.ndarray, np.ndarray]]
    default: Scores
    features: np.ndarray

    @property
    def p_topple(self) -> np.ndarray:
        """(n,) float, the default's P(topple) in log order."""
        return self.default.p_topple


def read_pushes(path: str, config: Config) -> LogPushes:
    """A log scored by ``config``'s model (the corpus's objects as in a held-out report: all read).

    path : a log, or several joined by commas, read as one (the 498 fresh objects' ten logs)
    """
    log = read_log(path.split(","), config, read_list(DEFAULT_LIST, config.mesh.default_mass))
    scorer = Scorer(log, config.seed, config.contacts)
    inputs, _, _ = scorer.boosted_inputs(config.topple)
    predictions = scorer.predict(config.topple)
    default = scorer.score_predictions(predictions)
    return LogPushes(path, scorer, predictions, default, np.column_stack([inputs, fitted_logit(default.p_topple)]))


def fit_trees(features: np.ndarray, observed: np.ndarray, repeats: np.ndarray, seed: int = 0):
    """Boosted trees of P(topple) (scikit-learn), each push two rows weighted by its toppled and stayed repeats.

    Not ``boosted_map.fit_trees``: that writes the engine's tree format, whose columns are C.19's 24 features, and
    it leaves out rows of weight 0, which moves scikit-learn's bins; RS was frozen and judged with these (its
    trees fitted the other way differ by up to 0.12 in P on the fit logs)."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    x = np.vstack([features, features])
    y = np.r_[np.ones(len(features)), np.zeros(len(features))]
    weight = np.r_[observed * repeats, (1 - observed) * repeats]
    return HistGradientBoostingClassifier(**FIT_PARAMS, early_stopping=False, random_state=seed).fit(x, y, sample_weight=weight)


def with_stage(pushes: LogPushes, q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The default's predictions with P(topple) replaced by ``staged_p`` (``recalibration.rows_toppling``: each
    row's leaving part scaled to q, keeping where it lands; a row with no leaving part as it was).

    q : (n,) float, log order;  returns : per group, (rows (pushes, P + 1), P(topple) (pushes,))
    """
    return [rows_toppling(rows, group.pose.index, q[group.rows])
            for group, (rows, _) in zip(pushes.scorer.groups, pushes.predictions)]


def object_folds(object_keys: list[np.ndarray], seed: int = 0) -> list[np.ndarray]:
    """Folds of objects across several logs, drawn as ``toppledb recalibrate`` draws them (``recalibrate.push_folds``):
    every push of an object in its object's one fold, an object of two logs counting as two.

    object_keys : per log, (n,) the object of each push;  returns : per log, (n,) int, each push's fold
    """
    keys = [f"{i}:{o}" for i, objects in enumerate(object_keys) for o in objects]
    _, fold_of = push_folds(keys, FOLDS, seed)
    return np.split(fold_of, np.cumsum([len(objects) for objects in object_keys])[:-1])


def staged_p(p_default: np.ndarray, q: np.ndarray) -> np.ndarray:
    """RS's P(topple): q where the default's row has a leaving part to scale (P > 0), else the default's P.

    Unlike C.19, which can give a push at P = 0 its neighbourhood's or its pose's landing (C.13.2), RS keeps
    such a row: as judged, it cannot raise a push the default says never topples."""
    return np.where(p_default > 0, q, p_default)


def cross_validate(logs: list[LogPushes], seed: int = 0) -> dict:
    """RS fitted out of fold against the default, per log: the Brier score of P(topple), RS's as judged
    (``staged_p``) and, for comparison, with q on every push, in ``object_folds``."""
    folds = object_folds([np.asarray(p.scorer.object_ids)[p.scorer.object_index] for p in logs], seed)
    q = [np.full(len(pushes.scorer), np.nan) for pushes in logs]
    for k in range(FOLDS):
        train = [(p.features[f != k], p.scorer.empirical_topple[f != k], p.scorer.repeats[f != k]) for p, f in zip(logs, folds)]
        trees = fit_trees(*(np.concatenate(parts) for parts in zip(*train)), seed=seed)
        for p, f, out in zip(logs, folds, q):
            if (f == k).any():
                out[f == k] = trees.predict_proba(p.features[f == k])[:, 1]

    def brier(predicted: np.ndarray, p: LogPushes) -> float:
        return float(np.mean((predicted - p.scorer.empirical_topple) ** 2))

    return {p.name: {"pushes": len(p.scorer), "objects": len(p.scorer.object_ids), "kept_rows": int(np.sum(p.p_topple <= 0)),
                     "brier_p_default": brier(p.p_topple, p),
                     "brier_p_rs_out_of_fold": brier(staged_p(p.p_topple, out), p),
                     "brier_p_rs_out_of_fold_every_push": brier(out, p)}
            for p, out in zip(logs, q)}


def judge(pushes: LogPushes, trees, n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """The default and RS on one log: the validation report's metrics of each and RS minus the default, paired over objects."""
    scorer = pushes.scorer
    q = trees.predict_proba(pushes.features)[:, 1]
    default = pushes.default
    stage = scorer.score_predictions(with_stage(pushes, q))
    return {
        "pushes": len(scorer), "objects": len(scorer.object_ids),
        "kept_rows": int(np.sum(pushes.p_topple <= 0)),
        "default": predictor_summary(default, scorer, n_resamples=n_resamples, seed=seed),
        "rs": predictor_summary(stage, scorer, n_resamples=n_resamples, seed=seed),
        "rs_minus_default": bootstrap_metric_difference(stage, default, scorer.empirical_topple, scorer.object_index, n_resamples, seed),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.rolling_stage", description=__doc__.split("\n")[0])
    parser.add_argument("--fit", nargs="+", required=True, help="logs to fit RS on (the corpus's and the rolling set's)")
    parser.add_argument("--judge", nargs="*", default=[], help="logs to score the default and RS on, each one log or several joined by commas")
    parser.add_argument("--out", type=Path, required=True, help="JSON report")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    config = Config()
    fit_logs = [read_pushes(p, config) for p in args.fit]
    result = {"fit": args.fit, "fit_params": FIT_PARAMS, "features": [*FEATURES, "logit_p_default"],
              "cross_validation": cross_validate(fit_logs, args.seed)}
    trees = fit_trees(np.concatenate([p.features for p in fit_logs]), np.concatenate([p.scorer.empirical_topple for p in fit_logs]),
                      np.concatenate([p.scorer.repeats for p in fit_logs]), seed=args.seed)
    result["judged"] = {path: judge(read_pushes(path, config), trees, seed=args.seed) for path in args.judge}
    args.out.write_text(json.dumps(to_json(result), indent=1))
    for name, cv in result["cross_validation"].items():
        print(f"{name}: Brier of P, default {cv['brier_p_default']:.4f}, RS out of fold {cv['brier_p_rs_out_of_fold']:.4f}")
    for name, j in result["judged"].items():
        d = j["rs_minus_default"]
        print(f"{name} ({j['pushes']} pushes, {j['objects']} objects): " + ", ".join(
            f"{k} {j['default'][k]:.3f} -> {j['rs'][k]:.3f} ({d[k]['difference']:+.3f} [{d[k]['ci'][0]:+.3f}, {d[k]['ci'][1]:+.3f}])"
            for k in ("tv_informative", "brier", "ap", "ece")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
