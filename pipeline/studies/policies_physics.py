"""The policy experiment executed in physics: each policy's pushes played in pybullet.

``toppledb policies`` replays thesis 4.4.3 inside the model: every next pose is drawn
from the dataset's own P(x' | x, u), so it measures what the model believes.  Here
the pushes are played by the push player instead:

1. a trial drops a corpus object (uniformly) into a stable pose drawn by its drop
   probability, standing in that pose's canonical transform on the table;
2. each policy (max_height, greedy, value_iteration) looks its push up in the dataset
   (``<policy>_action`` of the pose, the action's point and direction in the pose
   frame), which is mapped to the world through the object's observed transform, as
   the service's ``/plan`` does (``pose_to_world = observed @ T_pose^-1``);
3. pybullet plays it under the model's noise (friction, contact, direction); the
   object's final transform is re-observed and settled into a stable pose
   (``pipeline.model.poses.settle``), and the policy re-plans from there, at most
   ``max_pushes`` times or until it chooses not to push.

Per policy it reports the physical V_s gain (V_s of the pose the object ends in minus
V_s of the start pose) beside the gain the model's own table predicts for the same
start (the exact expectation over the stored transitions, up to ``max_pushes``
pushes), and the chosen pushes' predicted P(topple) against how often they toppled, in all
and per push direction (``validation.DIRECTIONS``: the model ranks pushes from the side well
and pushes from above poorly, so one average can hide two opposite errors).
All policies see the same starts and the same noise draws (common random numbers), so
their differences are their own.  Every push played is also written to a push log
(``schema.pushlog``), one part file per object.

    toppledb policies-physics data/dataset --trials 200 --log data/logs/policies

A trial whose object comes to rest in a pose outside the dataset's pose set (no V_s
is known for it) is counted under ``outside`` and left out of every policy's means,
so the comparison stays paired.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from schema.pushlog import PUSHLOG, below_pybullet_data
from schema.reader import Dataset, DatasetUnreadable
from schema.vocabulary import NO_OP, POLICIES

from ..build.atomic import file_sha256, write_json_atomic
from ..build.corpus import ObjectSpec, is_pybullet_source, pybullet_data_dir
from ..model.config import Config
from ..model.rng import stream
from .playlog import ObjectLog, append_row, mesh_location, write_part
from .policy_experiment import ACTION_SPAN, PolicyTables, draw_starts, load_tables, useful_starts
from .pushsim import body_model, draw_noise, play_push, player_parameters
from .validation import direction_classes

MAX_PUSHES = 3
"""Most pushes per trial and policy (the experiment of the issue; ``toppledb policies`` uses 5)."""
PUSH_STEP_SPAN = 10
"""Log push_id = (trial * len(POLICIES) + policy index) * PUSH_STEP_SPAN + push number."""
PURPOSE = "play"
TRANSFORM_TOLERANCE = 1e-6
"""Largest difference between a recomputed pose transform and the dataset's for the pose sets to agree."""


class ExperimentError(ValueError):
    """The experiment cannot run on this dataset; one line."""


# ---------------------------------------------------------------- the model's side


def dataset_config(dataset: Dataset) -> Config:
    """The parameters the dataset was built with (its stable poses and noise)."""
    try:
        return Config.from_dict(dataset.manifest.parameters.model_dump())
    except ValueError as err:
        raise ExperimentError(f"{dataset.root}: the manifest's parameters are not this code's: {err}") from None


def predicted_values(tables: PolicyTables, policy: str, max_pushes: int) -> np.ndarray:
    """Expected V_s after following ``policy`` for at most ``max_pushes`` pushes, under the stored transitions.

    E_0 = V_s;  E_k(x) = V_s(x) where the policy does not push, else sum_x' P(x' | x, u) E_{k-1}(x').
    returns : (N,) float, one per (object, pose) row of ``tables``
    """
    rows, actions = tables.keys // ACTION_SPAN, tables.keys % ACTION_SPAN
    mine = actions == tables.actions[policy][rows]
    probability = np.diff(np.concatenate([[0.0], tables.cumulative]))[mine]
    rows, next_rows = rows[mine], tables.next_row[mine]
    acting = tables.actions[policy] != NO_OP
    values = tables.v_s.copy()
    for _ in range(max_pushes):
        expected = np.bincount(rows, weights=probability * values[next_rows], minlength=len(values))
        values = np.where(acting, expected, tables.v_s)
    return values


