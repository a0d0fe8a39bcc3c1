"""How much of P(topple)'s error belongs to the start pose rather than to the push.

If two pushes on the same pose err the same way more often than two pushes anywhere, part of
the error is the pose's: something about it the model gets wrong for all its pushes.  Its size
is the covariance of the residuals (observed topple rate - P) of two different pushes on one
pose; the same covariance over pushes on different poses of one object says whether it is the
object's instead.  What knowing it would be worth is the Brier score of P shifted by the mean
residual of the pose's other pushes (leave-one-out: an oracle, since it reads physics).  And
what one failed push says about the pose's other pushes is the table ``after_another``.

    python -m pipeline.studies.pose_error data/logs/corpus_all data/logs/corpus_s1 --json F.json

reads the logs against the default model (``--config`` for another) on corpus objects only, as a
calibration does (docs/VALIDATION.md, "The error that belongs to the pose").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..build.atomic import write_text_atomic

BANDS = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.0))
"""The failed push's P(topple) bands of ``after_another``; the last one includes 1."""


def pair_covariance(residual: np.ndarray, group: np.ndarray) -> float:
    """Covariance of the residuals of two different pushes of one group, about the overall mean:
    the mean of r_i r_j over ordered pairs i != j in the same group, less mean(r)^2.

    residual : (n,) float;  group : (n,) int, non-negative
    returns : float, NaN when no group has two pushes
    """
    residual, group = np.asarray(residual, dtype=float), np.asarray(group)
    total = np.bincount(group, residual)
    squares = np.bincount(group, residual ** 2)
    count = np.bincount(group)
    pairs = float(np.sum(count * (count - 1)))
    if pairs == 0:
        return float("nan")
    # sum over i != j of r_i r_j within a group = (sum r)^2 - sum r^2
    return float(np.sum(total ** 2 - squares) / pairs - residual.mean() ** 2)


def other_group_covariance(residual: np.ndarray, group: np.ndarray, outer: np.ndarray) -> float:
    """``pair_covariance`` over pairs in the same ``outer`` group (an object) but different
    ``group``s (its poses).  residual : (n,) float;  group, outer : (n,) int, each group inside one outer"""
    residual, group, outer = np.asarray(residual, dtype=float), np.asarray(group), np.asarray(outer)
    # Pairs within an object less pairs within a pose; each push paired with itself is in both
    # sums and cancels, so the products' and the counts' squares are all it takes.
    products = float(np.sum(np.bincount(outer, residual) ** 2) - np.sum(np.bincount(group, residual) ** 2))
    pairs = float(np.sum(np.bincount(outer) ** 2) - np.sum(np.bincount(group) ** 2))
    if pairs == 0:
        return float("nan")
    return products / pairs - float(residual.mean()) ** 2


