"""Hard heaps (thesis 3.3.1): drop a heap, then grasp objects out of it, best grasp first, until
grasping fails; the heap where it fails is a scenario pushing may help with.

"Fails" here: neither gripper's best accessible grasp reaches ``HeapConfig.grasp_threshold``.
The thesis's grasping policy also gave up after n failed attempts in a row; with an analytic
quality there is no attempt to fail, only the confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

from clutter.state import HeapState

from .config import HeapConfig
from .grasps import HeapConfidence, heap_confidence
from .objects import ObjectLibrary
from .world import drop_heap, heap_friction, library_for, remove_object


@dataclass(frozen=True)
class HardHeap:
    """The outcome of one hard-heap search.

    heap : heap number; friction : the heap's friction coefficient
    dropped : the heap as it settled after the drop
    removed : object ids picked out, in order
    state : the hard heap, None when the bin was emptied (or ``max_removals`` ran out)
    confidence : the hard heap's grasp confidence (None with ``state``)
    """

    heap: int
    friction: float
    dropped: HeapState
    removed: tuple[str, ...]
    state: HeapState | None
    confidence: HeapConfidence | None


def hard_heap(seed: int, heap: int, config: HeapConfig, library: ObjectLibrary | None = None) -> HardHeap:
    """Drop heap ``heap`` and pick out the object of the best grasp until grasping fails."""
    library = library_for(config, library)
    friction = heap_friction(seed, heap, config)
    dropped = drop_heap(seed, config, heap=heap, library=library)
    state, removed = dropped, []
    for _ in range(config.max_removals + 1):
        if len(state) == 0:
            break
        confidence = heap_confidence(state, config, library)
        if confidence.overall < config.grasp_threshold:
            return HardHeap(heap, friction, dropped, tuple(removed), state, confidence)
        if len(removed) == config.max_removals:
            break
        target = confidence.best.target
        removed.append(state.object_ids[target])
        state = remove_object(state, target, config, friction, library)
    return HardHeap(heap, friction, dropped, tuple(removed), None, None)