@dataclass
class ObjectPlan:
    """What the workers need of one object from the dataset.

    transforms : (P, 4, 4) float, object -> pose frame of each stable pose;  v_s : (P,) float
    drop_probabilities : (P,) float, each pose's (section 4 of docs/MODEL.md)
    actions : policy -> (P,) int, the policy's action per pose (NO_OP: no push)
    pushes : (pose, action) -> (point (3,), direction (3,), p_topple), pose frame
    """

    spec: ObjectSpec
    transforms: np.ndarray
    v_s: np.ndarray
    drop_probabilities: np.ndarray
    actions: dict[str, np.ndarray]
    pushes: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, float]]


def mesh_file(path: str, source: str, sha256: str) -> Path | None:
    """The file on this machine with a manifest mesh's recorded bytes (``sha256``), or None: its recorded
    ``path``, or, for one of pybullet's meshes recorded under another venv's ``pybullet_data`` (a dataset
    copied from another machine, a venv rebuilt elsewhere), the same file under this one's.

    The manifest records the absolute path the build read, so without this a dataset could be played in
    physics only where it was built.
    """
    recorded = Path(path)
    candidates = [recorded]
    if is_pybullet_source(source) and not recorded.is_absolute():
        candidates = [pybullet_data_dir() / recorded]
    elif is_pybullet_source(source) and (below := below_pybullet_data(path)) is not None:
        candidates.append(pybullet_data_dir() / below)
    return next((c for c in candidates if file_sha256(c) == sha256), None)


def object_plans(dataset: Dataset, object_ids: list[str]) -> dict[str, ObjectPlan]:
    """Each object's spec (mesh path resolved, checked against the manifest's SHA-256) and policy pushes."""
    corpus = {o.object_id: o for o in dataset.manifest.corpus.objects}
    poses = dataset.table("poses", columns=["object_id", "pose", "transform", "v_s", "probability", *(f"{p}_action" for p in POLICIES)])
    poses = poses.sort_by([("object_id", "ascending"), ("pose", "ascending")]).to_pydict()
    by_object: dict[str, list[int]] = {}
    for i, object_id in enumerate(poses["object_id"]):
        by_object.setdefault(object_id, []).append(i)
    plans = {}
    for object_id in object_ids:
        entry = corpus[object_id]
        path = mesh_file(entry.path, entry.source, entry.sha256)
        if path is None:
            raise ExperimentError(f"{object_id}: mesh {entry.path} is missing or differs from the dataset's (sha256)")
        spec = ObjectSpec(object_id, str(path), entry.scale, entry.mass, entry.source, entry.sha256)
        rows = by_object[object_id]
        actions = {p: np.array([poses[f"{p}_action"][i] for i in rows]) for p in POLICIES}
        chosen = {(pose, int(a[pose])) for a in actions.values() for pose in range(len(rows)) if a[pose] != NO_OP}
        table = dataset.object_rows(
            "actions", object_id,
            columns=["pose", "action", "point_x", "point_y", "point_z", "direction_x", "direction_y", "direction_z", "p_topple"],
        ).to_pydict()
        pushes = {}
        for i, key in enumerate(zip(table["pose"], table["action"])):
            if key in chosen:
                point = np.array([table[f"point_{a}"][i] for a in "xyz"])
                direction = np.array([table[f"direction_{a}"][i] for a in "xyz"])
                pushes[key] = (point, direction, float(table["p_topple"][i]))
        if len(pushes) != len(chosen):
            raise ExperimentError(f"{object_id}: a policy's action is missing from the actions table")
        plans[object_id] = ObjectPlan(
            spec=spec,
            transforms=np.array([np.reshape(poses["transform"][i], (4, 4)) for i in rows]),
            v_s=np.array([poses["v_s"][i] for i in rows]),
            drop_probabilities=np.array([poses["probability"][i] for i in rows], dtype=float),
            actions=actions,
            pushes=pushes,
        )
    return plans


