"""Two boosted maps' folds scored out of fold on each of several push logs.

``toppledb recalibrate --boosted --fold-maps DIR`` writes each fold's map, fitted without the fold's
objects; ``--folds-from`` fits another map on the same folds.  Here every logged push is mapped by
the fold map of its object's fold, A's and B's, and each log gets its own score: a map refitted
with a new log (the pushes a planner weighs, say) is judged on that log and, separately, on the
logs it was fitted on before, all out of fold.  The score is the Brier score of P(topple) weighted
by plays (``recalibrate.brier``), with B minus A bootstrapped over objects (paired: the same pushes).

    python -m pipeline.studies.compare_fold_maps data/corpus_folds data/corpus_folds_bp LOG... --json F
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..model.boosted_map import BoostedMapError, load_trees
from ..model.config import Config
from .logreader import LogError, read_log
from .recalibrate import RecalibrationError, fold_of_pushes, metrics, out_of_fold, read_fold_lists
from .scoring import Scorer
from .validation import percentile_interval

BOOTSTRAP = 2000
"""Resamples of the objects for B minus A's interval."""


def paired_interval(difference: np.ndarray, weight: np.ndarray, objects: np.ndarray, seed: int = 0) -> list[float]:
    """95 % bootstrap interval over objects of the weighted mean of ``difference``, (n,) per push."""
    ids = np.unique(objects)
    index = np.searchsorted(ids, objects)
    num = np.bincount(index, weight * difference, len(ids))
    den = np.bincount(index, weight, len(ids))
    draws = np.random.default_rng(seed).integers(0, len(ids), (BOOTSTRAP, len(ids)))
    return percentile_interval(num[draws].sum(axis=1) / den[draws].sum(axis=1))


def compare(a: Path, b: Path, logs: list[str], config: Config, corpus=None) -> dict:
    """Per log: pushes, objects, A's and B's metrics out of fold (``recalibrate.metrics``), B minus A's
    Brier and its interval.  A and B must hold the same fold lists."""
    folds = read_fold_lists(a)
    if read_fold_lists(b) != folds:
        raise RecalibrationError(f"{a} and {b} hold different folds; fit B with --folds-from {a}")
    try:
        maps = {name: [load_trees(str(d / f"fold_{k}.trees.json")) for k in range(len(folds))] for name, d in (("a", a), ("b", b))}
    except (BoostedMapError, OSError) as err:
        raise RecalibrationError(str(err)) from None
    out = {"a": str(a), "b": str(b), "folds": len(folds), "logs": {}}
    for path in logs:
        log = read_log([path], config, corpus, corpus_only=corpus is not None)
        if not log.pushes:
            raise RecalibrationError(f"no usable pushes in {path} ({log.rows} rows; rejected: {dict(log.rejected)})")
        scorer = Scorer(log, config.seed, config.contacts)
        features, p, lands = scorer.boosted_inputs(config.topple)
        observed, weight, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
        fold_of = fold_of_pushes([scorer.object_ids[i] for i in objects], folds)
        rows = np.isfinite(p)
        record: dict = {"pushes": int(rows.sum()), "objects": len(scorer.object_ids)}
        per_push = {}
        for name, trees in maps.items():
            q = out_of_fold(features, p, lands, fold_of, trees)[rows]
            record[name] = metrics(q, observed[rows], weight[rows], objects[rows])
            per_push[name] = (q - observed[rows]) ** 2
        record["b_minus_a_brier"] = record["b"]["brier"] - record["a"]["brier"]
        record["b_minus_a_interval"] = paired_interval(per_push["b"] - per_push["a"], weight[rows], objects[rows])
        out["logs"][path] = record
    return out


def text(result: dict) -> str:
    lines = [f"A {result['a']}, B {result['b']}; {result['folds']} folds, each push by its fold's maps",
             f"{'log':<40} {'pushes':>7} {'Brier A':>8} {'Brier B':>8} {'B - A':>8}  {'95 % over objects':<20} {'ECE A':>6} {'ECE B':>6}"]
    for path, r in result["logs"].items():
        low, high = r["b_minus_a_interval"]
        lines.append(f"{path[-40:]:<40} {r['pushes']:>7} {r['a']['brier']:>8.4f} {r['b']['brier']:>8.4f} {r['b_minus_a_brier']:>+8.4f}  "
                     f"[{low:+.4f}, {high:+.4f}]   {r['a']['ece']:>6.3f} {r['b']['ece']:>6.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..build.corpus import CorpusError, load_corpus
    from ..cli import UsageError, make_config, print_and_record

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.compare_fold_maps", description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="fold maps A (a --fold-maps DIR)")
    parser.add_argument("b", type=Path, help="fold maps B, fitted on the same folds (--folds-from A)")
    parser.add_argument("logs", nargs="+", help="push logs on the folds' objects, each scored on its own")
    parser.add_argument("--corpus", default="default", help="the logs' objects' corpus ('none': any object; default: %(default)s)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="the model the maps sit on (default: the defaults)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--json", type=Path, help="write the comparison here")
    args = parser.parse_args(argv)
    try:
        config = make_config(args)
        corpus = None if args.corpus == "none" else load_corpus(args.corpus, config.mesh.default_mass)
        result = compare(args.a, args.b, args.logs, config, corpus)
    except (UsageError, RecalibrationError, LogError, CorpusError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
