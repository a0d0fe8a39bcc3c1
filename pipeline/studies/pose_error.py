"""How much of P(topple)'s error belongs to the start pose rather than to the push.

If two pushes on the same pose err the same way more often than two pushes anywhere, part of
the error is the pose's: something about it the model gets wrong for all its pushes.  Its size
is the covariance of the residuals (observed topple rate - P) of two different pushes on one
pose; the same covariance over pushes on different poses of one object says whether it is the
object's instead.  What knowing it would be worth is the Brier score of P shifted by the mean
residual of the pose's other pushes (leave-one-out: an oracle, since it reads physics).  And
what one failed push says about the pose's other pushes is the table ``after_another``.

    python -m pipeline.studies.pose_error data/logs/corpus_all data/logs/corpus_s1 --json F.json

reads the logs against the default model (``--config`` for another) on the default corpus's objects
only, as a calibration does (``--corpus`` for another list, ``none`` for every object), and gives each
statistic a 95 % interval over resamples of the objects (docs/VALIDATION.md, "The error that belongs
to the pose").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..build.atomic import write_text_atomic
from .after_failure import mapped
from .validation import BOOTSTRAP, percentile_interval, to_json

BANDS = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.0))
"""The failed push's P(topple) bands of ``after_another``, each [low, high); the last one includes 1."""

LIKELY = 0.6
"""``after_another``'s second table: only the other pushes this likely (those a planner weighs)."""


def _groups(*labels) -> list[np.ndarray]:
    """Group labels as non-negative integer arrays (an empty list is an empty int array)."""
    return [np.asarray(label, dtype=np.intp) for label in labels]


def pair_covariance(residual: np.ndarray, group: np.ndarray) -> float:
    """Covariance of the residuals of two different pushes of one group, about the overall mean:
    with r centred on its mean, the mean of r_i r_j over ordered pairs i != j in the same group.

    residual : (n,) float;  group : (n,) int, non-negative
    returns : float, NaN when no group has two pushes
    """
    residual = np.asarray(residual, dtype=float)
    (group,) = _groups(group)
    if len(residual) == 0:
        return float("nan")
    r = residual - residual.mean()
    count = np.bincount(group)
    pairs = float(np.sum(count * (count - 1)))
    if pairs == 0:
        return float("nan")
    # sum over i != j of r_i r_j within a group = (sum r)^2 - sum r^2
    return float(np.sum(np.bincount(group, r) ** 2 - np.bincount(group, r ** 2)) / pairs)


def other_group_covariance(residual: np.ndarray, group: np.ndarray, outer: np.ndarray) -> float:
    """``pair_covariance`` over pairs in the same ``outer`` group (an object) but different
    ``group``s (its poses).  residual : (n,) float;  group, outer : (n,) int, each group inside one outer

    Raises ``ValueError`` when a group spans two outer groups."""
    residual = np.asarray(residual, dtype=float)
    group, outer = _groups(group, outer)
    if len(residual) == 0:
        return float("nan")
    if len(np.unique(np.column_stack([group, outer]), axis=0)) != len(np.unique(group)):
        raise ValueError("a group (pose) lies in two outer groups (objects)")
    r = residual - residual.mean()
    # Pairs within an object less pairs within a pose; each push paired with itself is in both
    # sums and cancels, so the products' and the counts' squares are all it takes.
    products = float(np.sum(np.bincount(outer, r) ** 2) - np.sum(np.bincount(group, r) ** 2))
    pairs = float(np.sum(np.bincount(outer) ** 2) - np.sum(np.bincount(group) ** 2))
    if pairs == 0:
        return float("nan")
    return products / pairs


def leave_one_out_shift(residual: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Per push, the mean residual of the other pushes of its group (0 for a push alone in it).

    residual : (n,) float;  group : (n,) int;  returns : (n,) float
    """
    residual = np.asarray(residual, dtype=float)
    (group,) = _groups(group)
    total, count = np.bincount(group, residual), np.bincount(group)
    others = count[group] - 1
    return np.divide(total[group] - residual, others, out=np.zeros_like(residual), where=others > 0)


def after_another(p_topple: np.ndarray, observed: np.ndarray, group: np.ndarray, power: float,
                  bands: tuple[tuple[float, float], ...] = BANDS, others_from: float = 0.0) -> list[dict]:
    """What a push's failure, or its topple, says about the other pushes of its pose.

    Over ordered pairs (a, b) of different pushes in one group, with a's P in the band and b's
    P at least ``others_from``, b's predicted, believed (P^``power``, ``after_failure.mapped``, what docs/MODEL.md (12.11)
    believes once a push of the pose has failed) and observed topple rates, averaged with
    weight 1 - observed(a) (how often one repeat of a failed) and with weight observed(a) (how
    often it toppled).

    p_topple, observed : (n,) float, P and the observed topple rate;  group : (n,) int
    returns : per band {"band", "pairs", "failed": {"predicted", "believed", "toppled"}, "toppled": {...}},
      NaN where a band has no weight
    """
    p_topple, observed = np.asarray(p_topple, dtype=float), np.asarray(observed, dtype=float)
    (group,) = _groups(group)
    other = p_topple >= others_from
    believed = mapped(p_topple, power)
    out = []
    for low, high in bands:
        in_band = (p_topple >= low) & ((p_topple <= high) if high >= 1.0 else (p_topple < high))
        in_band_count = np.bincount(group, in_band.astype(float))
        row = {"band": [low, high], "pairs": int(np.sum(np.where(other, in_band_count[group] - in_band, 0)))}
        for name, weight_of_a in (("failed", 1.0 - observed), ("toppled", observed)):
            a_weight = np.where(in_band, weight_of_a, 0.0)
            # b's weight: its group's band pushes but itself, and none unless b is likely enough
            w = np.where(other, np.bincount(group, a_weight)[group] - a_weight, 0.0)
            total = float(w.sum())
            row[name] = {key: float(np.sum(w * value) / total) if total > 0 else float("nan")
                         for key, value in (("predicted", p_topple), ("believed", believed), ("toppled", observed))}
        out.append(row)
    return out


def resampled(group: np.ndarray, outer: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One bootstrap resample of the outer groups (objects), drawn with replacement, each copy of
    an object its own object with its own poses.

    returns : rows (m,) int into the pushes; group, outer (m,) int, relabelled
    """
    group, outer = _groups(group, outer)
    objects = np.unique(outer)
    order = np.argsort(outer, kind="stable")
    starts = np.searchsorted(outer[order], objects)
    ends = np.append(starts[1:], len(order))
    chosen = rng.integers(0, len(objects), len(objects))
    rows = np.concatenate([order[starts[o]:ends[o]] for o in chosen])
    copy = np.repeat(np.arange(len(chosen)), ends[chosen] - starts[chosen])
    return rows, copy * (group.max() + 1) + group[rows], copy


