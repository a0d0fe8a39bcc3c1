"""``make bench``: speed and memory of the toppling model, suction quality and value
iteration on a fixed set of corpus meshes, on one core.

The process pins itself to one CPU and limits BLAS/OpenMP threads before numpy
loads, so the figures are per core.  The scalar reference runs on a subsample of
the same trials; the speed-up compares seconds per trial.  The last line printed
is one JSON object.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402

from schema.vocabulary import STATUS_OK  # noqa: E402

from ..model.config import Config  # noqa: E402
from ..model.evaluation import evaluate_object, load_object  # noqa: E402
from ..model.reference import configured_trial, draw_of, scene_from_pose  # noqa: E402
from ..model.rng import stream  # noqa: E402
from ..model.topple import sample_noise  # noqa: E402

THESIS_SECONDS_PER_POSE = 40.47


def bench_specs(count: int) -> list[SimpleNamespace]:
    """The first ``count`` of pybullet_data's random objects at their URDF scale and mass."""
    import pybullet_data

    root = pybullet_data.getDataPath()
    return [
        SimpleNamespace(object_id=f"random_{i:03d}", path=f"{root}/random_urdfs/{i:03d}/{i:03d}.obj", scale=0.015, mass=0.1)
        for i in range(count)
    ]


def pin_to_one_core() -> int:
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    return cpu


def model_seconds(pose_seconds: dict[str, list[float]]) -> np.ndarray:
    """A pose's toppling-model time from ``evaluate_object``'s ``pose_seconds``: its candidate pushes,
    its toppling table, and its share of the contacts every pose shares.  returns : (P,) float, s"""
    shared = pose_seconds["shared_contacts"][0] / len(pose_seconds["topple"])
    return np.array(pose_seconds["actions"]) + np.array(pose_seconds["topple"]) + shared


def beside(n_objects: int, config: Config, other: Config) -> dict:
    """Time ``config``'s model and ``other``'s on the same objects, object by object in turn (which goes
    first alternating), so that a machine whose speed drifts from minute to minute slows both alike.

    returns : other's median s per pose, and config's time over other's: the ratio of their totals
      over every pose, and the median of the per-pose ratios
    """
    seconds: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    for i, spec in enumerate(bench_specs(n_objects)):
        for which in ((0, 1) if i % 2 == 0 else (1, 0)):
            model = (config, other)[which]
            timed: dict[str, list[float]] = {}
            evaluate_object(load_object(spec, model), model, pose_seconds=timed)
            seconds[which].append(model_seconds(timed))
        if len(seconds[0][-1]) != len(seconds[1][-1]):
            raise SystemExit(f"toppledb bench: --beside needs a model with the same stable poses; {spec.object_id} has "
                             f"{len(seconds[0][-1])} and {len(seconds[1][-1])}")
    mine, theirs = np.concatenate(seconds[0]), np.concatenate(seconds[1])  # (P,) each: the same poses
    return {
        "median_s_per_pose": round(float(np.median(theirs)), 4),
        "ratio_total": round(float(mine.sum() / theirs.sum()), 3),
        "ratio_median_per_pose": round(float(np.median(mine / theirs)), 3),
    }