def leave_one_out_shift(residual: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Per push, the mean residual of the other pushes of its group (0 for a push alone in it).

    residual : (n,) float;  group : (n,) int;  returns : (n,) float
    """
    residual, group = np.asarray(residual, dtype=float), np.asarray(group)
    total, count = np.bincount(group, residual), np.bincount(group)
    others = count[group] - 1
    return np.divide(total[group] - residual, others, out=np.zeros_like(residual), where=others > 0)


def after_another(p_topple: np.ndarray, observed: np.ndarray, group: np.ndarray,
                  bands: tuple[tuple[float, float], ...] = BANDS) -> list[dict]:
    """What a push's failure, or its topple, says about the other pushes of its pose.

    Over ordered pairs (a, b) of different pushes in one group, with a's P in the band, b's
    predicted and observed topple rates averaged with weight 1 - observed(a) (how often one
    repeat of a failed) and with weight observed(a) (how often it toppled).

    p_topple, observed : (n,) float, P and the observed topple rate;  group : (n,) int
    returns : per band {"band", "pairs", "failed": {"predicted", "toppled"}, "toppled": {...}},
      NaN where a band has no weight
    """
    p_topple, observed, group = np.asarray(p_topple, dtype=float), np.asarray(observed, dtype=float), np.asarray(group)
    out = []
    for low, high in bands:
        in_band = (p_topple >= low) & ((p_topple <= high) if high >= 1.0 else (p_topple < high))
        failed_weight = np.bincount(group, np.where(in_band, 1.0 - observed, 0.0))
        toppled_weight = np.bincount(group, np.where(in_band, observed, 0.0))
        in_band_count = np.bincount(group, in_band.astype(float))
        row = {"band": [low, high], "pairs": int(np.sum(in_band_count[group] - in_band))}
        for name, weight in (("failed", failed_weight), ("toppled", toppled_weight)):
            # b's weight: the band's pushes of its group but itself
            own = np.where(in_band, observed if name == "toppled" else 1.0 - observed, 0.0)
            w = weight[group] - own
            total = float(w.sum())
            row[name] = {
                "predicted": float(np.sum(w * p_topple) / total) if total > 0 else float("nan"),
                "toppled": float(np.sum(w * observed) / total) if total > 0 else float("nan"),
            }
        out.append(row)
    return out


def summarise(p_topple: np.ndarray, observed: np.ndarray, group: np.ndarray, outer: np.ndarray) -> dict:
    """Every number of the study from the pushes' P, observed rate, pose group and object."""
    p_topple, observed = np.asarray(p_topple, dtype=float), np.asarray(observed, dtype=float)
    residual = observed - p_topple
    shifted = np.clip(p_topple + leave_one_out_shift(residual, group), 0.0, 1.0)
    return {
        "pushes": len(p_topple),
        "poses": len(np.unique(group)),
        "objects": len(np.unique(outer)),
        "mean_residual": float(residual.mean()),
        "residual_variance": float(residual.var()),
        "same_pose_covariance": pair_covariance(residual, group),
        "same_object_other_pose_covariance": other_group_covariance(residual, group, outer),
        "brier": {
            "model": float(np.mean(residual ** 2)),
            "pose_oracle": float(np.mean((shifted - observed) ** 2)),
            "never_topples": float(np.mean(observed ** 2)),
            "constant_rate": float(np.mean((observed - observed.mean()) ** 2)),
        },
        "after_another": after_another(p_topple, observed, group),
    }


def read_pushes(logs: list[str], config, corpus=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(P, observed rate, pose group, object index) of every usable push in ``logs``, by the model
    of ``config``; given a ``corpus``, of its objects only (the study's: calibration data).

    returns : (n,) float, (n,) float, (n,) int, (n,) int"""
    from .logreader import read_log
    from .scoring import Scorer

    log = read_log(logs, config, corpus, corpus_only=corpus is not None)
    scorer = Scorer(log)
    p_topple = np.full(len(scorer), np.nan)
    group = np.zeros(len(scorer), dtype=int)
    for index, (members, (_, p)) in enumerate(zip(scorer.groups, scorer.predict(config.topple))):
        p_topple[members.rows] = p
        group[members.rows] = index
    usable = np.isfinite(p_topple)
    return p_topple[usable], scorer.empirical_topple[usable], group[usable], scorer.object_index[usable]


def main(argv: list[str] | None = None) -> int:
    from ..build.corpus import load_corpus
    from ..cli import UsageError, make_config

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.pose_error", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="push logs of corpus objects (toppledb play)")
    parser.add_argument("--config", help="a TOML file or preset name (default: the default model)")
    parser.add_argument("--json", metavar="FILE", help="write the result here too")
    args = parser.parse_args(argv)
    try:
        config = make_config(argparse.Namespace(config=args.config, overrides=[], seed=None))
    except UsageError as err:
        parser.exit(2, f"{err}\n")
    result = summarise(*read_pushes(args.logs, config, load_corpus("default", config.mesh.default_mass)))
    text = json.dumps(result, indent=1)
    if args.json:
        write_text_atomic(Path(args.json), text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