def summarise(p_topple: np.ndarray, observed: np.ndarray, group: np.ndarray, outer: np.ndarray,
              power: float, n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """Every number of the study from the pushes' P, observed rate, pose group and object, with
    95 % intervals over ``n_resamples`` resamples of the objects (0: none).  power : k of (12.11)"""
    p_topple, observed = np.asarray(p_topple, dtype=float), np.asarray(observed, dtype=float)
    group, outer = _groups(group, outer)
    if len(p_topple) == 0:
        raise ValueError("no pushes to study")

    def statistics(rows: np.ndarray, group: np.ndarray, outer: np.ndarray) -> dict:
        residual = observed[rows] - p_topple[rows]
        shifted = np.clip(p_topple[rows] + leave_one_out_shift(residual, group), 0.0, 1.0)
        return {
            "same_pose_covariance": pair_covariance(residual, group),
            "same_object_other_pose_covariance": other_group_covariance(residual, group, outer),
            "oracle_gain": float(np.mean((shifted - observed[rows]) ** 2) - np.mean(residual ** 2)),
        }

    found = statistics(np.arange(len(p_topple)), group, outer)
    rng = np.random.default_rng(seed)
    draws = [statistics(*resampled(group, outer, rng)) for _ in range(n_resamples)]
    residual = observed - p_topple
    return {
        "pushes": len(p_topple),
        "poses": len(np.unique(group)),
        "objects": len(np.unique(outer)),
        "after_failure_power": power,
        "mean_residual": float(residual.mean()),
        "residual_variance": float(residual.var()),
        **found,
        "intervals": {key: percentile_interval([d[key] for d in draws]) if draws else None for key in found},
        "brier": {
            "model": float(np.mean(residual ** 2)),
            "pose_oracle": float(np.mean(residual ** 2)) + found["oracle_gain"],
            "never_topples": float(np.mean(observed ** 2)),
            "constant_rate": float(np.mean((observed - observed.mean()) ** 2)),
        },
        "after_another": after_another(p_topple, observed, group, power),
        f"after_another_others_from_{LIKELY}": after_another(p_topple, observed, group, power, others_from=LIKELY),
    }


def read_pushes(logs: list[str], config, corpus=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(P, observed rate, pose group, object index) of every usable push in ``logs``, by the model
    of ``config``; given a ``corpus``, of its objects only (the study's: calibration data).

    returns : (n,) float, (n,) float, (n,) int, (n,) int"""
    from .logreader import read_log
    from .scoring import Scorer

    log = read_log(logs, config, corpus, corpus_only=corpus is not None)
    scorer = Scorer(log, seed=config.seed, contacts=config.contacts)
    p_topple = scorer.score(config.topple).p_topple  # in log order
    group = np.zeros(len(scorer), dtype=int)
    for index, members in enumerate(scorer.groups):
        group[members.rows] = index
    usable = np.isfinite(p_topple)
    return p_topple[usable], scorer.empirical_topple[usable], group[usable], scorer.object_index[usable]


def main(argv: list[str] | None = None) -> int:
    from ..build.corpus import load_corpus
    from ..cli import UsageError, make_config

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.pose_error", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="push logs (toppledb play)")
    parser.add_argument("--config", help="a TOML file or preset name (default: the default model)")
    parser.add_argument("--corpus", default="default",
                        help="read only this corpus's objects (default: the default corpus; 'none': every object)")
    parser.add_argument("--bootstrap", type=int, default=BOOTSTRAP, help="object resamples for the intervals (0: none)")
    parser.add_argument("--json", metavar="FILE", help="write the result here too")
    args = parser.parse_args(argv)
    try:
        config = make_config(argparse.Namespace(config=args.config, overrides=[], seed=None))
    except UsageError as err:
        parser.exit(2, f"{err}\n")
    corpus = None if args.corpus == "none" else load_corpus(args.corpus, config.mesh.default_mass)
    pushes = read_pushes(args.logs, config, corpus)
    if len(pushes[0]) == 0:
        parser.exit(2, f"no usable push in {', '.join(args.logs)}"
                       + (f" of an object of the {args.corpus} corpus (--corpus none reads every object)\n" if corpus else "\n"))
    result = summarise(*pushes, power=config.mdp.after_failure_power, n_resamples=max(args.bootstrap, 0), seed=config.seed)
    text = json.dumps(to_json(result), indent=1, allow_nan=False)
    if args.json:
        write_text_atomic(Path(args.json), text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