# ---------------------------------------------------------------- the physics side


def load_planned(plan: ObjectPlan, config: Config):
    """The plan's object and its stable poses, as the dataset had them (runs in a worker): (object, pose set),
    or a one-line reason it cannot be played: its mesh does not load, or its stable poses are not the
    dataset's (their number or transforms: other code or parameters), which would put every index of the
    dataset's rows on another pose."""
    from ..model.evaluation import load_object
    from ..model.mesh import MeshError
    from ..model.poses import stable_poses

    try:
        obj = load_object(plan.spec, config)
        pose_set = stable_poses(obj, config.poses)
    except MeshError as err:
        return str(err)
    if len(pose_set.poses) != len(plan.transforms) or not np.allclose(pose_set.transforms, plan.transforms, atol=TRANSFORM_TOLERANCE):
        return f"{plan.spec.object_id}: its stable poses differ from the dataset's (other code or parameters)"
    return obj, pose_set


@dataclass
class PolicyRun:
    """One policy in one trial: the poses it went through and its pushes.

    poses : visited poses, start first (the last is where it ended; -1: outside the pose set)
    predicted : (n,) P(topple) of each push;  toppled : (n,) bool, the push changed the pose
    direction_z : (n,) the push direction's vertical component in the pose frame (z up)
    """

    poses: list[int]
    predicted: list[float] = field(default_factory=list)
    toppled: list[bool] = field(default_factory=list)
    direction_z: list[float] = field(default_factory=list)


def play_trials(
    plan: ObjectPlan, trials: list[tuple[int, int]], config: Config, seed: int, max_pushes: int, world: Config | None = None
) -> tuple[str, dict, ObjectLog]:
    """Play every policy from each (trial, start pose) of one object (runs in a worker).

    config : the dataset's parameters (poses, pushes); world : whose noise the simulated
    pushes draw (default ``config``'s)

    returns : (object id, {trial: {policy: PolicyRun}} or {"failure": reason}, the pushes as a log)
    """
    from ..model.poses import settle

    spec = plan.spec
    key = {"object_id": spec.object_id, "mesh_sha256": spec.sha256, "experiment": "policies-physics", "seed": seed,
           "max_pushes": max_pushes, "player": player_parameters()}
    loaded = load_planned(plan, config)
    if isinstance(loaded, str):
        return spec.object_id, {"failure": loaded}, ObjectLog(spec.object_id, PUSHLOG.empty_table(), key, {"pushes": 0})
    obj, pose_set = loaded
    body = body_model(obj)
    source, path = mesh_location(spec)
    columns: dict[str, list] = {f.name: [] for f in PUSHLOG}
    results: dict[int, dict[str, PolicyRun]] = {}
    for trial, start in trials:
        rng = stream(seed, f"{spec.object_id}/trial/{trial}", start, PURPOSE)
        noises = [draw_noise(world or config, rng, noise=True) for _ in range(max_pushes)]  # shared by the policies
        results[trial] = {}
        for policy_index, policy in enumerate(POLICIES):
            run = PolicyRun([start])
            pose, transform = start, plan.transforms[start]
            for step in range(max_pushes):
                action = int(plan.actions[policy][pose])
                if action == NO_OP:
                    break
                point, direction, p_topple = plan.pushes[(pose, action)]
                run.direction_z.append(float(direction[2]))  # the stored direction is in the pose frame
                to_object = np.linalg.inv(plan.transforms[pose])
                point, direction = to_object[:3, :3] @ point + to_object[:3, 3], to_object[:3, :3] @ direction
                played = play_push(body, transform, point, direction, config, noises[step])
                after = settle(pose_set, obj, played.final_transform[:3, :3])
                push_id = (trial * len(POLICIES) + policy_index) * PUSH_STEP_SPAN + step
                append_row(columns, spec, source, path, push_id, 0, pose, action, point, direction, played, config, seed)
                run.predicted.append(p_topple)
                run.toppled.append(after != pose)
                run.poses.append(after)
                if after < 0:
                    break
                pose, transform = after, played.final_transform
            results[trial][policy] = run
    table = pa.Table.from_pydict(columns, schema=PUSHLOG)
    return spec.object_id, results, ObjectLog(spec.object_id, table, key, {"pushes": table.num_rows, "trials": len(trials)})


