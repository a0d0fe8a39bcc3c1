"""Fit the doubted shares of candidate LD (``pipeline.model.landing_direction``) on traced plays.

``push_course --plays`` traces a policy's chosen pushes in pybullet and records where each came to
rest.  For every pushed topple that landed in the pose set, (LD.1) gives the landed pose the
probability (1 - lambda) a + lambda b, a the push's own landing given a topple and b the pose's mean
landing.  Each direction class's lambda maximises the mean log of that over its topples (the log
score, a proper one; concave in lambda, so the maximum is found by bisection on its derivative).  A
topple that lands where neither a nor b puts anything is the same for every lambda and does not
count.  Beside it, the landed poses' V_s against what the rows expect of the topple, before and with
the fitted share (clustered by object), and a bootstrap over objects of each lambda:

    python -m pipeline.studies.push_course data/dataset --per-class 189 --repeats 5 --seed 55 --workers 2 --plays P.jsonl
    python -m pipeline.studies.landing_direction data/dataset P.jsonl --json reports/landing_direction_fit_s55.json

Fit on the corpus's own objects: its shares are then judged on held-out objects
(``robust_policy --landing-direction``), never fitted there.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..model.landing_direction import CLASSES, mean_landing
from .pooled_gain import clustered_entry

BOOTSTRAPS = 400
"""Resamples of the objects for each share's interval."""


def ml_share(own: np.ndarray, mean: np.ndarray, tolerance: float = 1e-9) -> float:
    """The lambda in [0, 1] that maximises sum log((1 - lambda) own + lambda mean).

    own, mean : (n,) float in [0, 1], not both 0 in any entry (such an entry does not depend on lambda)
    returns : lambda; 0 for no entries
    """
    own, mean = np.asarray(own, dtype=float), np.asarray(mean, dtype=float)
    if len(own) == 0:
        return 0.0

    def slope(share: float) -> float:  # d/d lambda of the log score: decreasing in lambda (the score is concave)
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = (mean - own) / ((1.0 - share) * own + share * mean)
        # An entry whose mixture is 0 pulls without bound toward the side that gives it mass.
        return float(np.sum(np.where(np.isfinite(terms), terms, np.copysign(np.inf, mean - own))))

    if slope(0.0) <= 0.0:
        return 0.0
    if slope(1.0) >= 0.0:
        return 1.0
    low, high = 0.0, 1.0
    while high - low > tolerance:
        middle = 0.5 * (low + high)
        low, high = (middle, high) if slope(middle) > 0.0 else (low, middle)
    return 0.5 * (low + high)


def play_terms(plays: list[dict], rows: dict[str, list[np.ndarray]], values: dict[str, np.ndarray]) -> list[dict]:
    """For each pushed topple that landed in the pose set, what (LD.1) needs of it.

    plays : ``push_course`` play records (``Play`` fields);  rows : per object, per pose (A_x, P) float;
    values : per object, (P,) V_s
    returns : dicts with object_id, direction class (``CLASSES``), own and mean (the landed pose's
      probability given a topple), value_own and value_mean (V_s expected), value_landed
    """
    terms = []
    landings = {}  # (object, pose) -> mean_landing: a push is played several times, a pose's starts share it
    for play in plays:
        if not play["toppled"] or play["kind"] == "no contact" or play["landed"] < 0:
            continue
        object_id, pose, action, landed = play["object_id"], play["pose"], play["action"], play["landed"]
        if (object_id, pose) not in landings:
            landings[object_id, pose] = mean_landing(rows[object_id][pose], pose)
        landing, total, mean = landings[object_id, pose]
        if total[action] <= 0:  # the rows say it cannot topple: nothing to mix
            continue
        v_s = values[object_id]
        terms.append({"object_id": object_id, "direction": play["direction"],
                      "own": float(landing[action, landed]), "mean": float(mean[landed]),
                      "value_own": float(landing[action] @ v_s), "value_mean": float(mean @ v_s),
                      "value_landed": float(v_s[landed])})
    return terms


