"""How long ``plan_push`` takes per policy, on synthetic heaps (numpy only, no dataset):

    python -m clutter.bench                      # 10 objects, 20 heaps, 5 repeats
    python -m clutter.bench --objects 30 --heaps 50

Each heap is ``--objects`` random convex objects (``--vertices`` hull vertices each, the
size of a corpus object's hull; 4-12 cm across) at random places and yaws in the default
bin, from ``--seed``.  Prints one JSON line per policy: median and 90th percentile of the
wall time and of the process's CPU time per plan (ms), how many heaps got a push, and the
machine's load average (other work on the cores slows the wall time).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from .policies import POLICIES, plan_push
from .state import Bin, HeapState


def synthetic_heap(rng: np.random.Generator, n: int, vertices: int, bin: Bin) -> tuple[HeapState, list[np.ndarray], np.ndarray]:
    """(state, hulls (V, 3) object frame, centres of mass (n, 3)): ellipsoid point clouds
    resting on z = 0, 4-12 cm across, anywhere in the bin (they may overlap, as in a heap)."""
    hulls, poses = [], []
    for _ in range(n):
        points = rng.normal(size=(vertices, 3))
        points *= rng.uniform(0.02, 0.06, size=3) / np.linalg.norm(points, axis=1, keepdims=True)
        points[:, 2] -= points[:, 2].min()
        hulls.append(points)
        yaw = rng.uniform(0, 2 * np.pi)
        pose = np.eye(4)
        pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        pose[:2, 3] = rng.uniform(-0.7, 0.7, size=2) * bin.half_extents
        poses.append(pose)
    centres = np.array([h.mean(axis=0) for h in hulls])
    return HeapState(bin, tuple(f"object_{i}" for i in range(n)), np.stack(poses)), hulls, centres


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clutter.bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=10)
    parser.add_argument("--heaps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--vertices", type=int, default=65, help="hull vertices per object (corpus median 65)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if min(args.objects, args.heaps, args.repeats) < 1 or args.vertices < 4:
        parser.error("--objects, --heaps and --repeats must be at least 1, --vertices at least 4")
    rng = np.random.default_rng(args.seed)
    heaps = [synthetic_heap(rng, args.objects, args.vertices, Bin()) for _ in range(args.heaps)]
    for policy in POLICIES:
        wall, cpu, found = [], [], 0
        for state, hulls, centres in heaps:
            for repeat in range(args.repeats):
                w, c = time.perf_counter(), time.process_time()
                push = plan_push(policy, state, hulls, centres, rng=np.random.default_rng(repeat))
                wall.append(time.perf_counter() - w)
                cpu.append(time.process_time() - c)
            found += push is not None
        print(json.dumps({
            "policy": policy, "objects": args.objects, "heaps": args.heaps,
            "wall_ms_median": round(float(np.median(wall)) * 1e3, 2), "wall_ms_p90": round(float(np.percentile(wall, 90)) * 1e3, 2),
            "cpu_ms_median": round(float(np.median(cpu)) * 1e3, 2), "cpu_ms_p90": round(float(np.percentile(cpu, 90)) * 1e3, 2),
            "found": found, "load_average": round(os.getloadavg()[0], 2),
        }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
