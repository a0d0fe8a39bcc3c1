"""P(topple) after a failed push: fit and judge the map /plan serves with ``failed_actions``.

Played in pybullet, a push's first try topples about as often as its P(topple) says, while
the pushes played after a push has left the object in its pose topple far less (docs/
VALIDATION.md, "After a failed push").  ``schema.retry.after_failure`` maps P to p^k; this
study fits k on the pushes of ``robust_policy`` runs (``--pushes FILE``, one JSON object per
push played, in play order) and scores a k on others, beside the trivial predictors.

    python -m pipeline.studies.after_failure fit /tmp/rp0.jsonl /tmp/rp1.jsonl          # corpus objects
    python -m pipeline.studies.after_failure score --power K /tmp/hrp0.jsonl /tmp/hrp1.jsonl

Only the pushes of one policy (``--policy``, default ``untried_vi``: the service's choice
after a failure, value iteration among the pushes no failed one rules out) that follow a
push which left the object where it was are used.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from schema.retry import after_failure

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
    return np.array([after_failure(p, power) for p in np.asarray(p_topple, float)])


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


def read_pushes(paths: list[str], policy: str) -> tuple[np.ndarray, np.ndarray]:
    """P(topple) and outcome of ``policy``'s after-failure pushes over the runs in ``paths``."""
    chosen = []
    for path in paths:
        records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        chosen += after_failed_pushes(records, policy)
    return np.array([r["p_topple"] for r in chosen], float), np.array([r["toppled"] for r in chosen], bool)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.after_failure", description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=["fit", "score"])
    parser.add_argument("pushes", nargs="+", help="robust_policy --pushes files")
    parser.add_argument("--policy", default="untried_vi")
    parser.add_argument("--power", type=float, help="k to score (score)")
    parser.add_argument("--constant", type=float, help="a constant rate to show beside it (score), e.g. the fit's rate")
    args = parser.parse_args(argv)
    p_topple, toppled = read_pushes(args.pushes, args.policy)
    if len(p_topple) == 0:
        parser.exit(2, f"no {args.policy} push follows a failed one in {args.pushes}\n")
    if args.mode == "fit":
        power = fit_power(p_topple, toppled)
        report = {"power": power, **score(p_topple, toppled, power, float(toppled.mean()))}
    else:
        if args.power is None or args.power < 1:
            parser.exit(2, "score needs --power K, K >= 1\n")
        report = score(p_topple, toppled, args.power, args.constant)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