# ---------------------------------------------------------------- the experiment


def open_trials(root: str | Path, n_trials: int, seed: int) -> tuple[Dataset, Config, PolicyTables, np.ndarray, dict]:
    """The dataset at ``root``, its config and policy tables, ``n_trials`` dropped starts
    (global pose rows, drawn from ``seed``) and, per object id, its (trial, pose) pairs:
    what every physics study of the policies plays from (common random numbers)."""
    try:
        dataset = Dataset.open(root)
    except DatasetUnreadable as err:
        raise ExperimentError(str(err)) from None
    tables = load_tables(dataset)
    starts = draw_starts(tables, n_trials, stream(seed, "policies-physics/starts", -1, PURPOSE))
    objects = np.searchsorted(tables.first_pose, starts, side="right") - 1
    start_pose = starts - tables.first_pose[objects]
    by_object: dict[str, list[tuple[int, int]]] = {}
    for trial, (o, p) in enumerate(zip(objects, start_pose)):
        by_object.setdefault(tables.object_ids[o], []).append((trial, int(p)))
    return dataset, dataset_config(dataset), tables, starts, by_object


def experiment(
    root: str | Path,
    n_trials: int,
    *,
    max_pushes: int = MAX_PUSHES,
    seed: int = 0,
    workers: int | None = 1,
    log: str | Path | None = None,
    progress: bool = False,
    world: Config | None = None,
) -> dict:
    """Run every policy in physics from ``n_trials`` dropped starts; the report as a dict (JSON-ready).

    world : the simulated world's noise (friction, contact, direction); default the
      dataset's own.  The CLI passes the thesis preset, as ``make logs`` does, so the world
      does not change when the model's noise is calibrated.
    """
    from ..build.fanout import map_unordered

    started = time.perf_counter()
    dataset, config, tables, starts, by_object = open_trials(root, n_trials, seed)
    plans = object_plans(dataset, sorted(by_object))

    runs: dict[int, dict[str, PolicyRun]] = {}
    failures: dict[str, str] = {}
    tasks = [(plans[o], by_object[o], config, seed, max_pushes, world) for o in sorted(by_object)]
    for object_id, results, object_log in map_unordered(play_trials, tasks, workers, description="objects", progress=progress):
        if "failure" in results:
            failures[object_id] = results["failure"]
            continue
        runs.update(results)
        if log is not None and object_log.table.num_rows:  # no file for an object no policy pushed
            write_part(Path(log), object_log)

    predicted = {p: predicted_values(tables, p, max_pushes) for p in POLICIES}
    report = summarise(tables, starts, runs, predicted, max_pushes)
    report.update({
        "dataset": str(Path(root).resolve()),
        "trials": n_trials,
        "objects": len(by_object),
        "failed_objects": failures,
        "seed": seed,
        "wall_s": round(time.perf_counter() - started, 1),
    })
    if log is not None:
        write_json_atomic(Path(log) / "_policies_physics.json", report)
    return report


def mean_se(values) -> tuple[float | None, float | None]:
    """Mean and its standard error; None for an empty sample (JSON null), no error for one value.
    values : (n,) float or a sequence of numbers;  returns : (mean, standard error)"""
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return None, None
    return float(values.mean()), (float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else None)


