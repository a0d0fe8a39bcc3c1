"""Time the heap experiment's pieces on one core: ``python -m pipeline.heaps.bench [N]``.

Per heap (heaps 0..N-1 of seed 0, default corpus): the drop and settle, the grasp confidence
(both grippers; the per-object candidate caches are built on first sight of an object and
timed separately), one quasi-random push, one pick-out.  Prints medians in ms.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from .config import HeapConfig
from .experiment import planner_geometry, push_config
from .grasps import heap_confidence, jaw_candidates, suction_candidates
from .seeds import heap_stream
from .world import drop_heap, execute_push, heap_friction, library_for, remove_object

DEFAULT = HeapConfig()


def bench(n: int = 20, config: HeapConfig = DEFAULT) -> dict[str, float]:
    """Median ms of each piece over ``n`` heaps (and the mean object cache build)."""
    from clutter.policies import plan_push

    library = library_for(config, None)
    planner = push_config(config)
    times: dict[str, list[float]] = {"drop_settle": [], "object_cache": [], "confidence": [], "push_settle": [], "remove_settle": []}
    objects_seen = set()
    for heap in range(n):
        t = time.process_time()
        state = drop_heap(config.seed, config, heap=heap, library=library)
        times["drop_settle"].append(time.process_time() - t)
        for k in set(state.object_ids) - objects_seen:
            t = time.process_time()
            suction_candidates(library[k], config.suction, config.seed, k)
            jaw_candidates(library[k], config.jaw, config.seed, k)
            times["object_cache"].append(time.process_time() - t)
            objects_seen.add(k)
        t = time.process_time()
        heap_confidence(state, config, library)
        times["confidence"].append(time.process_time() - t)
        friction = heap_friction(config.seed, heap, config)
        hulls, coms = planner_geometry(state, library)
        push = plan_push("quasi_random", state, hulls, coms, rng=heap_stream(config.seed, heap, "policy", "quasi_random"),
                         config=planner)
        if push is not None:
            t = time.process_time()
            execute_push(state, push, config, friction, library)
            times["push_settle"].append(time.process_time() - t)
        t = time.process_time()
        remove_object(state, 0, config, friction, library)
        times["remove_settle"].append(time.process_time() - t)
    return {k: 1000 * float(np.median(v)) for k, v in times.items() if v}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    n = int(argv[0]) if argv else 20
    for name, ms in bench(n).items():
        print(f"{name:14s} {ms:8.1f} ms (median CPU time, {n} heaps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
