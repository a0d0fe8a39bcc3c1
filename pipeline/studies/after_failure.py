"""P(topple) after a failed push: fit and judge the map /plan serves with ``failed_actions``.

Played in pybullet, a push's first try topples about as often as its P(topple) says, while
the pushes played after a push has left the object in its pose topple far less (docs/
VALIDATION.md, "After a failed push").  ``schema.retry.after_failure`` maps P to p^k; this
study fits k on the pushes of ``robust_policy`` runs (``--pushes FILE``, one JSON object per
push played, in play order) and scores a k on others, beside the trivial predictors.

    python -m pipeline.studies.after_failure fit /tmp/rp0.jsonl /tmp/rp1.jsonl          # corpus objects
    python -m pipeline.studies.after_failure score --power K /tmp/hrp0.jsonl /tmp/hrp1.jsonl
    python -m pipeline.studies.after_failure report --fit C0.jsonl C1.jsonl --judge H0.jsonl H1.jsonl \
        --gains C0.json C1.json H0.json H1.json --json reports/after_failure.json

Only the pushes of one policy (``--policy``, default ``untried_vi``: the service's choice
after a failure, value iteration among the pushes no failed one rules out) that follow a
push which left the object where it was are used.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from schema import retry

from ..build.atomic import write_text_atomic

POWERS = np.round(np.arange(1.0, 6.0 + 1e-9, 0.05), 2)
"""The k tried by ``fit``: 1 (the table's P) to 6."""


def after_failed_pushes(pushes: list[dict], policy: str) -> list[dict]:
    """The pushes of ``policy`` made right after one of its pushes failed in the same trial.

    pushes : one run's records in play order (``trial``, ``policy``, ``p_topple``, ``toppled``,
      ``object_id``); a failed push leaves the object in its pose, so the next one starts there.
    returns : those records
    """
    previous: dict[int, dict] = {}
    chosen = []
    for push in pushes:
        if push["policy"] != policy:
            continue
        before = previous.get(push["trial"])
        if before is not None and not before["toppled"]:
            chosen.append(push)
        previous[push["trial"]] = push
    return chosen


def brier(predicted: np.ndarray, toppled: np.ndarray) -> float:
    """Mean squared error of probabilities against 0/1 outcomes."""
    return float(np.mean((np.asarray(predicted, float) - np.asarray(toppled, float)) ** 2))


def mapped(p_topple: np.ndarray, power: float) -> np.ndarray:
    """``schema.retry.after_failure`` over an array: p^k, p clipped as it clips.  p_topple : (n,) float"""
    return retry.clip_probability(p_topple) ** power


def fit_power(p_topple: np.ndarray, toppled: np.ndarray, powers: np.ndarray = POWERS) -> float:
    """The k of least Brier score (the smallest of equal scores)."""
    scores = [brier(mapped(p_topple, k), toppled) for k in powers]
    return float(powers[int(np.argmin(scores))])


def score(p_topple: np.ndarray, toppled: np.ndarray, power: float, constant: float | None) -> dict:
    """Mean prediction and Brier score of the map, the table's P, never topples and a constant rate."""
    p_topple, toppled = np.asarray(p_topple, float), np.asarray(toppled, float)
    predictors = {f"p^{power:g}": mapped(p_topple, power), "table P": p_topple, "never topples": np.zeros(len(p_topple))}
    if constant is not None:
        predictors[f"constant {constant:.3f}"] = np.full(len(p_topple), constant)
    return {
        "pushes": len(p_topple),
        "toppled": float(toppled.mean()) if len(toppled) else None,
        "predictors": {name: {"mean": float(v.mean()), "brier": brier(v, toppled)} for name, v in predictors.items()},
    }


def breakdown(pushes: list[dict], policy: str, power: float) -> dict:
    """What ``policy``'s pushes were predicted to do against what they did: first tries (in a
    pose the object has just come to, at the start or after a topple), the same push again
    right after it failed, and another push after a failure (its prediction also through the map).

    pushes : one run's records in play order;  returns : per kind, pushes, mean P, rate
    """
    failed = {id(r) for r in after_failed_pushes(pushes, policy)}
    previous: dict[int, dict] = {}
    kinds: dict[str, list[tuple[float, bool]]] = {"first try": [], "same push again": [], "another push": []}
    for push in pushes:
        if push["policy"] != policy:
            continue
        before = previous.get(push["trial"])
        kind = "first try" if id(push) not in failed else ("same push again" if push["action"] == before["action"] else "another push")
        kinds[kind].append((push["p_topple"], push["toppled"]))
        previous[push["trial"]] = push
    out = {}
    for kind, values in kinds.items():
        if values:
            p, toppled = np.array([v[0] for v in values]), np.array([v[1] for v in values], float)
            out[kind] = {"pushes": len(values), "p_topple": float(p.mean()), "toppled": float(toppled.mean())}
            if kind == "another push":
                out[kind][f"p^{power:g}"] = float(mapped(p, power).mean())
    return out


def told(pushes: list[dict], policy: str, power: float) -> dict:
    """What a re-planning client is told about every push it makes, against what they did: the
    table's P of first tries, and after a failure P^k when it reports the failure (``policy``
    chooses among untried pushes) or the table's P when it does not (``power`` None)."""
    failed = {id(r) for r in after_failed_pushes(pushes, policy)}
    said, did = [], []
    for push in pushes:
        if push["policy"] == policy:
            p = push["p_topple"]
            said.append(retry.after_failure(p, power) if (power is not None and id(push) in failed) else p)
            did.append(push["toppled"])
    return {"pushes": len(said), "told": float(np.mean(said)), "toppled": float(np.mean(did)),
            "gap": float(np.mean(said) - np.mean(did))}


def read_runs(paths: list[str]) -> list[list[dict]]:
    """The pushes of each ``robust_policy --pushes`` file, in play order."""
    return [[json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()] for path in paths]


def report(fit_paths: list[str], judge_paths: list[str], gain_paths: list[str], policy: str) -> dict:
    """The whole study: k fitted on ``fit_paths``, scored on ``judge_paths``, each set's pushes
    broken down per policy, what re-planning clients are told, and the runs' V_s gains."""
    p, toppled = read_pushes(fit_paths, policy)
    power = fit_power(p, toppled)
    judged_p, judged_toppled = read_pushes(judge_paths, policy)
    sets = {"fit": read_runs(fit_paths), "judge": read_runs(judge_paths)}
    pooled = {name: [push for i, run in enumerate(runs) for push in _tagged(run, i)] for name, runs in sets.items()}
    return {
        "power": power,
        "fit": score(p, toppled, power, float(toppled.mean())),
        "judged": score(judged_p, judged_toppled, power, round(float(toppled.mean()), 3)),
        "breakdown": {name: {pol: breakdown(pushes, pol, power) for pol in sorted({r["policy"] for r in pushes})}
                      for name, pushes in pooled.items()},
        "told": {name: {"re-asking (value_iteration)": told(pushes, "value_iteration", None),
                        f"reporting failures ({policy})": told(pushes, policy, power)}
                 for name, pushes in pooled.items()},
        "gains": {path: {pol: {k: v for k, v in row.items() if k.startswith("gain_over")}
                         for pol, row in json.loads(Path(path).read_text())["policies"].items()}
                  for path in gain_paths},
    }


def _tagged(run: list[dict], index: int) -> list[dict]:
    """A run's pushes with trial numbers kept apart from other runs' (pooled runs share trial ids)."""
    return [{**push, "trial": (index, push["trial"])} for push in run]


def read_pushes(paths: list[str], policy: str) -> tuple[np.ndarray, np.ndarray]:
    """P(topple) and outcome of ``policy``'s after-failure pushes over the runs in ``paths``."""
    chosen = []
    for path in paths:
        records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        chosen += after_failed_pushes(records, policy)
    return np.array([r["p_topple"] for r in chosen], float), np.array([r["toppled"] for r in chosen], bool)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.after_failure", description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=["fit", "score", "report"])
    parser.add_argument("pushes", nargs="*", help="robust_policy --pushes files (fit, score)")
    parser.add_argument("--policy", default="untried_vi")
    parser.add_argument("--power", type=float, help="k to score (score)")
    parser.add_argument("--constant", type=float, help="a constant rate to show beside it (score), e.g. the fit's rate")
    parser.add_argument("--fit", nargs="+", default=[], metavar="FILE", help="report: the pushes k is fitted on")
    parser.add_argument("--judge", nargs="+", default=[], metavar="FILE", help="report: the pushes it is judged on")
    parser.add_argument("--gains", nargs="*", default=[], metavar="FILE", help="report: robust_policy --json files")
    parser.add_argument("--json", metavar="FILE", help="report: write it here too")
    args = parser.parse_intermixed_args(argv)  # files before or after the options
    if args.mode == "report":
        if not (args.fit and args.judge):
            parser.exit(2, "report needs --fit FILE... and --judge FILE...\n")
        result = report(args.fit, args.judge, args.gains, args.policy)
        text = json.dumps(result, indent=1)
        if args.json:
            write_text_atomic(args.json, text + "\n")
        print(text)
        return 0
    if not args.pushes:
        parser.exit(2, f"{args.mode} needs robust_policy --pushes files\n")
    p_topple, toppled = read_pushes(args.pushes, args.policy)
    if len(p_topple) == 0:
        parser.exit(2, f"no {args.policy} push follows a failed one in {args.pushes}\n")
    if args.mode == "fit":
        power = fit_power(p_topple, toppled)
        result = {"power": power, **score(p_topple, toppled, power, float(toppled.mean()))}
    else:
        if args.power is None or args.power < 1:
            parser.exit(2, "score needs --power K, K >= 1\n")
        result = score(p_topple, toppled, args.power, args.constant)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
