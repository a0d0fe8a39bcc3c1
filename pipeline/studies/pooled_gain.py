"""A policy's gain over a baseline pooled over many runs, with the uncertainty the objects carry.

Issue 9's value iteration goal is judged on many runs of ``pipeline.studies.robust_policy``: several
seeds, each over the same held-out objects.  The standard error over runs measures how much the
seeds' draws (start poses, noise) move the pooled gain on *these* objects.  What a robot meets is new
objects, and the objects differ among themselves far more than the draws do: an object whose poses
a push rescues gains on every seed, one it cannot gains on none.  More seeds do not shrink that part;
only more objects would.  This pools runs' ``--trials-out`` files and reports both: the gain pooled
over the useful trials, its SE over runs, its SE treating trials as independent, and its SE with the
trials clustered by object (the linearised standard error of a ratio of sums over objects, the usual
cluster-robust one), with the 95 % interval each gives.

    python -m pipeline.studies.pooled_gain RUN.jsonl [RUN.jsonl ...] [--policy value_iteration] [--baseline max_height]

A trial counts as in ``robust_policy``'s ``gain_over_max_height``: inside the pose set and useful.
Trials are clustered by ``object_id`` across every file, so the files must name their objects
(``robust_policy`` writes ``object_id`` since stop 45).  ``never_push``, the trivial planner that grasps
where the object lies, gains nothing on any trial; the files do not hold it, and ``--policy never_push``
pools it as 0 so that it is shown with the same intervals as the planners.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .paired_trials import NEVER_PUSH, PairingError, read_trials
from .policies_physics import mean_se

Z_95 = 1.959963984540054


def run_differences(trials: dict[int, dict], policy: str, baseline: str, path: str | Path) -> tuple[np.ndarray, list[str]]:
    """One run's gain of ``policy`` over ``baseline`` on the trials that count.

    trials : one run's records, ``paired_trials.read_trials``
    returns : (n,) float, V_s, in trial order, and the n trials' object ids
    raises PairingError : a counted trial lacks either policy or its object id
    """
    differences, objects = [], []
    for t in sorted(trials):
        record = trials[t]
        if record["outside"] or not record["useful"]:
            continue
        gains = {NEVER_PUSH: 0.0, **record["gains"]}
        missing = [name for name in (policy, baseline) if name not in gains]
        if missing:
            raise PairingError(f"{path}: trial {t} has no policy {missing[0]!r}; it played {', '.join(sorted(record['gains']))}")
        if not record["object_id"]:
            raise PairingError(f"{path}: trial {t} names no object_id (a file written before stop 45?); "
                               "its trials cannot be grouped by object")
        differences.append(float(gains[policy]) - float(gains[baseline]))
        objects.append(str(record["object_id"]))
    return np.array(differences, dtype=float), objects


def clustered_mean_se(values: np.ndarray, clusters: list[str]) -> tuple[float, float, int]:
    """The mean of ``values`` and its standard error with the values grouped into clusters.

    values : (n,) float; clusters : n labels
    returns : (mean, se, number of clusters).  The mean is sum over clusters of s_c over sum of n_c
      (s_c the cluster's sum, n_c its count); se^2 = G / (G - 1) sum_c (s_c - mean n_c)^2 / n^2, the
      linearised variance of that ratio when the G clusters are drawn independently.  With one value
      per cluster it is the ordinary SE of a mean; nan below two clusters (``pool`` reports None).
    """
    labels, index = np.unique(np.asarray(clusters, dtype=object).astype(str), return_inverse=True)
    sums = np.bincount(index, weights=values, minlength=len(labels))
    counts = np.bincount(index, minlength=len(labels)).astype(float)
    n, groups = float(counts.sum()), len(labels)
    mean = float(sums.sum() / n) if n else float("nan")
    if groups < 2:
        return mean, float("nan"), groups
    residual = sums - mean * counts
    return mean, float(np.sqrt(groups / (groups - 1) * np.sum(residual**2)) / n), groups


def clustered_entry(values, clusters, counted: str) -> dict:
    """``clustered_mean_se`` as a report's entry: {"mean", "se" (None below two clusters), "objects": the
    number of clusters, ``counted``: the number of values} (the studies cluster by object)."""
    mean, se, count = clustered_mean_se(np.asarray(values, dtype=float), list(clusters))
    return {"mean": mean, "se": None if np.isnan(se) else se, "objects": count, counted: len(values)}


def pool(paths: list[str | Path], policy: str = "value_iteration", baseline: str = "max_height") -> dict:
    """The gain of ``policy`` over ``baseline`` pooled over the runs' counted trials, with three
    standard errors: over runs (of the runs' means), over trials (as if independent) and clustered by
    object.  Each run's own count and mean come along."""
    runs, pooled, objects = [], [], []
    for path in paths:
        differences, run_objects = run_differences(read_trials(path), policy, baseline, path)
        runs.append({"file": str(path), "trials": len(differences),
                     "mean": float(differences.mean()) if len(differences) else None})
        pooled.append(differences)
        objects += run_objects
    values = np.concatenate(pooled) if pooled else np.zeros(0)
    if len(values) < 2:
        raise PairingError(f"{len(values)} counted trial(s) in {len(paths)} run(s): nothing to pool")
    runs_mean, runs_se = mean_se([r["mean"] for r in runs if r["mean"] is not None])
    mean, clustered_se, groups = clustered_mean_se(values, objects)
    if np.isnan(clustered_se):  # one object: no spread between objects to measure (None, as paired_trials', not NaN)
        clustered_se = None
    result = {"policy": policy, "baseline": baseline, "runs": runs, "trials": len(values), "objects": groups,
              "pooled": mean, "runs_mean": runs_mean, "runs_se": runs_se, "trials_se": mean_se(values)[1],
              "objects_se": clustered_se}
    result["objects_interval_95"] = None if clustered_se is None else [mean - Z_95 * clustered_se, mean + Z_95 * clustered_se]
    return result


def text(result: dict) -> str:
    def se(value: float | None) -> str:
        return "-" if value is None else f"{value:.4f}"

    lines = [(f"{result['policy']} minus {result['baseline']}, pooled over {result['trials']} useful trials of "
             f"{len(result['runs'])} runs on {result['objects']} objects: {result['pooled']:+.4f}"),
             (f"  SE over runs {se(result['runs_se'])} (the runs' mean {result['runs_mean']:+.4f}); over trials "
             f"{se(result['trials_se'])}; clustered by object {se(result['objects_se'])}"
             + ("" if result["objects_interval_95"] is None else
                f", 95 % [{result['objects_interval_95'][0]:+.4f}, {result['objects_interval_95'][1]:+.4f}]"))]
    lines += [f"  {r['trials']:>5} trials  {'-' if r['mean'] is None else format(r['mean'], '+.4f'):>8}  {Path(r['file']).name}"
              for r in result["runs"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.pooled_gain", description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", metavar="RUN.jsonl", help="runs' --trials-out files (robust_policy)")
    parser.add_argument("--policy", default="value_iteration", help=f"(default: %(default)s; {NEVER_PUSH}: 0 on every trial)")
    parser.add_argument("--baseline", default="max_height", help="(default: %(default)s)")
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    if refused_outputs(args.json):
        return 2
    try:
        result = pool(args.files, args.policy, args.baseline)
    except PairingError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
