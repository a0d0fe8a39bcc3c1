"""Two datasets' policies played on the same trials, compared trial by trial.

A change to the model's rows (a refitted map, say) changes a dataset's tables, not its objects or
poses.  ``pipeline.studies.robust_policy`` draws a seed's trials from the poses' drop
probabilities and plays them with streams of their own, so two datasets of the same objects and
poses played on one seed start every trial in the same pose under the same noise, and a policy's
difference between them is paired.  ``--trials-out`` writes each run's trials; this pairs them.

A trial counts where neither run left the pose set and either run calls it useful (greedy would
push from a pose that is not the object's best): the trials where either table says pushing can
pay, the same for both.

    python -m pipeline.studies.paired_trials A.jsonl B.jsonl [A2.jsonl B2.jsonl ...] --policies value_iteration

``--over max_height`` pairs each policy's gain over another's instead (issue 9's measure): B's minus A's
of (policy - baseline), trial by trial. Runs of one dataset and seed under other player settings pair the
same way (docs/VALIDATION.md, "The judge's own numerics").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .policies_physics import mean_se

NEVER_PUSH = "never_push"
"""The planner that never pushes: its V_s gain is 0 on every trial (``robust_policy``'s ``never_push``);
the records do not hold it, so it is read as 0 wherever a policy is asked for."""


class PairingError(ValueError):
    """Two runs that are not the same trials; one line."""


def read_trials(path: str | Path) -> dict[int, dict]:
    """A run's trial records (``robust_policy.trial_records``) by trial number.

    raises PairingError : the file cannot be read, or a record lacks what pairing reads, or a trial
      appears twice"""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as err:
        raise PairingError(f"{path}: {err.strerror or err}") from None
    trials: dict[int, dict] = {}
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            trial, start = int(record["trial"]), int(record["start"])
            outside, useful, gains = bool(record["outside"]), bool(record["useful"]), record["gains"]
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
            raise PairingError(f"{path}, line {number}: not a trial record ({type(err).__name__}: {err})") from None
        if not outside and not (isinstance(gains, dict) and all(isinstance(v, (int, float)) for v in gains.values())):
            raise PairingError(f"{path}, line {number}: a trial inside the pose set needs each policy's gain")
        if trial in trials:
            raise PairingError(f"{path}: trial {trial} appears twice")
        trials[trial] = {"start": start, "object_id": record.get("object_id"), "outside": outside, "useful": useful,
                         "gains": gains}
    return trials


def counted_trials(a: dict[int, dict], b: dict[int, dict]) -> list[int]:
    """The trials a pair counts, in order: played by both, left outside by neither, useful in either."""
    return [t for t in sorted(a) if t in b and not a[t]["outside"] and not b[t]["outside"] and (a[t]["useful"] or b[t]["useful"])]


def paired_gains(a: dict[int, dict], b: dict[int, dict], policy: str, over: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A policy's V_s gain in run ``a`` and in run ``b`` on the trials both count.

    over : a baseline policy: the gain is then the policy's minus the baseline's, trial by trial
    returns : (n,) float each, in trial order, over the trials both played, neither left outside
      and either calls useful
    raises PairingError : the runs played different trials, or a trial starts in different poses
    """
    if set(a) != set(b):
        raise PairingError(f"the runs played different trials ({len(a)} and {len(b)}); play both with the same --trials and --seed")
    for t in sorted(a):
        if (a[t]["start"], a[t]["object_id"]) != (b[t]["start"], b[t]["object_id"]):
            raise PairingError(f"trial {t} starts in pose row {a[t]['start']} of {a[t]['object_id']} in one run and "
                               f"{b[t]['start']} of {b[t]['object_id']} in the other: the runs are not of one seed on "
                               "datasets of the same objects and poses")
    counted = counted_trials(a, b)

    def gains(run: dict[int, dict]) -> np.ndarray:
        values = []
        for t in counted:
            gain = {NEVER_PUSH: 0.0, **run[t]["gains"]}
            for name in filter(None, (policy, over)):
                if name not in gain:
                    raise PairingError(f"trial {t} has no policy {name!r}; it played {', '.join(sorted(run[t]['gains']))}")
            values.append(gain[policy] - (gain[over] if over else 0.0))
        return np.array(values, dtype=float)

    return gains(a), gains(b)


def compare(pairs: list[tuple[str, str]], policies: list[str], over: str | None = None) -> dict:
    """Per policy: each pair's paired difference (B minus A, mean and SE over its trials), the mean
    of the pairs' means with its SE over pairs, and the difference pooled over every counted trial
    with its SE clustered by object (``pooled_gain.clustered_mean_se``; None when a record names no
    object): pairs of several seeds replay the same objects, and what a change does to an object
    it does on every seed. ``over``: each policy's gain over this baseline's (``paired_gains``)."""
    from .pooled_gain import clustered_mean_se

    runs = [(read_trials(a), read_trials(b)) for a, b in pairs]
    out = {"pairs": [{"a": str(a), "b": str(b)} for a, b in pairs], "over": over, "policies": {}}
    objects = [a[t]["object_id"] for a, b in runs for t in counted_trials(a, b)]
    for policy in policies:
        per_pair, pooled = [], []
        for (a, b), names in zip(runs, pairs):
            gain_a, gain_b = paired_gains(a, b, policy, over)
            mean, se = mean_se(gain_b - gain_a)
            per_pair.append({"trials": len(gain_a), "a": mean_se(gain_a)[0], "b": mean_se(gain_b)[0], "b_minus_a": mean,
                             "b_minus_a_se": se})
            pooled.append(gain_b - gain_a)
        means = np.array([p["b_minus_a"] for p in per_pair if p["b_minus_a"] is not None])
        runs_mean, runs_se = mean_se(means)
        differences = np.concatenate(pooled) if pooled else np.zeros(0)
        objects_se = None
        if len(differences) and all(objects):
            objects_se = clustered_mean_se(differences, objects)[1]
            objects_se = None if np.isnan(objects_se) else objects_se
        out["policies"][policy] = {"pairs": per_pair, "runs_mean": runs_mean, "runs_se": runs_se, "runs": len(means),
                                   "pooled": mean_se(differences)[0] if len(differences) else None,
                                   "pooled_objects_se": objects_se, "trials": len(differences)}
    return out


def text(result: dict) -> str:
    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:+.4f}"

    lines = []
    for policy, r in result["policies"].items():
        clustered = "" if r["pooled_objects_se"] is None else f" +/- {r['pooled_objects_se']:.4f} clustered by object"
        lines.append(f"{policy}: B minus A {cell(r['runs_mean'])} +/- {cell(r['runs_se'])} over {r['runs']} pairs with counted trials "
                     f"(pooled over {r['trials']} trials {cell(r['pooled'])}{clustered})")
        for pair, p in zip(result["pairs"], r["pairs"]):
            lines.append(f"  {p['trials']:>5} trials  A {cell(p['a'])}  B {cell(p['b'])}  B - A {cell(p['b_minus_a'])} "
                         f"+/- {cell(p['b_minus_a_se'])}  {Path(pair['b']).name}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.paired_trials", description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", metavar="A.jsonl B.jsonl",
                        help="pairs of runs' --trials-out files, A then B; the difference is B minus A")
    parser.add_argument("--policies", nargs="+", default=["value_iteration"], help="policies to compare (default: %(default)s)")
    parser.add_argument("--over", metavar="POLICY", help="pair each policy's gain over this one's, e.g. max_height")
    parser.add_argument("--json", type=Path, help="write the comparison here")
    args = parser.parse_args(argv)
    if len(args.files) % 2:
        print(f"error: {len(args.files)} files do not make pairs; give A B for each pair", file=sys.stderr)
        return 2
    try:
        result = compare(list(zip(args.files[::2], args.files[1::2])), args.policies, args.over)
    except PairingError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
