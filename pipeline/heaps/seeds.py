"""Seeded random streams of the heap experiment, derived as ``pipeline.model.rng.stream`` derives
the dataset's: from (experiment seed, heap number, purpose), never from global state, so a heap
is the same whatever the number of workers or the order they run in."""

from __future__ import annotations

import hashlib

import numpy as np

PURPOSES = ("drop", "friction", "grasps", "policy")
"""``drop``: which objects, their start poses; ``friction``: the heap's friction coefficient;
``grasps``: per-object grasp candidates and perturbations (keyed by object id, heap -1);
``policy``: the push policies' own draws (quasi-random's object and direction)."""


def heap_stream(seed: int, heap: int, purpose: str, key: str = "") -> np.random.Generator:
    """A generator for one (seed, heap, purpose, key).

    seed : int, experiment seed (``HeapConfig.seed``)
    heap : int, heap number (-1 for draws that belong to an object, not a heap)
    purpose : one of ``PURPOSES``
    key : str, e.g. an object id or a policy name (hashed, any string works)
    """
    if purpose not in PURPOSES:
        raise ValueError(f"unknown heap random stream purpose {purpose!r}")
    digest = hashlib.sha256(f"{key}\x00{purpose}".encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(heap) + 1, *words]))