def summarise(tables: PolicyTables, starts: np.ndarray, runs: dict[int, dict[str, PolicyRun]],
              predicted: dict[str, np.ndarray], max_pushes: int) -> dict:
    """Per policy: physical and predicted V_s gains (all and useful trials), pushes, topple rates."""
    played = np.array(sorted(runs), dtype=np.int64)
    outside = np.array([any(r.poses[-1] < 0 for r in runs[t].values()) for t in played], dtype=bool)
    kept = played[~outside]
    rows = starts[kept]
    first_of = np.searchsorted(tables.first_pose, rows, side="right") - 1
    useful = useful_starts(tables, rows)
    report: dict = {"max_pushes": max_pushes, "played_trials": len(played), "outside_trials": int(outside.sum()),
                    "useful_trials": int(useful.sum()), "policies": {}}
    gains = {}
    for policy in POLICIES:
        final_rows = np.array([tables.first_pose[o] + runs[t][policy].poses[-1] for t, o in zip(kept, first_of)], dtype=np.int64)
        physical = tables.v_s[final_rows] - tables.v_s[rows] if len(kept) else np.zeros(0)
        model = predicted[policy][rows] - tables.v_s[rows] if len(kept) else np.zeros(0)
        gains[policy] = physical
        pushes = [r for t in played for r in [runs[t][policy]]]
        p_hat = np.array([p for r in pushes for p in r.predicted])
        toppled = np.array([x for r in pushes for x in r.toppled], dtype=float)
        direction_z = np.array([z for r in pushes for z in r.direction_z])
        again = np.array([x for r in pushes for x in after_a_failure(r.toppled)], dtype=bool)
        n_pushes = np.array([len(runs[t][policy].predicted) for t in kept])
        gain_useful, gain_useful_se = mean_se(physical[useful])
        entry = {
            "physical_gain_all": mean_se(physical)[0],
            "model_gain_all": mean_se(model)[0],
            "physical_gain_useful": gain_useful,
            "physical_gain_useful_se": gain_useful_se,
            "model_gain_useful": mean_se(model[useful])[0],
            "mean_pushes_useful": mean_se(n_pushes[useful])[0],
            "pushes": len(p_hat),
            "predicted_topple_rate": mean_se(p_hat)[0],
            "physical_topple_rate": mean_se(toppled)[0],
            "by_direction": topple_rates_by_direction(p_hat, toppled, direction_z),
            "by_attempt": topple_rates_by_attempt(p_hat, toppled, again),
        }
        report["policies"][policy] = entry
    for policy in ("greedy", "value_iteration"):
        difference = gains[policy][useful] - gains["max_height"][useful]
        mean, error = mean_se(difference)
        model_difference = report["policies"][policy]["model_gain_useful"], report["policies"]["max_height"]["model_gain_useful"]
        report["policies"][policy]["physical_gain_over_max_height"] = mean
        report["policies"][policy]["physical_gain_over_max_height_se"] = error
        report["policies"][policy]["model_gain_over_max_height"] = (
            None if None in model_difference else model_difference[0] - model_difference[1]
        )
    return report


def topple_rates_by_direction(predicted: np.ndarray, toppled: np.ndarray, direction_z: np.ndarray) -> list[dict]:
    """Chosen pushes per push direction (``validation.DIRECTIONS``, by u_z in the pose frame):
    how many, their mean predicted P(topple) and how often they toppled.  Empty classes are left out.

    predicted, toppled, direction_z : (n,) float, one entry per push played
    """
    out = []
    for name, rows in direction_classes(direction_z):
        if rows.any():
            out.append({"direction": name, "pushes": int(rows.sum()),
                        "predicted_topple_rate": float(predicted[rows].mean()),
                        "physical_topple_rate": float(toppled[rows].mean())})
    return out


def after_a_failure(toppled: list[bool]) -> list[bool]:
    """Per push of one trial: whether the push before it left the object in its pose.

    The policies are stationary (one push per pose), so such a push is the same push again, from
    the same pose: the repeat of a push that just failed.  toppled : (n,) bool, in push order"""
    return [k > 0 and not toppled[k - 1] for k in range(len(toppled))]


def topple_rates_by_attempt(predicted: np.ndarray, toppled: np.ndarray, again: np.ndarray) -> list[dict]:
    """Chosen pushes split into first tries and repeats of a push that just failed
    (``after_a_failure``): how many, their mean predicted P(topple) and how often they toppled.

    A push's outcome is nearly fixed by the push (docs/VALIDATION.md, "Physics predicting
    itself"), while P(topple) is the same for every try, so the two parts are read apart.
    predicted, toppled : (n,) float;  again : (n,) bool.  Empty parts are left out."""
    out = []
    for name, rows in (("first try", ~again), ("after a failure", again)):
        if rows.any():
            out.append({"attempt": name, "pushes": int(rows.sum()),
                        "predicted_topple_rate": float(predicted[rows].mean()),
                        "physical_topple_rate": float(toppled[rows].mean())})
    return out


