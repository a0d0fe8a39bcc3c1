"""The judge against its own numerics: how much the physics the model is scored against depends on the
player's settings rather than on physics.

Every validation figure scores the model against pybullet played at one step (1/240 s), one number of
solver iterations (50) and one finger speed (0.05 m/s). ``toppledb play --time-step/--solver-iterations/
--finger-speed`` plays the same pushes with the same noise draws under other settings (the draws come
from the seeded stream of (seed, object, pose), not from the player), so two such logs differ only by
the player's numerics. This compares them, trial by trial and through the default model's metrics:

    python -m pipeline.studies.judge_numerics --base data/logs/heldout_b data/logs/heldout_c \\
        --variant step=data/logs/judge_step --variant slow=data/logs/judge_slow \\
        --rate-from data/logs/corpus --exclude-corpus --json reports/judge_numerics_s68.json

Per variant, on the pushes both logs hold with the same repeats:
- the share of trials whose final pose agrees, and whose toppled-or-not agrees;
- each log's topple rate and the variant's minus base's, with a 95 % bootstrap interval over objects;
- the mean sup-TV between the two logs' observed next-pose distributions per push;
- the default model's metrics (``validation.push_metrics``) on each log, beside never-topples and the
  constant rate, and the variant's minus base's, paired over the same resampled objects.
It measures; it decides nothing (docs/VALIDATION.md, "The judge's own numerics").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..model.config import Config
from .logreader import LogError, PushLog, read_log
from .scoring import Scorer, Scores, sup_tv
from .validation import BOOTSTRAP, observed_topple_rate, percentile_interval, push_metrics, to_json

PREDICTORS = ("default", "never_topples", "constant_rate")
"""What is scored on every log: the default model and the two trivial predictors."""


class JudgeError(ValueError):
    """Logs that cannot be compared; one line."""


def common_pushes(base: PushLog, variant: PushLog) -> tuple[PushLog, PushLog, dict]:
    """Both logs restricted to the pushes they both hold, with as many repeats in each.

    A push is named by (object id, push id); the two must agree on its start pose, point and direction
    (the same push), else the logs are not one play under two settings.
    returns : (base, variant, {"base_only": pushes, "variant_only": pushes}) with pushes in the same order
    raises JudgeError : a push the two logs describe differently
    """
    def by_key(log: PushLog) -> dict:
        return {(p.object_id, p.push_id): p for p in log.pushes}

    a, b = by_key(base), by_key(variant)
    keep = []
    for key in sorted(a.keys() & b.keys()):
        first, second = a[key], b[key]
        if first.pose != second.pose or not (np.allclose(first.point, second.point, atol=1e-9)
                                             and np.allclose(first.direction, second.direction, atol=1e-9)):
            raise JudgeError(f"push {key[1]} of {key[0]} differs between the logs: not the same play under other settings")
        if len(first.outcomes) == len(second.outcomes):
            keep.append(key)
    kept = set(keep)

    def restricted(log: PushLog, pushes: dict) -> PushLog:
        chosen = [pushes[key] for key in keep]
        objects = {p.object_id for p in chosen}
        return PushLog({k: v for k, v in log.objects.items() if k in objects}, chosen, log.rejected, log.examples,
                       log.rows, log.files, log.logs)

    unpaired = {"base_only": len(a.keys() - kept), "variant_only": len(b.keys() - kept)}
    return restricted(base, a), restricted(variant, b), unpaired


def trial_agreement(base: PushLog, variant: PushLog) -> dict:
    """How often the same trial ends the same way: shares over every paired trial.

    base, variant : ``common_pushes``'s, the same pushes in the same order
    """
    first = np.concatenate([p.outcomes for p in base.pushes])
    second = np.concatenate([p.outcomes for p in variant.pushes])
    start = np.concatenate([np.full(len(p.outcomes), p.pose) for p in base.pushes])
    return {"trials": len(first), "same_final_pose": float(np.mean(first == second)),
            "same_toppled": float(np.mean((first != start) == (second != start)))}


def topple_rates(base: PushLog, variant: PushLog, n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """Each log's topple rate over its trials, and the variant's minus base's with a 95 % interval
    over objects (the same objects resampled for both)."""
    objects = sorted({p.object_id for p in base.pushes})
    index = {name: i for i, name in enumerate(objects)}
    which = np.array([index[p.object_id] for p in base.pushes])
    trials = np.bincount(which, [len(p.outcomes) for p in base.pushes], len(objects))
    toppled = [np.bincount(which, [np.sum(p.outcomes != p.pose) for p in log.pushes], len(objects)) for log in (base, variant)]
    draws = np.random.default_rng(seed).integers(0, len(objects), (n_resamples, len(objects)))
    difference = (toppled[1][draws].sum(axis=1) - toppled[0][draws].sum(axis=1)) / trials[draws].sum(axis=1)
    rate = [float(t.sum() / trials.sum()) for t in toppled]
    return {"base": rate[0], "variant": rate[1], "difference": rate[1] - rate[0], "ci": percentile_interval(difference)}


def distribution_tv(base: Scorer, variant: Scorer) -> float:
    """Mean over pushes of the sup-TV between the two logs' observed next-pose distributions."""
    tv = [sup_tv(a.empirical, b.empirical) for a, b in zip(base.groups, variant.groups)]
    return float(np.mean(np.concatenate(tv)))