def fit_class(terms: list[dict], seed: int = 0) -> dict:
    """One direction class's share, its bootstrap interval over objects, and what it changes."""
    informative = [t for t in terms if t["own"] > 0 or t["mean"] > 0]
    own = np.array([t["own"] for t in informative])
    mean = np.array([t["mean"] for t in informative])
    share = ml_share(own, mean)
    objects = np.array([t["object_id"] for t in informative])
    names = np.unique(objects)
    rng = np.random.default_rng(seed)
    drawn = []
    for _ in range(BOOTSTRAPS if len(names) > 1 else 0):
        picked = np.concatenate([np.flatnonzero(objects == name) for name in rng.choice(names, len(names))])
        drawn.append(ml_share(own[picked], mean[picked]))
    clusters = [t["object_id"] for t in terms]
    landed = np.array([t["value_landed"] for t in terms])
    expected = np.array([t["value_own"] for t in terms])
    doubted = (1.0 - share) * expected + share * np.array([t["value_mean"] for t in terms])

    def score(s: float) -> float | None:  # the mean log score; -inf where the rows give a landing nothing
        if not len(own):
            return None
        with np.errstate(divide="ignore"):
            return float(np.mean(np.log((1.0 - s) * own + s * mean)))

    return {
        "topples": len(terms), "informative": len(informative), "objects": len(set(clusters)),
        "share": share,
        "share_95": [float(np.quantile(drawn, 0.025)), float(np.quantile(drawn, 0.975))] if drawn else None,
        "log_score": {"rows": score(0.0), "doubted": score(share)},
        "landed_probability": {"rows": float(own.mean()) if len(own) else None,
                               "doubted": float(((1 - share) * own + share * mean).mean()) if len(own) else None},
        "value_landed_minus_expected": {"rows": clustered_entry(landed - expected, clusters, "topples"),
                                        "doubted": clustered_entry(landed - doubted, clusters, "topples")},
    }


def fit(root: str | Path, plays: list[dict], seed: int = 0) -> dict:
    """Each direction class's share of (LD.1), fitted on ``plays`` of the dataset at ``root``."""
    from schema.reader import Dataset

    from .landing_trust import pose_columns
    from .policies_physics import object_plans
    from .robust_policy import next_pose_rows

    dataset = Dataset.open(root)
    objects = sorted({p["object_id"] for p in plays})
    n_actions = {o: c["n_actions"].tolist() for o, c in pose_columns(dataset, ["n_actions"]).items()}
    missing = [o for o in objects if o not in n_actions]
    if missing:
        raise ValueError(f"the plays name objects the dataset does not have: {', '.join(missing[:5])}")
    plans = object_plans(dataset, objects)
    rows = {o: next_pose_rows(dataset, o, n_actions[o]) for o in objects}
    terms = play_terms(plays, rows, {o: plans[o].v_s for o in objects})
    classes = {name: fit_class([t for t in terms if t["direction"] == name], seed) for name in CLASSES}
    return {"dataset": str(root), "plays": len(plays), "seed": seed, "classes": classes,
            "shares": [classes[name]["share"] for name in CLASSES]}


def text(result: dict) -> str:
    lines = [f"{result['plays']} plays of {result['dataset']}; (LD.1)'s share by push direction, maximum likelihood:"]
    for name in CLASSES:
        c = result["classes"][name]
        interval = "" if c["share_95"] is None else f" [{c['share_95'][0]:.2f}, {c['share_95'][1]:.2f}]"
        bias = c["value_landed_minus_expected"]
        lines.append(f"  {name:6s} lambda {c['share']:.3f}{interval}  {c['informative']} of {c['topples']} topples "
                     f"({c['objects']} objects); V_s landed minus expected {bias['rows']['mean']:+.3f} -> "
                     f"{bias['doubted']['mean']:+.3f}")
    lines.append("--landing-direction " + " ".join(f"{s:.2f}" for s in result["shares"]))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.landing_direction", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="the dataset the plays were traced on")
    parser.add_argument("plays", type=Path, help="push_course --plays output, JSON lines")
    parser.add_argument("--seed", type=int, default=0, help="draws the bootstrap's objects")
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    if refused_outputs(args.json):
        return 2
    try:
        plays = [json.loads(line) for line in args.plays.read_text().splitlines() if line.strip()]
        result = fit(args.dataset, plays, args.seed)
    except KeyError as err:
        print(f"error: a play lacks the field {err}: give the plays `push_course --plays` writes", file=sys.stderr)
        return 2
    except (OSError, ValueError) as err:  # a file not there, a line not JSON, an object not in the dataset
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
