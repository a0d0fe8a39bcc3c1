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

The logs must be one play: every object both hold played with the same seed, model, noise and mesh, base at
the player's defaults (the part files' recorded keys say so). Per variant, on the trials both logs hold (a
trial is a push's repeat):
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
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..model.config import Config
from .logreader import PLAY_METADATA_KEY, LogError, Push, PushLog, log_files, read_log, same_push
from .pushsim import player_parameters
from .scoring import Scorer, Scores, sup_tv
from .validation import BOOTSTRAP, bootstrap_metric_difference, observed_topple_rate, percentile_interval, push_metrics, to_json

PREDICTORS = ("default", "never_topples", "constant_rate")
"""What is scored on every log: the default model and the two trivial predictors."""


class JudgeError(ValueError):
    """Logs that cannot be compared; one line."""


def played_with(paths: list[str | Path]) -> dict[str, dict]:
    """What each object of ``toppledb play`` logs was played with: object id -> its part file's key
    (``playlog.PlayParams.key``: the object, the model and noise, the seed, the player).

    raises JudgeError : a file that is not a ``toppledb play`` part file, or an object in two files
    """
    keys: dict[str, dict] = {}
    for file in log_files(paths):
        try:
            key = json.loads((pq.read_schema(file).metadata or {})[PLAY_METADATA_KEY])["key"]
        except (OSError, KeyError, ValueError, pa.ArrowException):
            raise JudgeError(f"{file} is not a toppledb play part file: only plays of known settings can be compared") from None
        if key["object_id"] in keys:
            raise JudgeError(f"object {key['object_id']} is in two files of one side ({file}): give each side one play")
        keys[key["object_id"]] = key
    return keys


def same_play(base: dict[str, dict], variant: dict[str, dict]) -> dict:
    """Check that two logs are one play under two player settings; the two sides' settings.

    base, variant : ``played_with``'s
    returns : {"base": player parameters, "variant": player parameters}
    raises JudgeError : an object both sides hold played otherwise than by the player (another seed, noise
      draws, model or mesh), base not at the player's defaults, or a side with more than one setting
    """
    for name, keys in (("base", base), ("variant", variant)):
        if len({json.dumps(k["player"], sort_keys=True) for k in keys.values()}) > 1:
            raise JudgeError(f"the {name} logs were played with more than one player setting")
    for object_id in base.keys() & variant.keys():
        a, b = ({k: v for k, v in key[object_id].items() if k != "player"} for key in (base, variant))
        if a != b:
            differ = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
            raise JudgeError(f"object {object_id} was played otherwise, not only by the player ({', '.join(differ)} "
                             "differ): not the same play under other settings")
    players = {name: next(iter(keys.values()))["player"] for name, keys in (("base", base), ("variant", variant))}
    if players["base"] != player_parameters():
        raise JudgeError("the base logs were not played with the player's defaults")
    return players


def common_pushes(base: PushLog, variant: PushLog) -> tuple[PushLog, PushLog, dict]:
    """Both logs restricted to the trials they both hold: the pushes of both, each with the repeats of both.

    A push is named by (object id, push id) and a trial by its repeat number within it, so a row one log
    rejected (an object that left its pose before the push, say) leaves that trial out of both.
    returns : (base, variant, counts) with the same pushes in the same order and each push's outcomes in
      repeat order; counts : {"base_only", "variant_only"}, pushes one log lacks, and "trials_unpaired",
      trials of common pushes one log lacks
    raises JudgeError : a push named twice in one log, or one the two logs describe differently
    """
    def by_key(log: PushLog, name: str) -> dict:
        pushes = {}
        for push in log.pushes:
            if pushes.setdefault((push.object_id, push.push_id), push) is not push:
                raise JudgeError(f"push {push.push_id} of {push.object_id} is in two of the {name} logs")
        return pushes

    a, b = by_key(base, "base"), by_key(variant, "variant")
    pairs, unpaired_trials = [], 0
    for key in sorted(a.keys() & b.keys()):
        first, second = a[key], b[key]
        if not same_push(first, second):
            raise JudgeError(f"push {key[1]} of {key[0]} differs between the logs: not the same play under other settings")
        both = np.intersect1d(first.repeats, second.repeats)
        unpaired_trials += len(first.repeats) + len(second.repeats) - 2 * len(both)
        if len(both):
            pairs.append((on_repeats(first, both), on_repeats(second, both)))

    def restricted(log: PushLog, pushes: list) -> PushLog:
        objects = {p.object_id for p in pushes}
        return PushLog({k: v for k, v in log.objects.items() if k in objects}, pushes, log.rejected, log.examples,
                       log.rows, log.files, log.logs)

    paired = {(p.object_id, p.push_id) for p, _ in pairs}
    counts = {"base_only": len(a.keys() - b.keys()), "variant_only": len(b.keys() - a.keys()),
              "pushes_without_common_trials": len(a.keys() & b.keys()) - len(paired), "trials_unpaired": int(unpaired_trials)}
    return restricted(base, [p for p, _ in pairs]), restricted(variant, [q for _, q in pairs]), counts


def on_repeats(push: Push, repeats: np.ndarray) -> Push:
    """``push`` with only the outcomes of ``repeats`` ((k,) int, sorted, each one of ``push.repeats``), in their order."""
    order = np.argsort(push.repeats)
    return replace(push, outcomes=push.outcomes[order][np.searchsorted(push.repeats[order], repeats)], repeats=repeats)


def trial_agreement(base: PushLog, variant: PushLog) -> dict:
    """How often the same trial ends the same way, over every paired trial.

    base, variant : ``common_pushes``'s, the same pushes and repeats in the same order
    returns : {"trials": int, "same_final_pose": share, "same_toppled": share}
    """
    first = np.concatenate([p.outcomes for p in base.pushes])
    second = np.concatenate([p.outcomes for p in variant.pushes])
    start = np.concatenate([np.full(len(p.outcomes), p.pose) for p in base.pushes])
    return {"trials": len(first), "same_final_pose": float(np.mean(first == second)),
            "same_toppled": float(np.mean((first != start) == (second != start)))}


def topple_rates(base: PushLog, variant: PushLog, n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """Each log's topple rate over its trials, and the variant's minus base's with a 95 % interval
    over objects (the same objects resampled for both).

    base, variant : ``common_pushes``'s
    returns : {"base": share, "variant": share, "difference": float, "ci": [low, high]}
    """
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
    """Mean over pushes of the sup-TV between the two logs' observed next-pose distributions (in [0, 1])."""
    tv = [sup_tv(a.empirical, b.empirical) for a, b in zip(base.groups, variant.groups)]
    return float(np.mean(np.concatenate(tv)))


def paired_metrics(base: Scores, variant: Scores, observed: tuple[np.ndarray, np.ndarray], objects: np.ndarray,
                   n_resamples: int = BOOTSTRAP, seed: int = 0) -> dict:
    """One predictor's metrics (``validation.push_metrics``) on each log, and the variant's minus base's
    bootstrapped over objects.

    base, variant : the predictor's scores against each log (the same pushes in the same order)
    observed : (n,) float each, the pushes' topple rates in base and in the variant
    objects : (n,) int, object of each push
    returns : {"base": metrics, "variant": metrics, "difference": metric -> {"difference", "ci"}}
    """
    on = [push_metrics(s.tv, s.p_topple, o, objects, s.brier) for s, o in zip((base, variant), observed)]
    difference = bootstrap_metric_difference(variant, base, observed[1], objects, n_resamples, seed, second_observed=observed[0])
    return {"base": on[0], "variant": on[1], "difference": difference}


def compare(base: PushLog, variant: PushLog, config: Config, rate: float | None, n_resamples: int = BOOTSTRAP,
            predicted: dict | None = None) -> dict:
    """Everything the module docstring lists for one variant against base (JSON-ready).

    rate : the constant-rate predictor's topple rate (left out when None)
    predicted : the model's predictions by the pushes they are of, kept between calls on one base: every
      variant that pairs all of base's pushes reuses them instead of predicting base again
    raises JudgeError : logs with no push in common, or pushes they describe differently
    """
    base, variant, counts = common_pushes(base, variant)
    if not base.pushes:
        raise JudgeError("the logs hold no push in common")
    scorers = [Scorer(log, config.seed, config.contacts) for log in (base, variant)]
    groups = [[(g.object_id, g.pose.index, tuple(g.rows)) for g in s.groups] for s in scorers]
    assert groups[0] == groups[1], "common_pushes gives both logs the same pushes in the same order"
    # The same pushes: the model's rows are predicted once and scored against both logs (and every variant
    # of the same pushes): they depend on the pushes, not on what physics made of them.
    predicted = {} if predicted is None else predicted
    pushes = tuple((p.object_id, p.push_id) for p in base.pushes)
    if pushes not in predicted:
        predicted[pushes] = scorers[0].predict(config.topple)
    predictions = predicted[pushes]
    scores = {"default": [s.score_predictions(predictions) for s in scorers],
              "never_topples": [s.never_topples() for s in scorers]}
    if rate is not None:
        scores["constant_rate"] = [s.constant_rate(rate) for s in scorers]
    observed = (scorers[0].empirical_topple, scorers[1].empirical_topple)
    return {
        "pushes": len(base.pushes),
        "objects": len(scorers[0].object_ids),
        "unpaired": counts,
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
            if name in variants:
                raise JudgeError(f"--variant {name} is given twice")
            variants[name] = paths.split(",")
        # Before minutes of reading: every variant must be the base's play under other player settings.
        base_keys = played_with(args.base)
        players = {name: same_play(base_keys, played_with(paths)) for name, paths in variants.items()}
        corpus = load_corpus("default", config.mesh.default_mass) if args.exclude_corpus else None
        base = read_log(args.base, config, corpus, exclude_corpus=args.exclude_corpus)
        rate = observed_topple_rate(read_log(args.rate_from, config)) if args.rate_from else None
        out = {"base": args.base, "base_player": player_parameters(), "rate": rate, "rate_from": args.rate_from, "model": "the defaults", "variants": {}}
        predicted: dict = {}
        for name, paths in variants.items():
            variant = read_log(paths, config, corpus, exclude_corpus=args.exclude_corpus)
            result = compare(base, variant, config, rate, args.bootstrap, predicted)
            out["variants"][name] = {"logs": paths, "player": players[name]["variant"], **result}
            print(format_comparison(name, result), flush=True)
    except (JudgeError, LogError, CorpusError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json:
        write_text_atomic(args.json, json.dumps(to_json(out), indent=1, allow_nan=False) + "\n")
        print(f"json: {args.json}")
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