def paired_metrics(base: Scores, variant: Scores, observed: tuple[np.ndarray, np.ndarray], objects: np.ndarray,
                   n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """One predictor's metrics on each log and the variant's minus base's, bootstrapped over objects.

    base, variant : the predictor's scores against each log (the same pushes in the same order)
    observed : (n,) float each, the pushes' topple rates in base and in the variant
    objects : (n,) int, object of each push
    returns : {"base": metrics, "variant": metrics, "difference": metric -> {"difference", "ci"}}
    """
    rows = [np.flatnonzero(objects == i) for i in range(int(objects.max()) + 1)]

    def metrics(draw: np.ndarray) -> tuple[dict, dict]:
        index = np.concatenate([rows[d] for d in draw])
        copies = np.repeat(np.arange(len(draw)), [len(rows[d]) for d in draw])
        return tuple(push_metrics(s.tv[index], s.p_topple[index], o[index], copies, s.brier[index])
                     for s, o in zip((base, variant), observed))

    first, second = metrics(np.arange(len(rows)))
    rng = np.random.default_rng(seed)
    draws = [metrics(rng.integers(len(rows), size=len(rows))) for _ in range(n_resamples)]
    difference = {key: {"difference": second[key] - first[key],
                        "ci": percentile_interval([b[key] - a[key] for a, b in draws], fewest=n_resamples // 2 + 1)}
                  for key in first}
    return {"base": first, "variant": second, "difference": difference}


def compare(base: PushLog, variant: PushLog, config: Config, rate: float | None, n_resamples: int = BOOTSTRAP) -> dict:
    """Everything the module docstring lists for one variant against base."""
    base, variant, unpaired = common_pushes(base, variant)
    if not base.pushes:
        raise JudgeError("the logs hold no push in common")
    scorers = [Scorer(log, config.seed, config.contacts) for log in (base, variant)]
    # The same pushes: the model's rows are predicted once and scored against both logs.
    predictions = scorers[0].predict(config.topple)
    scores = {"default": [s.score_predictions(predictions) for s in scorers],
              "never_topples": [s.never_topples() for s in scorers]}
    if rate is not None:
        scores["constant_rate"] = [s.constant_rate(rate) for s in scorers]
    observed = (scorers[0].empirical_topple, scorers[1].empirical_topple)
    return {
        "pushes": len(base.pushes),
        "objects": len(scorers[0].object_ids),
        "unpaired_pushes": unpaired,
        **trial_agreement(base, variant),
        "topple_rate": topple_rates(base, variant, n_resamples, config.seed),
        "push_tv": distribution_tv(*scorers),
        "predictors": {name: paired_metrics(*pair, observed, scorers[0].object_index, n_resamples, config.seed)
                       for name, pair in scores.items()},
    }


def format_comparison(name: str, result: dict) -> str:
    """A few lines for the terminal."""
    rate = result["topple_rate"]
    lines = [(f"{name}: {result['pushes']} pushes, {result['objects']} objects, {result['trials']} trials; "
              f"same final pose {result['same_final_pose']:.3f}, same toppled {result['same_toppled']:.3f}; "
              f"topple rate {rate['base']:.3f} -> {rate['variant']:.3f} ({rate['difference']:+.3f} "
              f"[{rate['ci'][0]:+.3f}, {rate['ci'][1]:+.3f}]); push TV {result['push_tv']:.3f}")]
    for predictor, metrics in result["predictors"].items():
        parts = []
        for key in ("tv_informative", "ap", "ece", "brier"):
            d = metrics["difference"][key]
            parts.append(f"{key} {metrics['base'][key]:.4f} -> {metrics['variant'][key]:.4f} "
                         f"({d['difference']:+.4f} [{d['ci'][0]:+.4f}, {d['ci'][1]:+.4f}])")
        lines.append(f"  {predictor}: " + "; ".join(parts))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..build.atomic import write_text_atomic
    from ..build.corpus import CorpusError, load_corpus

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.judge_numerics", description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", nargs="+", required=True, metavar="LOG", help="the logs played with the player's defaults")
    parser.add_argument("--variant", action="append", required=True, metavar="NAME=LOG[,LOG...]",
                        help="the same play under other settings (repeatable)")
    parser.add_argument("--rate-from", nargs="+", metavar="LOG", help="calibration log(s) for the constant-rate predictor")
    parser.add_argument("--exclude-corpus", action="store_true", help="leave out rows of corpus objects (held-out logs)")
    parser.add_argument("--bootstrap", type=int, default=BOOTSTRAP, help="resamples over objects (default: %(default)s)")
    parser.add_argument("--json", type=Path, help="write the comparison here")
    args = parser.parse_args(argv)
    config = Config()
    try:
        variants = {}
        for given in args.variant:
            name, _, paths = given.partition("=")
            if not name or not paths:
                raise JudgeError(f"--variant takes NAME=LOG[,LOG...], got {given!r}")
            variants[name] = paths.split(",")
        corpus = load_corpus("default", config.mesh.default_mass) if args.exclude_corpus else None
        base = read_log(args.base, config, corpus, exclude_corpus=args.exclude_corpus)
        rate = observed_topple_rate(read_log(args.rate_from, config)) if args.rate_from else None
        out = {"base": args.base, "rate": rate, "rate_from": args.rate_from, "model": "the defaults", "variants": {}}
        for name, paths in variants.items():
            variant = read_log(paths, config, corpus, exclude_corpus=args.exclude_corpus)
            result = compare(base, variant, config, rate, args.bootstrap)
            out["variants"][name] = {"logs": paths, **result}
            print(format_comparison(name, result), flush=True)
    except (JudgeError, LogError, CorpusError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json:
        write_text_atomic(args.json, json.dumps(to_json(out), indent=1, allow_nan=False) + "\n")
        print(f"json: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
