"""The pushing-in-clutter experiment (thesis 3.3.1): hard heaps, every push policy rolled out
from the same states, the confidence gains, the improvable-heap filter, a robust regression.

    toppledb heaps --heaps 1000 --out data/heaps --workers 2

Steps, each heap independent of the others (its random streams derive from (seed, heap)):

1. heap k: drop, then grasp out the best grasp's object until grasping fails
   (``pipeline.heaps.hard``); a heap that empties is no scenario;
2. from the hard state each policy of ``clutter.policies`` plans one push (quasi-random with its
   own stream), the finger executes it in pybullet, and the suction, parallel-jaw and overall
   confidences after it are scored; a policy that plans no push leaves the heap as it was;
3. a heap is *improvable* when some policy (quasi-random included) raised a gripper's confidence.

Heaps are computed until ``--heaps`` hard heaps exist (heap numbers 0, 1, ...; at most
``--max-drops`` drops); the tables hold the first ``--heaps`` hard heaps by heap number, so the
result does not depend on the number of workers.  Each finished heap is a JSON record written
atomically under ``DIR/records/``; a rerun skips them (resumable; a record made with other
parameters stops the run with a one-line error).

Analysis over the improvable heaps, per gripper: mean and standard error of the gain per policy
(figure like thesis figure 3.2), and a robust linear regression (statsmodels RLM, Huber's T) of
the gain on policy dummies (baseline quasi_random) with heap fixed effects (within
transformation): each policy's effect over the baseline with its p-value.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from schema.heaps import GRIPPERS, TABLES

from ..build.atomic import write_atomic, write_text_atomic
from ..build.fanout import SchedulerError, map_unordered
from .config import HeapConfig, to_dict
from .grasps import HeapConfidence, heap_confidence
from .hard import hard_heap
from .objects import ObjectLibrary
from .seeds import heap_stream
from .world import execute_push, library_for

RECORD_VERSION = "1"
"""Bumped whenever a heap record's meaning changes, so old records are not resumed into."""
BASELINE = "quasi_random"
GAIN_EPSILON = 1e-9
"""A confidence gain above this counts as an improvement (qualities are fractions of samples)."""
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def policies():
    """``clutter.policies``'s planner and policy names (imported late: a clear error if missing)."""
    try:
        from clutter.policies import POLICIES, PushConfig, plan_push
    except ImportError as err:
        raise RuntimeError(f"the push policies (clutter.policies) are not available: {err}") from None
    return POLICIES, PushConfig, plan_push


def push_config(config: HeapConfig):
    """The planner's parameters, with the simulation's finger radius."""
    return policies()[1](finger_radius=config.sim.finger_radius)