def run(n_objects: int, reference_trials: int, config: Config) -> dict:
    """Time ``evaluate_object`` (the dataset job's own per-object evaluation) on each object,
    per pose, and re-run a subsample of its trials in the scalar reference."""
    pose_seconds, suction_seconds, vi_seconds = [], [], []
    engine_seconds = engine_trials = 0.0
    reference_seconds, reference_count = 0.0, 0
    per_object_reference = max(1, reference_trials // n_objects)
    topple = config.topple
    for spec in bench_specs(n_objects):
        obj = load_object(spec, config)
        seconds: dict[str, list[float]] = {}
        result = evaluate_object(obj, config, pose_seconds=seconds)
        poses, tables, all_actions = result.poses, result.topple, result.actions
        per_pose = model_seconds(seconds)
        pose_seconds += per_pose.tolist()
        engine_seconds += float(per_pose.sum())
        engine_trials += sum(int((a.status == STATUS_OK).sum()) for a in all_actions) * topple.trials
        suction_seconds += seconds["suction"]
        vi_seconds += seconds["mdp"]

        # The reference on a subsample of the very same trials.
        rng = np.random.default_rng(0)
        for _ in range(per_object_reference):
            pose_index = int(rng.integers(len(poses)))
            actions = all_actions[pose_index]
            ok = np.flatnonzero(actions.status == STATUS_OK)
            if len(ok) == 0:
                continue
            pose = poses[pose_index]
            noise = sample_noise(stream(config.seed, obj.name, pose_index, "trials"), len(actions.status), topple)
            scene = scene_from_pose(obj, pose, topple.gravity)
            action, trial = int(rng.choice(ok)), int(rng.integers(topple.trials))
            start = time.perf_counter()
            edge, _ = configured_trial(scene, draw_of(actions, noise, action, trial), topple)
            reference_seconds += time.perf_counter() - start
            reference_count += 1
            if edge != tables[pose_index].outcomes[action, trial]:
                raise AssertionError(f"engine and reference disagree on {obj.name} pose {pose_index} action {action} trial {trial}")

    median = float(np.median(pose_seconds))
    engine_per_trial = engine_seconds / max(engine_trials, 1)
    reference_per_trial = reference_seconds / max(reference_count, 1)
    return {
        "objects": n_objects,
        "poses": len(pose_seconds),
        "contacts": config.contacts.n_contacts,
        "trials": config.topple.trials,
        "median_s_per_pose": round(median, 4),
        "p90_s_per_pose": round(float(np.percentile(pose_seconds, 90)), 4),
        "trials_per_s": round(engine_trials / engine_seconds),
        "speedup_vs_thesis": round(THESIS_SECONDS_PER_POSE / median, 1),
        "reference_trials": reference_count,
        "reference_s_per_trial": round(reference_per_trial, 6),
        "speedup_vs_reference": round(reference_per_trial / engine_per_trial, 1),
        "vs_median_s_per_pose": round(float(np.median(suction_seconds)), 4),
        "vi_median_s_per_object": round(float(np.median(vi_seconds)), 5),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="toppledb bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=20, help="random corpus objects to time (default 20)")
    parser.add_argument("--reference-trials", type=int, default=400, help="trials re-run by the scalar reference")
    parser.add_argument("--config", metavar="PRESET|FILE.toml", help="model parameters, e.g. thesis (default: the dataset's defaults)")
    parser.add_argument("--beside", metavar="PRESET|FILE.toml",
                        help="also time this model on the same objects, in turn with --config's, and report the ratio "
                             "(e.g. thesis: read on a machine whose speed drifts)")
    args = parser.parse_args(argv)
    from ..cli import make_config

    config = make_config(argparse.Namespace(config=args.config, overrides=[], seed=None))
    other = make_config(argparse.Namespace(config=args.beside, overrides=[], seed=None)) if args.beside else None
    cpu = pin_to_one_core()
    print(f"toppledb bench: {args.objects} pybullet random objects, all stable poses, "
          f"{config.contacts.n_contacts} contacts x {config.topple.trials} trials, variant {config.topple.variant}, CPU {cpu} only")
    result = run(args.objects, args.reference_trials, config)
    print(f"toppling model   median {result['median_s_per_pose']:.3f} s/pose (p90 {result['p90_s_per_pose']:.3f}) over {result['poses']} poses; "
          f"{result['trials_per_s']:,} trials/s; {result['speedup_vs_thesis']}x the thesis's {THESIS_SECONDS_PER_POSE} s/pose")
    print(f"scalar reference {result['reference_s_per_trial'] * 1e3:.2f} ms/trial over {result['reference_trials']} trials "
          f"(all agree); engine speed-up {result['speedup_vs_reference']}x per trial")
    print(f"suction V_s      median {result['vs_median_s_per_pose']:.3f} s/pose")
    print(f"value iteration  median {result['vi_median_s_per_object'] * 1e3:.2f} ms/object")
    if other is not None:
        result["beside"] = {"config": args.beside, **beside(args.objects, config, other)}
        print(f"beside {args.beside}: median {result['beside']['median_s_per_pose']:.3f} s/pose; this model takes "
              f"{result['beside']['ratio_total']}x its time (objects in turn; per-pose median {result['beside']['ratio_median_per_pose']}x)")
    print(f"peak memory      {result['peak_rss_mb']} MB")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