def text(report: dict) -> str:
    """A plain-text table of the report."""
    def cell(value, signed=True):
        return "    -" if value is None else (f"{value:+.3f}" if signed else f"{value:.3f}")

    lines = [
        (
            f"{report['played_trials']} trials on {report['objects']} objects (at most {report['max_pushes']} pushes each), "
            f"{report['useful_trials']} useful, {report['outside_trials']} left out (a rest pose outside the pose set); "
            f"{report['wall_s']} s"
        ),
        (
            f"{'policy':<16} {'V_s gain physics':>17} {'model':>7} {'(all trials: physics':>21} {'model)':>7} "
            f"{'pushes':>7} {'P(topple) predicted':>20} {'physics':>8}"
        ),
    ]
    for policy, r in report["policies"].items():
        lines.append(
            f"{policy:<16} {cell(r['physical_gain_useful']):>17} {cell(r['model_gain_useful']):>7} "
            f"{cell(r['physical_gain_all']):>21} {cell(r['model_gain_all']):>7} {r['pushes']:>7} "
            f"{cell(r['predicted_topple_rate'], False):>20} {cell(r['physical_topple_rate'], False):>8}"
        )
    for split, label in (("by_direction", "direction"), ("by_attempt", "attempt")):
        for policy, r in report["policies"].items():
            lines.append(f"{policy} pushes by {label}, predicted / toppled: " + ", ".join(
                f"{d[label]} {d['pushes']} {d['predicted_topple_rate']:.3f} / {d['physical_topple_rate']:.3f}"
                for d in r.get(split, [])))
    for policy in ("greedy", "value_iteration"):
        r = report["policies"][policy]
        se = r["physical_gain_over_max_height_se"]
        lines.append(
            f"{policy} - max_height on useful trials: physics {cell(r['physical_gain_over_max_height'])}"
            f"{'' if se is None else f' +/- {se:.3f}'}, model {cell(r['model_gain_over_max_height'])}"
        )
    return "\n".join(lines)


def world_config(name: str) -> Config:
    """A preset name or a TOML file, through the dataset command's rules (one-line errors)."""
    import argparse

    from ..cli import UsageError, make_config

    try:
        return make_config(argparse.Namespace(config=name, overrides=[], seed=None))
    except UsageError as err:
        raise ExperimentError(str(err)) from None


def main(argv: list[str] | None = None) -> int:
    """``toppledb policies-physics DATASET --trials N``: the report as a table, then one JSON line."""
    from ..cli import positive_int, print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="toppledb policies-physics", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", help="dataset directory (its corpus objects and policy tables)")
    parser.add_argument("--trials", type=positive_int, default=100, help="dropped starts (default: %(default)s)")
    parser.add_argument("--max-pushes", type=positive_int, default=MAX_PUSHES, help="most pushes per trial (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the starts and the noise (default: %(default)s)")
    parser.add_argument("--workers", type=positive_int, help="worker processes (default: all cores)")
    parser.add_argument("--log", type=Path, metavar="DIR", help="also write every push played to this push-log directory")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report to this JSON file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--world", default="thesis", metavar="PRESET|FILE.toml",
                        help="config whose noise the simulated pushes draw (default: %(default)s, as make logs)")
    args = parser.parse_args(argv)
    if refused_outputs(args.json, directories=(args.log,)):
        return 2
    try:
        report = experiment(args.dataset, args.trials, max_pushes=args.max_pushes, seed=args.seed, workers=args.workers,
                            log=args.log, progress=not args.no_progress, world=world_config(args.world))
    except ExperimentError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    if print_and_record(text(report), report, args.json):
        return 2
    for object_id, reason in report["failed_objects"].items():
        print(f"not played: {object_id}: {reason}", file=sys.stderr)
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