def fingerprint(config: HeapConfig) -> str:
    """Short hash of every parameter, the planner's included (and the record version): records
    are resumed only into a run with the same one.  (Not of the code: after changing a policy
    or the simulation, bump ``RECORD_VERSION`` or use a new directory.)"""
    text = json.dumps(
        {"version": RECORD_VERSION, "config": to_dict(config), "push": repr(push_config(config))},
        sort_keys=True, default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ---------------------------------------------------------------- one heap


def planner_geometry(state, library: ObjectLibrary) -> tuple[list[np.ndarray], np.ndarray]:
    """What ``plan_push`` needs of the heap's objects: hull vertices (V_i, 3) and centres of mass
    (n, 3), object frame, m."""
    hulls = [library[k].model.hull.vertices for k in state.object_ids]
    return hulls, np.array([library[k].model.center_mass for k in state.object_ids])


def state_rows(heap: int, seed: int, stage: str, state) -> list[dict]:
    return [
        {"heap": heap, "seed": seed, "stage": stage, "slot": i, "object_id": oid, "transform": pose.reshape(-1).tolist()}
        for i, (oid, pose) in enumerate(zip(state.object_ids, state.poses))
    ]


def confidences(c: HeapConfidence) -> dict[str, float]:
    return {"suction": c.quality("suction"), "parallel_jaw": c.quality("parallel_jaw"), "overall": c.overall}


def run_heap(heap: int, config: HeapConfig, library: ObjectLibrary | None = None) -> dict:
    """Hard-heap search and every policy's rollout for heap number ``heap``; a JSON-able record
    holding its rows of the three tables."""
    names, _, plan_push = policies()
    library = library_for(config, library)
    started = time.process_time()
    seed = config.seed
    found = hard_heap(seed, heap, config, library)
    objects = state_rows(heap, seed, "dropped", found.dropped)
    summary = {
        "heap": heap, "seed": seed, "friction": found.friction, "n_dropped": len(found.dropped),
        "n_removed": len(found.removed), "hard": found.state is not None,
        "n_objects": 0 if found.state is None else len(found.state),
        **{f"{g}_confidence": None for g in GRIPPERS},
    }
    pushes = []
    if found.state is not None:
        state = found.state
        before = confidences(found.confidence)
        summary.update({f"{g}_confidence": before[g] for g in GRIPPERS})
        objects += state_rows(heap, seed, "hard", state)
        hulls, coms = planner_geometry(state, library)
        planner = push_config(config)
        for policy in names:
            rng = heap_stream(seed, heap, "policy", policy)
            push = plan_push(policy, state, hulls, coms, rng=rng, config=planner)
            if push is None:
                after_state, after = state, before
            else:
                after_state = execute_push(state, push, config, friction=found.friction, library=library)
                after = confidences(heap_confidence(after_state, config, library))
                objects += state_rows(heap, seed, f"after:{policy}", after_state)
            row = {"heap": heap, "seed": seed, "policy": policy, "planned": push is not None,
                   "target": None if push is None else push.target}
            for name, point in (("start", None if push is None else push.start), ("end", None if push is None else push.end)):
                for axis, value in zip("xyz", [None] * 3 if point is None else np.asarray(point, dtype=float).tolist()):
                    row[f"{name}_{axis}"] = value
            for g in GRIPPERS:
                row[f"{g}_before"], row[f"{g}_after"] = before[g], after[g]
                row[f"{g}_gain"] = after[g] - before[g]
            row["n_objects_after"] = len(after_state)
            pushes.append(row)
        improvable = any(r[f"{g}_gain"] > GAIN_EPSILON for r in pushes for g in ("suction", "parallel_jaw"))
        for row in pushes:
            row["improvable"] = improvable
    summary["seconds"] = time.process_time() - started
    return {"heap": heap, "fingerprint": fingerprint(config), "heaps": [summary], "heap_objects": objects, "pushes": pushes}


def record_path(out: Path, heap: int) -> Path:
    return out / "records" / f"heap_{heap:07d}.json"


def compute_and_save(heap: int, config: HeapConfig, out: Path) -> dict:
    """``run_heap`` and its record written atomically (the unit of resumption)."""
    record = run_heap(heap, config)
    write_text_atomic(record_path(out, heap), json.dumps(record))
    return record


class ResumeError(ValueError):
    """A record in the output directory was made with other parameters; one line."""


def load_record(out: Path, heap: int, config: HeapConfig) -> dict | None:
    path = record_path(out, heap)
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    if record.get("fingerprint") != fingerprint(config):
        raise ResumeError(f"{path} was made with other parameters; use a new --out directory")
    return record


# ---------------------------------------------------------------- many heaps


def collect(config: HeapConfig, out: Path, n_hard: int, max_drops: int, workers: int, progress: bool,
            scheduler: str | None = None) -> list[dict]:
    """Records of heaps 0, 1, ... until the first ``n_hard`` hard ones (or ``max_drops`` drops);
    on ``scheduler`` (a dask.distributed address) instead of local workers when given."""
    records: dict[int, dict] = {}
    next_heap = 0

    def hard_so_far() -> int:
        # Only a prefix without gaps counts: the first n_hard hard heaps by number.
        count, k = 0, 0
        while k in records and count < n_hard:
            count += bool(records[k]["heaps"][0]["hard"])
            k += 1
        return count

    while hard_so_far() < n_hard and next_heap < max_drops:
        done = [k for k in records if records[k]["heaps"][0]["hard"]]
        rate = max(len(done), 1) / max(len(records), 1)
        batch = int(min(max_drops - next_heap, max(2 * workers, math.ceil((n_hard - hard_so_far()) / rate * 1.1))))
        todo = []
        for k in range(next_heap, next_heap + batch):
            record = load_record(out, k, config)
            if record is None:
                todo.append(k)
            else:
                records[k] = record
        next_heap += batch
        for record in map_unordered(
            compute_and_save, [(k, config, out) for k in todo], workers=workers, scheduler=scheduler,
            description="heaps", progress=progress,
        ):
            records[record["heap"]] = record
    chosen, count = [], 0
    for k in sorted(records):
        if count >= n_hard:
            break
        chosen.append(records[k])
        count += bool(records[k]["heaps"][0]["hard"])
    return chosen


def tables(records: Sequence[dict]):
    """The three pyarrow tables of the chosen records."""
    import pyarrow as pa

    out = {}
    for name, schema in TABLES.items():
        rows = [row for record in records for row in record[name]]
        out[name] = pa.Table.from_pylist(rows, schema=schema)
    return out


# ---------------------------------------------------------------- analysis


def summary_stats(pushes) -> dict:
    """Per gripper and policy: n, mean gain and its standard error (over the given rows)."""
    result = {}
    for g in GRIPPERS:
        result[g] = {}
        for policy, group in pushes.groupby("policy", sort=False):
            gains = group[f"{g}_gain"].to_numpy()
            sem = float(gains.std(ddof=1) / np.sqrt(len(gains))) if len(gains) > 1 else None
            result[g][policy] = {"n": len(gains), "mean": float(gains.mean()) if len(gains) else None, "sem": sem}
    return result


def regression(pushes, gripper: str) -> dict:
    """Robust linear regression of one gripper's gain on policy dummies (baseline quasi_random),
    controlling for the heap (heap fixed effects).

    The heap effects are absorbed by the within transformation: each heap's mean is subtracted
    from the gains and from the dummies, and the regression runs without heap dummies or
    constant.  For least squares this gives exactly the dummy-variable coefficients (Frisch-Waugh-
    Lovell); for the robust fit (statsmodels RLM, Huber's T) it is the usual approximation, and it
    keeps the design at (n, policies) instead of (n, heaps): with a thousand heaps the dummy
    design takes minutes and gigabytes.  Least squares with errors clustered by heap is reported
    beside it (``ols_cluster``) as a check.

    returns : {"n_obs", "n_heaps", "rlm_scale", "effects": {policy: {"coef", "se", "p"}},
      "ols_cluster": {...}} or {"error": why, "n_obs"}
    """
    import pandas as pd
    import statsmodels.api as sm

    data = pushes[["heap", "policy", f"{gripper}_gain"]].dropna()
    others = [p for p in data["policy"].unique() if p != BASELINE]
    if data["heap"].nunique() < 2 or BASELINE not in set(data["policy"]) or not others:
        return {"error": "too few heaps or policies for a regression", "n_obs": len(data)}
    heaps = data["heap"].to_numpy()
    dummies = pd.DataFrame({p: (data["policy"] == p).to_numpy(float) for p in others})
    gains = pd.Series(data[f"{gripper}_gain"].to_numpy(float))
    x = dummies - dummies.groupby(heaps).transform("mean")
    y = gains - gains.groupby(heaps).transform("mean")
    if np.allclose(y, 0.0):
        return {"error": "every gain equals its heap's mean; nothing to regress", "n_obs": len(y)}
    robust = sm.RLM(y.to_numpy(), x, M=sm.robust.norms.HuberT()).fit()
    ols = sm.OLS(y.to_numpy(), x).fit(cov_type="cluster", cov_kwds={"groups": heaps})

    def effects(fit) -> dict:
        return {p: {"coef": float(fit.params[p]), "se": float(fit.bse[p]), "p": float(fit.pvalues[p])} for p in others}

    return {
        "n_obs": len(y), "n_heaps": len(set(heaps)), "rlm_scale": float(robust.scale),
        "effects": effects(robust), "ols_cluster": effects(ols),
    }


def figure(stats: dict, names: Sequence[str], path: Path) -> None:
    """Means and standard errors of the gain per policy, one group per gripper (thesis figure 3.2)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(names)
    for i, policy in enumerate(names):
        means = [stats[g].get(policy, {}).get("mean") or 0.0 for g in GRIPPERS]
        sems = [stats[g].get(policy, {}).get("sem") or 0.0 for g in GRIPPERS]
        ax.bar(np.arange(len(GRIPPERS)) + (i - (len(names) - 1) / 2) * width, means, width, yerr=sems, capsize=3, label=policy)
    ax.set_xticks(np.arange(len(GRIPPERS)), ["suction", "parallel jaw", "overall"])
    ax.set_ylabel("grasp confidence gain (mean, SEM)")
    ax.axhline(0.0, color="black", linewidth=0.5)
    ax.legend(fontsize=8)
    ax.set_title("Confidence gain per push policy, improvable heaps")
    fig.tight_layout()
    write_atomic(path, lambda temp: fig.savefig(temp, format="png", dpi=100))
    plt.close(fig)


def analyse(tabs: dict) -> dict:
    heaps = tabs["heaps"].to_pandas()
    pushes = tabs["pushes"].to_pandas()
    improvable = pushes[pushes["improvable"]]
    planned = improvable[improvable["planned"]]
    return {
        "heaps_dropped": len(heaps),
        "hard_heaps": int(heaps["hard"].sum()),
        "improvable_heaps": int(improvable["heap"].nunique()),
        "objects_per_hard_heap": heaps.loc[heaps["hard"], "n_objects"].value_counts().sort_index().to_dict(),
        "pushes_planned": pushes.groupby("policy")["planned"].mean().to_dict() if len(pushes) else {},
        "gain_improvable": summary_stats(improvable) if len(improvable) else {},
        "regression": {g: regression(planned, g) for g in GRIPPERS} if len(planned) else {},
        "cpu_seconds_per_heap": float(heaps["seconds"].mean()) if len(heaps) else None,
        "cpu_seconds_total": float(heaps["seconds"].sum()),
    }


# ---------------------------------------------------------------- command


def write_outputs(out: Path, records: list[dict], config: HeapConfig, elapsed: float, workers: int) -> dict:
    import pyarrow.parquet as pq

    tabs = tables(records)
    for name, table in tabs.items():
        write_atomic(out / f"{name}.parquet", lambda temp, t=table: pq.write_table(t, temp))
    report = analyse(tabs)
    names = policies()[0]
    if report["gain_improvable"]:
        figure(report["gain_improvable"], names, out / "gains.png")
    # Wall time of this invocation only: heaps resumed from records cost nothing here
    # (cpu_seconds_total is the whole experiment's compute, wherever it ran).
    report.update({"wall_seconds_this_run": elapsed, "workers": workers, "config": to_dict(config)})
    write_text_atomic(out / "report.json", json.dumps(report, indent=2, default=str) + "\n")
    return report


def _output_directory(text: str) -> Path:
    """--out as a path, refusing "" (``Path("")`` is the working directory; as ``pipeline.cli.path_arg``,
    which this layer does not import)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; name a directory ('.' is the working directory)")
    return Path(text)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="toppledb heaps",
        description="Pushing in clutter (thesis chapter 3): hard heaps in pybullet, five push policies, "
        "grasp-confidence gains and a robust regression.  Resumable: rerun the same command.",
    )
    p.add_argument("--heaps", type=int, default=20, metavar="N", help="hard heaps (pushing scenarios) to collect (default 20)")
    p.add_argument("--out", type=_output_directory, required=True, help="output directory (tables, report.json, gains.png)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on this dask.distributed scheduler, e.g. tcp://host:8786")
    p.add_argument("--seed", type=int, default=0, help="experiment seed (default 0)")
    p.add_argument("--max-drops", type=int, default=None, metavar="M", help="most heaps dropped (default 20 x --heaps)")
    p.add_argument("--threshold", type=float, default=None, help="hard-heap grasp confidence threshold (default 0.9)")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=sys.stderr.isatty(), help="progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.heaps < 1 or args.workers < 1 or args.seed < 0 or (args.max_drops is not None and args.max_drops < 1):
        print("toppledb heaps: --heaps, --workers and --max-drops must be at least 1, --seed at least 0", file=sys.stderr)
        return EXIT_USAGE
    try:
        config = HeapConfig(seed=args.seed, **({} if args.threshold is None else {"grasp_threshold": args.threshold}))
        policies()
    except (ValueError, RuntimeError) as err:
        print(f"toppledb heaps: {err}", file=sys.stderr)
        return EXIT_USAGE
    started = time.perf_counter()
    try:
        records = collect(config, args.out, args.heaps, args.max_drops or 20 * args.heaps, args.workers, args.progress,
                          args.scheduler)
    except (ResumeError, SchedulerError) as err:
        print(f"toppledb heaps: {err}", file=sys.stderr)
        return EXIT_USAGE
    report = write_outputs(args.out, records, config, time.perf_counter() - started, args.workers)
    print(
        f"{report['heaps_dropped']} heaps dropped, {report['hard_heaps']} hard, {report['improvable_heaps']} improvable; "
        f"tables and report.json in {args.out}"
    )
    return EXIT_OK if report["hard_heaps"] else EXIT_FAILED
