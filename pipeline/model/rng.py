"""Seeded random streams.

Every random draw in toppledb comes from a generator derived from
(seed, object id, pose index, purpose), never from global state, so results do
not depend on the number of workers, their order, or the backend.
"""

from __future__ import annotations

import hashlib

import numpy as np

PURPOSES = ("contacts", "trials", "suction", "play", "replay")
"""``play``: the push player's draws (which pushes, their noise; ``pipeline.studies.playlog``);
``replay``: the noise of a replay of those pushes with other draws (``play --noise-draws``)."""


def stream(seed: int, object_id: str, pose: int, purpose: str) -> np.random.Generator:
    """A generator for one (seed, object, pose, purpose).

    Parameters
    ----------
    seed : int
      Dataset seed.
    object_id : str
      Stable object identifier (hashed, so any string works).
    pose : int
      Stable pose index, or -1 for per-object draws.
    purpose : str
      One of ``PURPOSES``; separate purposes get independent streams so that
      changing, e.g., the number of suction samples never changes topple trials.
    """
    if purpose not in PURPOSES:
        raise ValueError(f"unknown random stream purpose {purpose!r}")
    digest = hashlib.sha256(f"{object_id}\x00{purpose}".encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.default_rng(np.random.SeedSequence([int(seed), pose + 1, *words]))
