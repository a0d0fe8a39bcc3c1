"""The top of the scale for the policy goal: a push budget that knows the physics of its candidates.

Issue 9 asks value iteration to gain +0.15 V_s over Max-Height in physics.  The validation
report puts physics replaying itself beside the model, the top of its scale; this study does
the same for the policies.  It asks how much a policy would gain if the model's probabilities
were replaced, for the pushes it would consider, by what physics does:

1. **Estimate.** Every start pose of a useful trial of ``toppledb policies-physics`` (the same
   dataset, trials and seed) gets its candidates: the ``k_max`` choosable pushes of highest
   Q_T (``mdp.min_direction_z``, as the dataset's policies choose), plus the pushes Max-Height,
   value iteration and the budget (``horizon_vi``, 3 pushes left) take there.  Each is played
   ``repeats`` times from the pose's canonical transform under the world's noise, drawn from a
   stream of its own (``<object>/oracle/<pose>/<action>``) that no trial draws from.
2. **Play.** From the useful trials' starts, with the trials' own noise (common random
   numbers, so ``max_height`` and ``value_iteration`` reproduce that report's gains), it plays
   the budget over all choosable pushes (``horizon_vi``) and, for each k of ``ks``:
   ``candidates_k``, the budget whose choice at those start poses is restricted to the top k
   candidates (the policies' own pushes always among them), the model's probabilities for each;
   and ``oracle_k``, the same budget reading each candidate's row from the physics estimate
   (the fraction of its plays that came to rest in each pose; one that left the pose set counts
   as staying).  Every other pose, and every other push, keeps the model's rows.  The restriction
   holds at every useful start pose of the object, whichever trial the budget is played in.

``oracle_k`` is not a model: its knowledge comes from the objects it is judged on.  Its gain
over ``candidates_k`` is what knowing those pushes' physics is worth, and its gain over
Max-Height is how far the goal is from what such knowledge reaches.  A budget that chooses by a
``repeats``-sample estimate suffers the winner's curse, and only the top ``k_max`` pushes are
known, so it is a floor under the ceiling, not the ceiling.

``--every-ok`` ranks every ok push for the candidates, pushes from above included (which the policies
of a dataset built with ``mdp.min_direction_z`` above -1 may not choose); ``--log DIR`` writes the estimate's plays as a push log, which ``toppledb
report`` scores like any other: the model on the pushes its planner weighs.

    python -m pipeline.studies.oracle_policy DATASET --trials 600 --seed S --repeats 16 --workers 2 --json F
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from schema import horizon
from schema.pushlog import PUSHLOG
from schema.vocabulary import NO_OP

from ..model.config import Config
from ..model.rng import stream
from .playlog import ObjectLog, append_row, mesh_location, write_part
from .policies_physics import (
    PURPOSE,
    ExperimentError,
    ObjectPlan,
    load_planned,
    mean_se,
    object_plans,
    open_trials,
    world_config,
)
from .policy_experiment import ACTION_SPAN, useful_starts
from .pushsim import body_model, draw_noise, play_push, player_parameters
from .robust_policy import (
    HORIZON_POLICY,
    PoseCandidates,
    Push,
    Smoothing,
    cell,
    horizon_actions,
    next_pose_rows,
    play_object,
    pose_landings,
    pose_scores,
    read_candidates,
    study_parser,
    trial_gains,
)

KS = (1, 3, 6, 12)
"""Candidates per start pose the restricted budgets choose among (the largest is how many are played)."""
REPEATS = 16
"""Plays per candidate push; 16 puts a standard error of at most 0.125 on each estimated P(topple)."""
ALWAYS = ("max_height", "value_iteration")
"""The policies whose push at a start pose is always a candidate (with the budget's first push)."""


def top_pushes(q: np.ndarray, choosable: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` choosable pushes of highest Q_T, best first.

    q : (A,) float, NaN unless ok;  choosable : (A,) bool
    returns : (<= k,) int, action ids; ties in Q_T go to the lower id
    """
    usable = np.flatnonzero(choosable & np.isfinite(q))
    return usable[np.argsort(-q[usable], kind="stable")[:k]]


def landing_row(landed: np.ndarray, pose: int, n_poses: int) -> np.ndarray:
    """Where a push's plays came to rest as a transition row.

    landed : (R,) int, the pose each play settled in, -1 outside the pose set (counted as
      staying: the budget cannot value a pose it does not know)
    returns : (n_poses,) float, fractions summing to one
    """
    landed = np.where(np.asarray(landed) < 0, pose, landed)
    return np.bincount(landed, minlength=n_poses) / len(landed)


def estimated_topple(landed: np.ndarray, pose: int) -> float:
    """The estimate's P(topple): the share of plays that settled in another pose of the set
    (``landing_row``'s reading: outside the pose set counts as staying)."""
    landed = np.asarray(landed)
    return float(np.mean((landed >= 0) & (landed != pose)))


def estimate_object(plan: ObjectPlan, pushes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]], config: Config,
                    world: Config, repeats: int, seed: int) -> tuple[str, dict[int, np.ndarray] | str, ObjectLog]:
    """Play each candidate push of each start pose ``repeats`` times (runs in a worker).

    pushes : start pose -> (actions (k,) int, points (k, 3) float m, directions (k, 3) float),
      pose frame
    returns : (object id, start pose -> (k, repeats) int, the pose each play settled in (-1:
      outside the pose set), or a one-line reason the object cannot be played; the plays as a
      push log, push_id = pose * ``ACTION_SPAN`` + action, one row per repeat)
    """
    from ..model.poses import settle

    spec = plan.spec
    object_id = spec.object_id
    key = {"object_id": object_id, "mesh_sha256": spec.sha256, "experiment": "oracle-policy", "seed": seed,
           "repeats": repeats, "player": player_parameters()}
    empty = ObjectLog(object_id, PUSHLOG.empty_table(), key, {"pushes": 0})
    loaded = load_planned(plan, config)
    if isinstance(loaded, str):
        return object_id, loaded, empty
    obj, pose_set = loaded
    body = body_model(obj)
    source, path = mesh_location(spec)
    columns: dict[str, list] = {f.name: [] for f in PUSHLOG}
    landed = {}
    for pose, (actions, points, directions) in pushes.items():
        to_object = np.linalg.inv(plan.transforms[pose])
        outcome = np.empty((len(actions), repeats), dtype=np.int64)
        for i, action in enumerate(actions):
            point = to_object[:3, :3] @ points[i] + to_object[:3, 3]
            direction = to_object[:3, :3] @ directions[i]
            rng = stream(seed, f"{object_id}/oracle/{pose}/{action}", pose, PURPOSE)
            for r in range(repeats):
                played = play_push(body, plan.transforms[pose], point, direction, config, draw_noise(world, rng, noise=True))
                outcome[i, r] = settle(pose_set, obj, played.final_transform[:3, :3])
                append_row(columns, spec, source, path, pose * ACTION_SPAN + int(action), r, pose, int(action), point,
                           direction, played, config, seed)
        landed[pose] = outcome
    table = pa.Table.from_pydict(columns, schema=PUSHLOG)
    return object_id, landed, ObjectLog(object_id, table, key, {"pushes": table.num_rows // repeats, "repeats": repeats})


@dataclass
class ObjectCandidates:
    """What the estimate and the budgets need of one object.

    candidates : per pose, its pushes (``read_candidates``);  rows : per pose (A_x, P) float,
    the model's P(x' | x, u);  choosable : per pose (A_x,) bool;  starts : start pose -> (top
    pushes best first, always-actions);  pushes : start pose -> (played actions (k,) int,
    points (k, 3), directions (k, 3)), pose frame, what ``estimate_object`` plays
    """

    candidates: list[PoseCandidates]
    rows: list[np.ndarray]
    choosable: list[np.ndarray]
    starts: dict[int, tuple[np.ndarray, np.ndarray]]
    pushes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]


def restricted_budgets(v_s: np.ndarray, rows: list[np.ndarray], choosable: list[np.ndarray],
                       starts: dict[int, tuple[np.ndarray, np.ndarray]], landed: dict[int, dict[int, np.ndarray]],
                       ks: tuple[int, ...], max_pushes: int) -> dict[str, np.ndarray]:
    """``candidates_k`` and ``oracle_k`` for each k, as (max_pushes, P) action tables (``horizon_actions``).

    rows : per pose (A_x, P) float, the model's P(x' | x, u) (``next_pose_rows``);  choosable :
      per pose (A_x,) bool;  starts : start pose -> (its top pushes best first, ``top_pushes``;
      the actions always among its candidates);  landed : start pose -> action -> (R,) int,
      where that candidate's plays settled (every candidate of every k)
    At a start pose the budget chooses among the top k and the always-actions only; ``oracle_k``
    reads their rows from ``landing_row``.  Every other pose keeps ``horizon_vi``'s inputs (the
    model's rows, every choosable push), but not always its choice: a push there that can topple
    into a start pose is valued at what the restricted budget makes of that pose.
    """
    out = {}
    for k in ks:
        mask = list(choosable)
        physics = list(rows)
        for pose, (ranked, always) in starts.items():
            allowed = np.union1d(ranked[:k], always).astype(np.int64)
            mask[pose] = np.zeros(len(choosable[pose]), dtype=bool)
            mask[pose][allowed] = True
            physics[pose] = rows[pose].copy()
            for action in allowed:
                physics[pose][action] = landing_row(landed[pose][action], pose, len(v_s))
        out[f"candidates_{k}"] = horizon_actions(v_s, rows, max_pushes, mask)
        out[f"oracle_{k}"] = horizon_actions(v_s, physics, max_pushes, mask)
    return out


def experiment(root: str | Path, n_trials: int, *, seed: int = 0, repeats: int = REPEATS, ks: tuple[int, ...] = KS,
               max_pushes: int = 3, workers: int | None = 1, world: Config | None = None, every_ok: bool = False,
               log: str | Path | None = None,
               progress: bool = False) -> tuple[dict, list[Push], dict[str, dict[int, dict[int, np.ndarray]]]]:
    """Estimate the candidates' physics, then play every budget from the useful trials.

    world : the simulated world's noise (the CLI passes the thesis preset, as ``policies-physics``)
    every_ok : rank every ok push for the candidates, those the dataset's policies may not choose
      (``mdp.min_direction_z`` above -1) included: what knowing them would be worth
    log : write the estimate's plays here as a push log (one part file per object), which
      ``toppledb report`` scores: the model on the pushes its planner weighs
    returns : the report (JSON-ready), every push played, and the estimate: object -> start
      pose -> candidate action -> (repeats,) int, where its plays settled
    """
    from ..build.fanout import map_unordered

    if repeats < 1 or not ks or min(ks) < 1:
        raise ExperimentError("--repeats and every k must be 1 or more")
    started = time.perf_counter()
    dataset, config, tables, starts, by_object = open_trials(root, n_trials, seed)
    world = world or config
    useful = useful_starts(tables, starts)
    trials = {o: mine for o, pairs in by_object.items() if (mine := [(t, p) for t, p in pairs if useful[t]])}
    plans = object_plans(dataset, sorted(trials))

    extras, estimates = {}, []
    for object_id in sorted(trials):
        plan = plans[object_id]
        candidates = read_candidates(dataset, object_id)
        rows = next_pose_rows(dataset, object_id, [len(c.q) for c in candidates])
        choosable = [horizon.choosable_pushes(c.directions[:, 2], config.mdp.min_direction_z) for c in candidates]
        plan.actions[HORIZON_POLICY] = horizon_actions(plan.v_s, rows, max_pushes, choosable)
        start_candidates, pushes = {}, {}
        for pose in sorted({p for _, p in trials[object_id]}):
            always = [int(plan.actions[p][pose]) for p in ALWAYS] + [int(plan.actions[HORIZON_POLICY][0, pose])]
            always = np.unique([a for a in always if a != NO_OP]).astype(np.int64)
            pool = np.ones(len(choosable[pose]), dtype=bool) if every_ok else choosable[pose]
            start_candidates[pose] = (top_pushes(candidates[pose].q, pool, max(ks)), always)
            played = np.union1d(*start_candidates[pose]).astype(np.int64)
            pushes[pose] = (played, candidates[pose].points[played], candidates[pose].directions[played])
        extras[object_id] = ObjectCandidates(candidates, rows, choosable, start_candidates, pushes)
        estimates.append((plan, pushes, config, world, repeats, seed))

    failures: dict[str, str] = {}
    landed: dict[str, dict[int, dict[int, np.ndarray]]] = {}
    for object_id, outcome, object_log in map_unordered(estimate_object, estimates, workers, description="estimate",
                                                        progress=progress):
        if isinstance(outcome, str):
            failures[object_id] = outcome
            continue
        if log is not None:
            write_part(Path(log), object_log)
        pushes = extras[object_id].pushes
        landed[object_id] = {pose: dict(zip(pushes[pose][0].tolist(), plays)) for pose, plays in outcome.items()}
    estimated_wall = time.perf_counter() - started

    policies = ("max_height", "value_iteration", HORIZON_POLICY, *(f"{kind}_{k}" for k in ks for kind in ("candidates", "oracle")))
    tasks = []
    for object_id in sorted(landed):
        plan, mine = plans[object_id], extras[object_id]
        plan.actions.update(restricted_budgets(plan.v_s, mine.rows, mine.choosable, mine.starts, landed[object_id], ks,
                                               max_pushes))
        scores = [pose_scores(c, Smoothing()) for c in mine.candidates]  # the pushes' records want them; rows unsmoothed
        landings = [pose_landings(r, x, plan.v_s) for x, r in enumerate(mine.rows)]  # so do their landing fields
        tasks.append((plan, {"candidates": mine.candidates, "scores": scores, "landings": landings}, trials[object_id], config,
                      seed, max_pushes, world, policies))
    runs: dict[int, dict[str, list[int]]] = {}
    played: list[Push] = []
    for object_id, results, object_pushes in map_unordered(play_object, tasks, workers, description="play", progress=progress):
        if "failure" in results:
            failures[object_id] = results["failure"]
            continue
        runs.update(results)
        played.extend(object_pushes)
    report = summarise(tables, starts, runs, played, landed, policies)
    report.update({"dataset": str(Path(root).resolve()), "trials": n_trials, "objects": len(trials),
                   "failed_objects": failures, "seed": seed, "every_ok": every_ok, "max_pushes": max_pushes,
                   "repeats": repeats, "ks": list(ks),
                   "estimate_plays": int(sum(len(p[0]) for e in estimates for p in e[1].values()) * repeats),
                   "estimate_wall_s": round(estimated_wall, 1), "wall_s": round(time.perf_counter() - started, 1)})
    return report, played, landed


def summarise(tables, starts: np.ndarray, runs: dict, pushes: list[Push], landed: dict, policies: tuple[str, ...]) -> dict:
    """Per policy: V_s gain on the useful trials, paired gains over max_height and horizon_vi,
    the chosen pushes' table P(topple), the estimate's P(topple) where one was played, and how
    often they toppled."""
    kept, gains, useful, outside = trial_gains(tables, starts, runs, policies)
    kept_trials = set(kept.tolist())
    report: dict = {"played_trials": len(runs), "outside_trials": outside, "useful_trials": int(useful.sum()), "policies": {}}
    for policy in policies:
        mine = [p for p in pushes if p.policy == policy and p.trial in kept_trials]
        estimated = [estimated_topple(landed[p.object_id][p.pose][p.action], p.pose) for p in mine
                     if p.action in landed.get(p.object_id, {}).get(p.pose, {})]
        over, over_se = mean_se(gains[policy][useful] - gains["max_height"][useful])
        over_h, over_h_se = mean_se(gains[policy][useful] - gains[HORIZON_POLICY][useful])
        gain, gain_se = mean_se(gains[policy][useful])
        report["policies"][policy] = {
            "physical_gain_useful": gain, "physical_gain_useful_se": gain_se,
            "gain_over_max_height": over, "gain_over_max_height_se": over_se,
            "gain_over_horizon_vi": over_h, "gain_over_horizon_vi_se": over_h_se,
            "pushes": len(mine),
            "predicted_topple_rate": mean_se([p.p_topple for p in mine])[0],
            "estimated_pushes": len(estimated), "estimated_topple_rate": mean_se(estimated)[0],
            "physical_topple_rate": mean_se([p.toppled for p in mine])[0],
        }
    return report


def text(report: dict) -> str:
    lines = [(f"{report['useful_trials']} useful trials on {report['objects']} objects, {report['outside_trials']} outside; "
              f"{report['estimate_plays']} estimate plays ({report['estimate_wall_s']} s); {report['wall_s']} s"),
             (f"{'policy':<18} {'gain':>7} {'over max_height':>18} {'over horizon_vi':>16} {'pushes':>7} {'P table':>8} "
              f"{'P est.':>7} {'physics':>8}")]
    for policy, r in report["policies"].items():
        se = r["gain_over_max_height_se"]
        lines.append(f"{policy:<18} {cell(r['physical_gain_useful']):>7} "
                     f"{cell(r['gain_over_max_height']) + ('' if se is None else f' +/- {se:.3f}'):>18} "
                     f"{cell(r['gain_over_horizon_vi']):>16} {r['pushes']:>7} {cell(r['predicted_topple_rate'], False):>8} "
                     f"{cell(r['estimated_topple_rate'], False):>7} {cell(r['physical_topple_rate'], False):>8}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import positive_int, print_and_record, refused_outputs

    parser = study_parser("python -m pipeline.studies.oracle_policy", __doc__)
    parser.add_argument("--repeats", type=positive_int, default=REPEATS, help="plays per candidate (default: %(default)s)")
    parser.add_argument("--ks", type=positive_int, nargs="+", default=list(KS), help="candidates per start pose (default: %(default)s)")
    parser.add_argument("--every-ok", action="store_true",
                        help="candidates from every ok push, those from above included (default: the choosable ones)")
    parser.add_argument("--log", type=Path, help="write the estimate's plays here as a push log")
    args = parser.parse_args(argv)
    if refused_outputs(args.json, directories=(args.log,)):
        return 2
    try:
        report, _, _ = experiment(args.dataset, args.trials, seed=args.seed, repeats=args.repeats, ks=tuple(sorted(set(args.ks))),
                                  max_pushes=args.max_pushes, workers=args.workers, world=world_config(args.world),
                                  every_ok=args.every_ok, log=args.log)
    except (ExperimentError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(report), report, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
