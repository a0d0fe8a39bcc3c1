"""A heap of objects in a bin, and a planar push: the vocabulary of chapter 3.

Frames and units: the world frame has its origin at the centre of the bin's floor, z up,
x along the bin's length; metres throughout.  An object's pose maps its object frame (the
mesh frame of the dataset, metres) into the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Bin:
    """An open box: inner floor ``length`` x ``width`` (m) centred on the world origin,
    walls ``height`` (m) high and ``wall`` (m) thick.  The defaults are a common picking tote."""

    length: float = 0.50
    width: float = 0.40
    height: float = 0.15
    wall: float = 0.01

    def __post_init__(self) -> None:
        for name in ("length", "width", "height", "wall"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"bin {name} must be a positive number of metres, got {value!r}")

    @property
    def half_extents(self) -> np.ndarray:
        """(2,) float, m: half the inner floor size along x and y."""
        return np.array([self.length / 2, self.width / 2])


@dataclass(frozen=True)
class HeapState:
    """Which objects lie where.

    object_ids : (n,) str, dataset object ids (an id may repeat: two copies of one object)
    poses : (n, 4, 4) float, object frame -> world frame, m
    """

    bin: Bin
    object_ids: tuple[str, ...]
    poses: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.shape != (len(self.object_ids), 4, 4):
            raise ValueError(f"poses must be ({len(self.object_ids)}, 4, 4), got {poses.shape}")
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "object_ids", tuple(self.object_ids))

    def __len__(self) -> int:
        return len(self.object_ids)

    def without(self, index: int) -> HeapState:
        """The heap after object ``index`` is picked out of it."""
        keep = [i for i in range(len(self)) if i != index]
        return HeapState(self.bin, tuple(self.object_ids[i] for i in keep), self.poses[keep])


@dataclass(frozen=True)
class Push:
    """A straight finger stroke: the finger tip moves from ``start`` to ``end`` (both (3,) float,
    m, world frame) to push object ``target`` (index into the heap) with ``policy``."""

    policy: str
    target: int
    start: np.ndarray = field(repr=False)
    end: np.ndarray = field(repr=False)

    @property
    def length(self) -> float:
        """m, the stroke's length."""
        return float(np.linalg.norm(np.asarray(self.end) - np.asarray(self.start)))
