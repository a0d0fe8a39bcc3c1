"""Arrow schemas of the heap experiment's tables (pushing in clutter, thesis chapter 3).

Three Parquet files in an experiment directory (``toppledb heaps --out DIR``):

- ``heaps.parquet``: one row per dropped heap (hard or not) and its hard-heap search;
- ``heap_objects.parquet``: one row per object of a heap state (the dropped heap, the hard
  heap, and the heap after each policy's push), its pose as a row-major 4x4 transform;
- ``pushes.parquet``: one row per (hard heap, policy): the planned push and the grasp
  confidences before and after it.

Frames: world = the bin's frame (origin at the centre of the floor, z up, x along the bin's
length, metres); an object's pose maps its object frame (the corpus mesh frame) to the world.
Missing values are nulls: a policy that plans no push has no start, end or target.
"""

from __future__ import annotations

import pyarrow as pa

from schema.tables import column, xyz

GRIPPERS = ("suction", "parallel_jaw", "overall")
"""Confidence columns: each gripper's best accessible grasp quality, and the better of the two."""
STAGES = ("dropped", "hard")
"""``heap_objects.stage`` besides ``after:<policy>`` (the heap after that policy's push)."""

HEAP = column("heap", pa.int32(), "Heap number within the experiment (its random streams derive from seed and heap)")
SEED = column("seed", pa.int64(), "Experiment seed")

HEAPS = pa.schema(
    [
        HEAP,
        SEED,
        column("friction", pa.float64(), "The heap's friction coefficient (objects, bin, finger)"),
        column("n_dropped", pa.int32(), "Objects in the heap after the drop settled"),
        column("n_removed", pa.int32(), "Objects grasped out before grasping failed (or the bin emptied)"),
        column("hard", pa.bool_(), "Grasping failed with objects left: a pushing scenario"),
        column("n_objects", pa.int32(), "Objects in the hard heap (0 when not hard)"),
        *[
            column(f"{g}_confidence", pa.float64(), f"{g} grasp confidence of the hard heap (null when not hard)", nullable=True)
            for g in GRIPPERS
        ],
        column("seconds", pa.float64(), "Wall time of this heap's search and rollouts on one core", "s"),
    ]
)

HEAP_OBJECTS = pa.schema(
    [
        HEAP,
        SEED,
        column("stage", pa.string(), "Which state: dropped, hard, or after:<policy>"),
        column("slot", pa.int32(), "Object index within that state (a push's target refers to the hard state's)"),
        column("object_id", pa.string(), "Corpus object id"),
        column("transform", pa.list_(pa.float64(), 16), "Object frame -> world, row-major 4x4", "m"),
    ]
)

PUSHES = pa.schema(
    [
        HEAP,
        SEED,
        column("policy", pa.string(), "Push policy (quasi_random, boundary_shear, free_space, max_clearance, cluster_diffusion)"),
        column("planned", pa.bool_(), "The policy found a push (else it is a no-op and the heap is unchanged)"),
        column("target", pa.int32(), "Pushed object, index into the hard state", nullable=True),
        *xyz("start", "Finger tip start, world frame", "m", nullable=True),
        *xyz("end", "Finger tip end, world frame", "m", nullable=True),
        *[
            column(f"{g}_{when}", pa.float64(), f"{g} grasp confidence {when} the push", nullable=False)
            for g in GRIPPERS
            for when in ("before", "after")
        ],
        *[column(f"{g}_gain", pa.float64(), f"{g} confidence after minus before (thesis 2.3's Delta V)") for g in GRIPPERS],
        column("n_objects_after", pa.int32(), "Objects left in the bin after the push"),
        column("improvable", pa.bool_(), "Some policy (quasi-random included) raised a gripper's confidence on this heap"),
    ]
)

TABLES = {"heaps": HEAPS, "heap_objects": HEAP_OBJECTS, "pushes": PUSHES}
"""File stem -> schema."""
