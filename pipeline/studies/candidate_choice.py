"""How well the tables choose among a start's candidate pushes, against physics, by push direction.

An ``oracle_policy --log`` log holds, for each useful start, the planner's top candidates (the pushes
of highest Q_T) each played several times in pybullet.  Read against the datasets the planner saw,
each start's choice is scored in physics by its one-step value, the mean V_s of where its plays came
to rest (0 outside the pose set):

- ``rows``: the candidate whose row has the highest one-step value, sum_x' P(x' | x, u) V_s(x');
- ``q``: the candidate of highest stored Q (value iteration's own ranking, before (12.15)'s neighbourhood);
- ``mean``: a candidate drawn at random (the trivial chooser);
- ``oracle``: the candidate whose plays were best, chosen on the even plays and judged on the odd ones
  and the other way round (split halves, so no play both chooses and judges).

The oracle knows physics on the objects it is judged on: it measures what the candidates hold that
the tables do not, it is not a chooser.  The gap oracle - rows is split by the direction of the
rows' choice (from above: u_z < -0.3 in the pose frame; from the side; from below: u_z >= 0.3), and
within each start the rank correlation of the rows' P(topple) with the plays' topple rate says how
well the tables tell the candidates apart.  Standard errors are clustered by object
(``pooled_gain.clustered_mean_se``).  Seconds, not a policy run:

    python -m pipeline.studies.candidate_choice data/logs/corpus_planner --datasets data/corpus_oof_sa_{0..5}
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import rankdata

from ..model.config import Config
from .landing_trust import TrustError, object_datasets, planner_log_arguments, pose_columns
from .logreader import LogError, read_log
from .policy_experiment import ACTION_SPAN
from .pooled_gain import clustered_entry
from .robust_policy import next_pose_rows
from .validation import direction_classes

CLASSES = ("above", "side", "below")
"""The validation report's push directions (``validation.DIRECTIONS``), its two downward ones as one:
from above (u_z < -0.3, where the policies stop choosing), from the side, from below (u_z >= 0.3)."""
CHOOSERS = ("rows", "q", "mean", "oracle")


def direction_class(u_z: np.ndarray) -> np.ndarray:
    """(n,) int index into ``CLASSES`` of push directions' z components (pose frame, unit vectors),
    split as ``validation.direction_classes`` splits them (in float32, as the policies compare)."""
    classes = dict(direction_classes(u_z))
    return np.where(classes["from above"] | classes["oblique"], 0, np.where(classes["side"], 1, 2))


@dataclass
class Candidates:
    """Every usable logged push, grouped by start.

    start : (n,) int, the start each push belongs to (0..S-1);  objects : (S,) str, each start's object
    row_value : (n,) float, sum_x' P(x' | x, u) V_s(x');  q : (n,) float, the stored Q;  topple : (n,) float,
    the rows' P(topple);  u_z : (n,) float;  plays : list of n (R_i,) float arrays, V_s where each play
    came to rest (0 outside);  moved : list of n (R_i,) bool, whether each play left the start pose
    rejected : reason -> pushes not used
    """

    start: np.ndarray
    objects: np.ndarray
    row_value: np.ndarray
    q: np.ndarray
    topple: np.ndarray
    u_z: np.ndarray
    plays: list
    moved: list
    rejected: dict


def candidates(log, datasets: dict) -> Candidates:
    """The log's pushes against the rows, Q and V_s of the datasets their planner saw."""
    start_of: dict[tuple[str, int], int] = {}
    columns = {name: [] for name in ("start", "row_value", "q", "topple", "u_z")}
    plays, moved, rejected = [], [], Counter()
    poses_of: dict[Path, dict] = {}  # each dataset's V_s and actions per pose, by object, read once
    tables: dict[str, tuple | None] = {}  # object -> (V_s, rows, Q), None where the poses differ from the log's
    for push in log.pushes:
        dataset = datasets.get(push.object_id)
        if dataset is None:
            rejected["object in none of the datasets"] += 1
            continue
        if push.object_id not in tables:
            if dataset.root not in poses_of:
                poses_of[dataset.root] = pose_columns(dataset, ["v_s", "n_actions"])
            poses = poses_of[dataset.root].get(push.object_id, {"v_s": np.zeros(0), "n_actions": np.zeros(0, int)})
            if len(poses["v_s"]) != len(log.objects[push.object_id].poses.poses):
                tables[push.object_id] = None  # its actions are not read: the dataset may hold none of them
            else:
                actions = dataset.object_rows("actions", push.object_id, columns=["pose", "action", "q"]).to_pandas()
                q = {(int(p), int(a)): float(v) for p, a, v in zip(actions.pose, actions.action, actions.q)}
                rows = next_pose_rows(dataset, push.object_id, poses["n_actions"].astype(int).tolist())
                tables[push.object_id] = (poses["v_s"].astype(float), rows, q)
        if tables[push.object_id] is None:
            rejected["the dataset's stable poses differ from the log's"] += 1
            continue
        v_s, rows, q = tables[push.object_id]
        pose, action = divmod(int(push.push_id), ACTION_SPAN)
        if pose != push.pose or action >= len(rows[pose]) or not np.isfinite(rows[pose][action]).all():
            rejected["push id names no ok push of its start pose"] += 1
            continue
        row = rows[pose][action]
        outcomes = np.asarray(push.outcomes)
        columns["start"].append(start_of.setdefault((push.object_id, pose), len(start_of)))
        columns["row_value"].append(float(row @ v_s))
        columns["q"].append(q[(pose, action)])
        columns["topple"].append(float(1.0 - row[pose]))
        columns["u_z"].append(float(push.direction[2]))
        plays.append(np.append(v_s, 0.0)[np.where(outcomes >= 0, outcomes, len(v_s))])  # the last entry: outside
        moved.append(outcomes != pose)
    if not start_of:
        raise TrustError(f"no push of the log is in the datasets (rejected: {dict(rejected)})")
    objects = np.empty(len(start_of), dtype=object)
    for (object_id, _), index in start_of.items():
        objects[index] = object_id
    return Candidates(np.array(columns["start"]), objects.astype(str), *(np.array(columns[k], dtype=float) for k in
                      ("row_value", "q", "topple", "u_z")), plays, moved, dict(rejected))


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rho (average ranks for ties); nan when either is constant."""
    x, y = rankdata(x), rankdata(y)  # ties share their mean rank
    if x.std() == 0 or y.std() == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def start_choices(c: Candidates, index: np.ndarray) -> dict:
    """One start's choosers and what their choices are worth in physics.

    index : the start's pushes (at least two).  returns : chooser -> physical one-step value, and the
    class of the rows' choice (``direction_class``)."""
    physics = np.array([c.plays[i].mean() for i in index])
    even = np.array([c.plays[i][0::2].mean() for i in index])
    odd = np.array([c.plays[i][1::2].mean() if len(c.plays[i]) > 1 else np.nan for i in index])
    rows = int(np.argmax(c.row_value[index]))
    if np.isnan(odd).any():  # a single play cannot both choose and judge
        oracle = float("nan")
    else:
        oracle = 0.5 * (odd[int(np.argmax(even))] + even[int(np.argmax(odd))])
    return {"rows": float(physics[rows]), "q": float(physics[int(np.argmax(c.q[index]))]), "mean": float(physics.mean()),
            "oracle": oracle, "class": int(direction_class(c.u_z[index[rows]]))}


def summary(c: Candidates, min_class_pushes: int = 4) -> dict:
    """Every chooser's mean physical value over the starts with two candidates or more, the gap
    oracle - rows in all and by the rows' choice's direction class, and the mean within-start rank
    correlation of P(topple) with the topple rate among a class's candidates (starts with at least
    ``min_class_pushes`` of them where both vary), each with its SE clustered by object."""
    order = np.argsort(c.start, kind="stable")
    bounds = np.flatnonzero(np.diff(c.start[order])) + 1
    chosen, objects, classes = [], [], []
    correlations = {name: ([], []) for name in CLASSES}
    for index in np.split(order, bounds):
        if len(index) < 2:
            continue
        start = int(c.start[index[0]])
        choice = start_choices(c, index)
        if np.isnan(choice["oracle"]):
            continue
        chosen.append([choice[name] for name in CHOOSERS])
        objects.append(c.objects[start])
        classes.append(choice["class"])
        kind = direction_class(c.u_z[index])
        for k, name in enumerate(CLASSES):
            mine = index[kind == k]
            if len(mine) >= min_class_pushes:
                rho = rank_correlation(c.topple[mine], [c.moved[i].mean() for i in mine])
                if np.isfinite(rho):
                    correlations[name][0].append(rho)
                    correlations[name][1].append(c.objects[start])
    if not chosen:
        raise TrustError("no start has two candidates with two plays or more")
    chosen, classes, objects = np.array(chosen), np.array(classes), np.array(objects)

    def described(values, groups):
        return clustered_entry(values, groups, "starts")

    gap = chosen[:, CHOOSERS.index("oracle")] - chosen[:, CHOOSERS.index("rows")]
    by_class = {}
    for k, name in enumerate(CLASSES):
        mine = classes == k
        if mine.any():
            by_class[name] = {**described(gap[mine], objects[mine]), "share_of_gap": float(gap[mine].sum() / gap.sum()) if gap.sum() else None}
    return {"starts": len(chosen), "objects": len(np.unique(objects)), "pushes": len(c.start), "rejected": c.rejected,
            "value": {name: described(chosen[:, j], objects) for j, name in enumerate(CHOOSERS)},
            "oracle_minus_rows": described(gap, objects), "by_rows_choice": by_class,
            "topple_rank_correlation": {name: described(rho, groups) for name, (rho, groups) in correlations.items() if rho}}


def study(logs: list[str], dataset_roots: list[Path], config: Config | None = None) -> dict:
    """``summary`` of the logs read against the datasets their planner saw."""
    config = Config() if config is None else config
    datasets = object_datasets(dataset_roots)
    result = summary(candidates(read_log(logs, config), datasets))
    return {"logs": list(logs), "datasets": [str(r) for r in dataset_roots], **result}


def _se(entry: dict) -> str:
    return "" if entry["se"] is None else f" +/- {entry['se']:.4f}"


def text(result: dict) -> str:
    lines = [(f"{result['starts']} starts with two candidates or more on {result['objects']} objects ({result['pushes']} pushes;"
              f" rejected {result['rejected']}); physical one-step value of the choice, SE by object:")]
    for name, entry in result["value"].items():
        lines.append(f"  {name:7s} {entry['mean']:.4f}{_se(entry)}")
    gap = result["oracle_minus_rows"]
    lines.append(f"oracle - rows {gap['mean']:+.4f}{_se(gap)}; by the direction of the rows' choice:")
    for name, entry in result["by_rows_choice"].items():
        share = "" if entry["share_of_gap"] is None else f", {entry['share_of_gap']:.0%} of the gap"
        lines.append(f"  {name:6s} {entry['starts']:5d} starts: {entry['mean']:+.4f}{_se(entry)}{share}")
    lines.append("within a start, rank correlation of the rows' P(topple) with the plays' topple rate:")
    for name, entry in result["topple_rank_correlation"].items():
        lines.append(f"  {name:6s} {entry['starts']:5d} starts: {entry['mean']:+.3f}{_se(entry)}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.candidate_choice", description=__doc__.split("\n\n")[0])
    planner_log_arguments(parser)
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    if refused_outputs(args.json):
        return 2
    try:
        result = study(args.logs, args.datasets)
    except (TrustError, LogError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
