"""P(topple) after a failed push: fit and judge the map /plan serves with ``failed_actions``.

Played in pybullet, a push's first try topples about as often as its P(topple) says, while
the pushes played after a push has left the object in its pose topple far less (docs/
VALIDATION.md, "After a failed push").  ``schema.retry.after_failure`` maps P to p^k; this
study fits k on the pushes of ``robust_policy`` runs (``--pushes FILE``, one JSON object per
push played, in play order) and scores a k on others, beside the trivial predictors.
``fit-slope`` fits, for a given k, the slope s of a candidate k_f = max(1, k + s (P_f - 1/2))
(``slope_power``; P_f the largest P of the pushes that failed in the pose), and ``score --slope S``
scores it beside P^k, also per band of P_f (measured, not served: docs/VALIDATION.md, "A failure
weighed by its push").  ``fit-landing`` fits a power for each of two groups of the pushes after a
failure, those the model lands where it lands a failed push of the pose and the rest
(``landing_mapped``; the records' ``landing``), and ``score --landing-powers KS KO`` scores them
beside P^k (measured, not served: docs/VALIDATION.md, "Where the failed push lands").  ``score``
gives Brier differences with intervals over resampled objects.

    python -m pipeline.studies.after_failure fit /tmp/rp0.jsonl /tmp/rp1.jsonl          # corpus objects
    python -m pipeline.studies.after_failure score --power K /tmp/hrp0.jsonl /tmp/hrp1.jsonl
    python -m pipeline.studies.after_failure fit-slope --power K --policy belief_vi C*.jsonl --json FIT.json
    python -m pipeline.studies.after_failure score --power K --slope S --policy belief_vi H*.jsonl --json JUDGED.json
    python -m pipeline.studies.after_failure fit-landing --power K --policy belief_vi C*.jsonl --json FIT.json
    python -m pipeline.studies.after_failure score --power K --landing-powers KS KO --policy belief_vi H*.jsonl
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
from .scoring import Scores
from .validation import BOOTSTRAP, bootstrap_difference

POWERS = np.round(np.arange(1.0, 6.0 + 1e-9, 0.05), 2)
"""The k tried by ``fit``: 1 (the table's P) to 6."""

SLOPES = np.round(np.arange(0.0, 6.0 + 1e-9, 0.1), 1)
"""The s tried by ``fit-slope``: 0 (one k whatever failed) to 6."""

FAILED_P_CENTRE = 0.5
"""The failed push's P(topple) at which ``slope_power`` is k: the slope tilts k about it."""

FAILED_BANDS = (("P_f < 0.6", -np.inf, 0.6), ("P_f >= 0.6", 0.6, np.inf))
"""Bands of the failed pushes' largest P that ``score`` reports apart: unlikely and likely pushes failed."""


def failed_before(pushes: list[dict], policy: str, field: str = "p_topple") -> dict[int, list]:
    """The P(topple) (or another ``field`` of the records, e.g. ``landing``) of the pushes that had
    failed in its pose, for each push of ``policy`` made in a pose where one of its pushes failed
    earlier in the same trial.

    pushes : one run's records in play order (``trial``, ``policy``, ``pose``, ``p_topple``,
      ``toppled``, ``object_id``).  A failed push leaves the object in its pose; the player keeps
      a pose's failures for the whole trial (``robust_policy.play_object``), so a push there after
      the object toppled away and came back is an after-failure push too (with the default 3
      pushes a trial cannot come back, so then these are the pushes right after a failure).
    returns : id(record) -> the failed pushes' P (``field``) in play order, for those records
    """
    failed: dict[tuple, list] = {}
    found = {}
    for push in pushes:
        if push["policy"] != policy:
            continue
        where = (push["trial"], push["pose"])
        if where in failed:
            found[id(push)] = list(failed[where])
        if not push["toppled"]:
            failed.setdefault(where, []).append(push[field])
    return found


def after_failed_pushes(pushes: list[dict], policy: str) -> list[dict]:
    """The pushes of ``policy`` made where one of its pushes had failed in the same trial
    (``failed_before``'s records, in play order)."""
    return _after_failure_records([pushes], policy, "p_topple")[0]


def brier(predicted: np.ndarray, toppled: np.ndarray) -> float:
    """Mean squared error of probabilities against 0/1 outcomes."""
    return float(np.mean((np.asarray(predicted, float) - np.asarray(toppled, float)) ** 2))


def mapped(p_topple: np.ndarray, power: float, slope: float = 0.0, failed_p: np.ndarray | None = None) -> np.ndarray:
    """``schema.retry.after_failure`` over an array: p^k, p clipped as it clips, k the build's
    (``failed_p`` None) or each push's candidate ``slope_power``.

    p_topple : (n,) float;  failed_p : (n,) float, the largest P that had failed in each push's pose
    returns : (n,) float
    """
    p = retry.clip_probability(p_topple)
    if failed_p is None:
        if slope:
            raise ValueError("a slope needs each push's failed P (failed_p)")
        return p**power
    return p ** slope_power(power, slope, failed_p)


def slope_power(power: float, slope: float, failed_p: np.ndarray) -> np.ndarray:
    """The candidate k_f = max(1, k + s (P_f - 1/2)) of a push once pushes of largest P(topple)
    P_f have failed (docs/VALIDATION.md, "A failure weighed by its push"; measured, not served).

    A likely push that fails might say more about the pose than a long shot that fails; the
    floor keeps P^k_f at or below P, so a failure never makes a push likelier.
    failed_p : (n,) float, clipped to [0, 1] as P is;  returns : (n,) float
    """
    failed = retry.clip_probability(failed_p)
    return np.maximum(1.0, power + slope * (failed - FAILED_P_CENTRE))


def landing_mapped(p_topple: np.ndarray, same: np.ndarray, power_same: float, power_other: float) -> np.ndarray:
    """The candidate belief by where the model lands a push (docs/VALIDATION.md, "Where the failed
    push lands"; measured, not served): P^``power_same`` for a push the model lands where it lands a
    push that failed in the pose, P^``power_other`` for any other; P clipped as ``mapped`` clips it.

    p_topple : (n,) float;  same : (n,) bool;  returns : (n,) float
    """
    p = retry.clip_probability(p_topple)
    return np.where(np.asarray(same, dtype=bool), p**power_same, p**power_other)


def fit_power(p_topple: np.ndarray, toppled: np.ndarray, powers: np.ndarray = POWERS) -> float:
    """The k of least Brier score (the smallest of equal scores)."""
    scores = [brier(mapped(p_topple, k), toppled) for k in powers]
    return float(powers[int(np.argmin(scores))])


def fit_slope(p_topple: np.ndarray, failed_p: np.ndarray, toppled: np.ndarray, power: float,
              slopes: np.ndarray = SLOPES) -> float:
    """The s of least Brier score for this k (the smallest of equal scores).
    p_topple, failed_p, toppled : (n,) as ``mapped`` takes them"""
    scores = [brier(mapped(p_topple, power, s, failed_p), toppled) for s in slopes]
    return float(slopes[int(np.argmin(scores))])


def fit_landing(p_topple: np.ndarray, same: np.ndarray, toppled: np.ndarray) -> tuple[float, float]:
    """(k_same, k_other) of least Brier score: the two groups' squared errors add, so each power is
    ``fit_power`` over its own group's pushes.  Raises ``ValueError`` when a group has none.
    p_topple, same, toppled : (n,) float, bool, bool (``landing_arrays``)"""
    p_topple, toppled, same = np.asarray(p_topple, float), np.asarray(toppled, float), np.asarray(same, dtype=bool)
    if same.all() or not same.any():
        raise ValueError("fitting a power per landing needs pushes landing both where a failed push would and elsewhere")
    return fit_power(p_topple[same], toppled[same]), fit_power(p_topple[~same], toppled[~same])


def landing_score(p_topple: np.ndarray, toppled: np.ndarray, same: np.ndarray, power: float,
                  powers: tuple[float, float], constant: float | None) -> dict:
    """``score``'s predictors with the candidate by landing at ``powers`` (k_same, k_other) beside
    P^k, over all pushes and per group: those the model lands where it lands a failed push of the
    pose, and the rest.  p_topple, toppled, same : (n,) float, bool, bool (``landing_arrays``)"""
    p_topple, toppled, same = np.asarray(p_topple, float), np.asarray(toppled, float), np.asarray(same, dtype=bool)
    predictors = _predictors(p_topple, power, constant,
                             (f"by landing, k {powers[0]:g} / {powers[1]:g}", landing_mapped(p_topple, same, *powers)))
    result = _scored(predictors, toppled, np.ones(len(toppled), bool))
    result["groups"] = {"landing where a failed push would": _scored(predictors, toppled, same),
                        "landing elsewhere": _scored(predictors, toppled, ~same)}
    return result


def score(p_topple: np.ndarray, toppled: np.ndarray, power: float, constant: float | None,
          slope: float = 0.0, failed_p: np.ndarray | None = None) -> dict:
    """Mean prediction and Brier score of the map, the table's P, never topples and a constant
    rate; with ``failed_p``, the map at ``slope`` too, and every predictor per band of P_f
    (``FAILED_BANDS``)."""
    p_topple, toppled = np.asarray(p_topple, float), np.asarray(toppled, float)
    candidate = None if failed_p is None else (f"p^k_f, k {power:g}, slope {slope:g}", mapped(p_topple, power, slope, failed_p))
    predictors = _predictors(p_topple, power, constant, candidate)
    result = _scored(predictors, toppled, np.ones(len(toppled), bool))
    if failed_p is not None:
        failed_p = np.asarray(failed_p, float)
        result["bands"] = {name: _scored(predictors, toppled, (failed_p >= lo) & (failed_p < hi)) for name, lo, hi in FAILED_BANDS}
    return result


def _predictors(p_topple: np.ndarray, power: float, constant: float | None,
                candidate: tuple[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The predictors every score shows: the map P^k, a (name, prediction) candidate beside it, the
    table's P, never topples, and a constant rate when given; (n,) float each."""
    predictors = {f"p^{power:g}": mapped(p_topple, power)}
    if candidate is not None:
        predictors[candidate[0]] = candidate[1]
    predictors.update({"table P": p_topple, "never topples": np.zeros(len(p_topple))})
    if constant is not None:
        predictors[f"constant {constant:.3f}"] = np.full(len(p_topple), constant)
    return predictors


def brier_differences(p_topple: np.ndarray, toppled: np.ndarray, objects: np.ndarray, power: float,
                      slope: float | None = None, failed_p: np.ndarray | None = None,
                      n_resamples: int = BOOTSTRAP, seed: int = 0,
                      landing: tuple[np.ndarray, float, float] | None = None) -> dict:
    """Brier score differences per push, with 95 % intervals over objects resampled with
    replacement (``validation.bootstrap_difference``, paired: the pushes of one object, over all
    runs, err together): p^k minus the table's P, with ``slope`` the candidate p^k_f minus p^k, and
    with ``landing`` (same, k_same, k_other) the candidate ``landing_mapped`` minus p^k.
    Negative: the first is better.

    p_topple, toppled, objects : (n,) float, bool, str;  failed_p : (n,) float, with ``slope``
    returns : {name: {"difference", "interval"}}, and the number of objects
    """
    p_topple, toppled = np.asarray(p_topple, float), np.asarray(toppled, float)
    predicted = {"table": p_topple, "map": mapped(p_topple, power)}
    pairs = {f"p^{power:g} minus table P": ("map", "table")}
    if slope is not None:
        if failed_p is None:
            raise ValueError("a slope needs each push's failed P (failed_p)")
        predicted["slope"] = mapped(p_topple, power, slope, failed_p)
        pairs[f"p^k_f (slope {slope:g}) minus p^{power:g}"] = ("slope", "map")
    if landing is not None:
        same, power_same, power_other = landing
        predicted["landing"] = landing_mapped(p_topple, same, power_same, power_other)
        pairs[f"by landing (k {power_same:g} / {power_other:g}) minus p^{power:g}"] = ("landing", "map")
    scores = {name: Scores(tv=np.zeros(len(p)), p_topple=p, brier=(p - toppled) ** 2) for name, p in predicted.items()}
    result: dict = {"objects": len(np.unique(objects))}
    for label, (first, second) in pairs.items():
        paired = bootstrap_difference(scores[first], scores[second], toppled, objects, n_resamples, seed)["brier"]
        result[label] = {"difference": paired["difference"], "interval": paired["ci"]}
    return result


def _scored(predictors: dict[str, np.ndarray], toppled: np.ndarray, rows: np.ndarray) -> dict:
    """Pushes, topple rate, and each predictor's mean and Brier score over ``rows`` ((n,) bool)."""
    if not rows.any():
        return {"pushes": 0, "toppled": None, "predictors": {}}
    return {
        "pushes": int(rows.sum()),
        "toppled": float(toppled[rows].mean()),
        "predictors": {name: {"mean": float(v[rows].mean()), "brier": brier(v[rows], toppled[rows])} for name, v in predictors.items()},
    }


def breakdown(pushes: list[dict], policy: str, power: float) -> dict:
    """What ``policy``'s pushes were predicted to do against what they did: first tries (in a
    pose the object has just come to, at the start or after a topple), the same push again
    right after it failed, and another push after a failure (its prediction also through the map).

    pushes : one run's records in play order;  returns : per kind, pushes, mean P, rate
    """
    failed = failed_before(pushes, policy)
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
    failed = failed_before(pushes, policy)
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
    sets = {"fit": read_runs(fit_paths), "judge": read_runs(judge_paths)}
    p, toppled, _, _ = after_failure_arrays(sets["fit"], policy)
    power = fit_power(p, toppled)
    judged_p, judged_toppled, _, _ = after_failure_arrays(sets["judge"], policy)
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


def _after_failure_records(runs: list[list[dict]], policy: str, field: str) -> tuple[list[dict], list[list]]:
    """The after-failure pushes of ``policy`` over ``runs``, in play order, and for each the list of
    its failed pushes' ``field`` (``failed_before``)."""
    pushes, failed = [], []
    for records in runs:
        found = failed_before(records, policy, field)
        for push in records:
            if id(push) in found:
                pushes.append(push)
                failed.append(found[id(push)])
    return pushes, failed


def _arrays(pushes: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P(topple), outcome and object id of ``pushes``; (n,) each."""
    return (np.array([p["p_topple"] for p in pushes], float), np.array([p["toppled"] for p in pushes], bool),
            np.array([p["object_id"] for p in pushes], dtype=str))


def after_failure_arrays(runs: list[list[dict]], policy: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """P(topple), outcome, P_f (the largest P that had failed in the pose) and object id of
    ``policy``'s after-failure pushes over ``runs`` (``read_runs``); (n,) each."""
    pushes, failed = _after_failure_records(runs, policy, "p_topple")
    p_topple, toppled, objects = _arrays(pushes)
    return p_topple, toppled, np.array([max(f) for f in failed], float), objects


def landing_arrays(runs: list[list[dict]], policy: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """P(topple), outcome, whether the model lands the push where it lands a push that failed in the
    pose (both landings known, not -1), and object id of ``policy``'s after-failure pushes over
    ``runs``; (n,) each.  The records need ``landing`` (``robust_policy`` since stop 39): ``ValueError`` if not."""
    if any("landing" not in push for records in runs for push in records):
        raise ValueError("these pushes carry no model landing ('landing'): play them again with robust_policy")
    pushes, failed = _after_failure_records(runs, policy, "landing")
    p_topple, toppled, objects = _arrays(pushes)
    return p_topple, toppled, np.array([p["landing"] >= 0 and p["landing"] in f for p, f in zip(pushes, failed)], bool), objects


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.after_failure", description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=["fit", "fit-slope", "fit-landing", "score", "report"])
    parser.add_argument("pushes", nargs="*", help="robust_policy --pushes files (fit, fit-slope, fit-landing, score)")
    parser.add_argument("--policy", default="untried_vi")
    parser.add_argument("--power", type=float, help="k to score (score, fit-landing) or to fit the slope for (fit-slope)")
    parser.add_argument("--slope", type=float, help="s to score beside k alone (score): k + s (P_f - 1/2)")
    parser.add_argument("--landing-powers", type=float, nargs=2, metavar=("K_SAME", "K_OTHER"),
                        help="score beside k alone: K_SAME where the model lands a failed push of the pose, K_OTHER elsewhere")
    parser.add_argument("--constant", type=float, help="a constant rate to show beside it (score), e.g. the fit's rate")
    parser.add_argument("--fit", nargs="+", default=[], metavar="FILE", help="report: the pushes k is fitted on")
    parser.add_argument("--judge", nargs="+", default=[], metavar="FILE", help="report: the pushes it is judged on")
    parser.add_argument("--gains", nargs="*", default=[], metavar="FILE", help="report: robust_policy --json files")
    parser.add_argument("--json", metavar="FILE", help="write the result here too")
    args = parser.parse_intermixed_args(argv)  # files before or after the options
    if args.mode == "report":
        if not (args.fit and args.judge):
            parser.exit(2, "report needs --fit FILE... and --judge FILE...\n")
        return _emitted(report(args.fit, args.judge, args.gains, args.policy), args.json)
    if not args.pushes:
        parser.exit(2, f"{args.mode} needs robust_policy --pushes files\n")
    # The options before any file is read: each refusal names the one it refuses.
    if args.landing_powers is not None:
        if args.mode != "score":
            parser.exit(2, "--landing-powers is for score\n")
        if args.slope is not None:
            parser.exit(2, "--landing-powers and --slope are two candidates: score one at a time\n")
        if min(args.landing_powers) < 1:
            parser.exit(2, f"--landing-powers must be 1 or more, got {' '.join(f'{k:g}' for k in args.landing_powers)}\n")
    if args.slope is not None and args.mode not in ("score", "fit-slope"):
        parser.exit(2, "--slope is for score and fit-slope\n")
    by_landing = args.mode == "fit-landing" or args.landing_powers is not None
    arrays = landing_arrays if by_landing else after_failure_arrays
    try:
        p_topple, toppled, grouping, objects = arrays(read_runs(args.pushes), args.policy)
    except ValueError as err:
        parser.exit(2, f"{err}\n")
    failed_p, same = (None, grouping) if by_landing else (grouping, None)  # P_f per push, or where it lands
    if len(p_topple) == 0:
        parser.exit(2, f"no {args.policy} push follows a failed one in {args.pushes}\n")
    if args.mode == "fit":
        power = fit_power(p_topple, toppled)
        return _emitted({"power": power, **score(p_topple, toppled, power, float(toppled.mean()))}, args.json)
    if args.power is None or args.power < 1:
        parser.exit(2, f"{args.mode} needs --power K, K >= 1\n")
    if args.slope is not None and args.slope < 0:
        parser.exit(2, f"--slope must be 0 or more, got {args.slope:g}\n")
    if by_landing:
        try:
            powers = tuple(args.landing_powers or fit_landing(p_topple, same, toppled))
        except ValueError as err:
            parser.exit(2, f"{err}\n")
        constant = float(toppled.mean()) if args.mode == "fit-landing" else args.constant
        result = {"powers": list(powers), **landing_score(p_topple, toppled, same, args.power, powers, constant)}
        if args.mode == "score":
            result["differences"] = brier_differences(p_topple, toppled, objects, args.power, landing=(same, *powers))
        return _emitted(result, args.json)
    if args.mode == "fit-slope":
        slope = fit_slope(p_topple, failed_p, toppled, args.power)
        result = {"power": args.power, "slope": slope,
                  **score(p_topple, toppled, args.power, float(toppled.mean()), slope, failed_p)}
    elif args.slope is None:
        result = score(p_topple, toppled, args.power, args.constant)
        result["differences"] = brier_differences(p_topple, toppled, objects, args.power)
    else:
        result = score(p_topple, toppled, args.power, args.constant, args.slope, failed_p)
        result["differences"] = brier_differences(p_topple, toppled, objects, args.power, args.slope, failed_p)
    return _emitted(result, args.json)


def _emitted(result: dict, path: str | None) -> int:
    """Print ``result`` as JSON, and write it to ``path`` too when given; the exit status."""
    text = json.dumps(result, indent=1)
    if path:
        write_text_atomic(path, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
