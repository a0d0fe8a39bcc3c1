"""Arrow schemas of the dataset's tables, each column documented.

Every field carries metadata ``description`` and, where it has one, ``unit``;
``describe(schema)`` renders them as a Markdown table (docs/DATASET.md is made
from it).  Vectors are flat ``_x, _y, _z`` columns so that SQL and dataframes
can use them directly; the 4x4 pose transform is one fixed-size list.

Frames: "object" is the mesh's own frame (metres, after the corpus scale);
"pose" is the canonical frame of one stable pose: z up, table at z = 0, centre
of mass over the origin.

Missing values are nulls, never NaN: an action that is not ``ok`` has no topple
probability, Q-value or greedy value, so SQL aggregates skip it.

``actions`` and ``transitions`` are stored hive-partitioned by object
(``actions/object_id=<id>/part-0.parquet``); the files themselves do not hold the
partition column, readers add it from the directory name (pyarrow
``partitioning="hive"``, duckdb ``hive_partitioning=true``, polars
``hive_partitioning=True``).  ``objects.parquet`` and ``poses.parquet`` are single
files that include ``object_id``.
"""

from __future__ import annotations

import pyarrow as pa

from schema.vocabulary import NO_OP, POLICIES

PARTITION_KEY = "object_id"
"""Column by which ``actions`` and ``transitions`` are partitioned."""



def column(name: str, type_: pa.DataType, description: str, unit: str | None = None, nullable: bool = False) -> pa.Field:
    """A documented field."""
    metadata = {"description": description}
    if unit:
        metadata["unit"] = unit
    return pa.field(name, type_, nullable=nullable, metadata=metadata)


def xyz(prefix: str, description: str, unit: str | None = None, nullable: bool = False) -> list[pa.Field]:
    """Three float64 fields ``<prefix>_x``, ``_y``, ``_z`` of one 3-vector."""
    return [column(f"{prefix}_{axis}", pa.float64(), f"{description} ({axis})", unit, nullable) for axis in "xyz"]


OBJECT_ID = column(PARTITION_KEY, pa.string(), "Object identifier, unique in the corpus (e.g. random_042, duck)")
POSE = column("pose", pa.int32(), "Stable pose index within the object, 0 = most probable")
ACTION = column("action", pa.int32(), "Candidate push index within the pose")

OBJECTS = pa.schema(
    [
        OBJECT_ID,
        column("source", pa.string(), "Where the mesh comes from (e.g. pybullet_data/random_urdfs, dir:<path>)"),
        column("sha256", pa.string(), "SHA-256 of the mesh file, hex"),
        column("mass", pa.float64(), "Object mass", "kg"),
        column("scale", pa.float64(), "Factor applied to the mesh file's coordinates to give metres"),
        *xyz("com", "Centre of mass, object frame", "m"),
        column("n_poses", pa.int32(), "Number of stable poses"),
        column("n_hull_vertices", pa.int32(), "Vertices of the convex hull"),
        column("n_faces", pa.int32(), "Faces (triangles) of the convex hull"),
        column(
            "hull_vertices",
            pa.list_(pa.list_(pa.float64(), 3)),
            "Convex hull vertices, object frame, [x, y, z] each (the heap planner's footprints come from them)",
            "m",
        ),
        column("repairs", pa.list_(pa.string()), "Repairs made when loading the mesh, one sentence each"),
    ],
    metadata={"table": "objects", "description": "One row per object that was evaluated successfully"},
)

POLICY_NO_PUSH = {"max_height": " (also when its push is not ok, or the pose already has the object's best V_s)"}
"""Why a policy does not push, beyond that grasping now is worth as much (docs/MODEL.md section 12)."""

POLICY_VALUE = {
    "max_height": "greedy of its push (it pushes even into an expected loss)",
    "greedy": "greedy of its push",
    "value_iteration": "q of its push, before gamma's discount",
}
"""What a policy's ``<policy>_value`` is when it pushes."""

POSES = pa.schema(
    [
        OBJECT_ID,
        POSE,
        column("probability", pa.float64(), "Probability of coming to rest in this pose when dropped; poses below poses.min_probability are left out unless a topple reaches them, and the rest are not renormalised, so an object's may sum to less than 1"),
        column(
            "transform",
            pa.list_(pa.float64(), 16),
            "Object frame -> pose frame, 4x4 homogeneous matrix, row-major (reshape(4, 4))",
            "m (translation)",
        ),
        *xyz("down", "Unit vector in the object frame pointing down onto the table"),
        column(
            "equivalent_transforms",
            pa.list_(pa.list_(pa.float64(), 16)),
            "Every orientation that is this pose, object frame -> pose frame, 4x4 row-major each, this row's "
            "transform first; more than one only for a rotationally symmetric object whose turned copies of the "
            "pose were merged into it (a pose matcher searches them all)",
            "m (translation)",
        ),
        column("height", pa.float64(), "Top of the object above the table", "m"),
        column("com_height", pa.float64(), "Centre of mass above the table", "m"),
        column("n_base_edges", pa.int32(), "Edges of the support polygon"),
        column("n_actions", pa.int32(), "Candidate pushes, Max-Height baseline's included"),
        column("n_ok_actions", pa.int32(), "Candidate pushes whose status is ok"),
        column("v_s", pa.float64(), "V_s: robust quality of the best suction grasp from above, in [0, 1]: the share of suction.n_samples noisy grasps that hold, so a multiple of 1/n_samples"),
        *xyz("grasp_point", "Best suction grasp contact point, pose frame; null when there is none", "m", nullable=True),
        *xyz("grasp_axis", "Best grasp approach axis, unit, gripper -> object, pose frame; null when none", nullable=True),
        column("v_t", pa.float64(), "V_T = max(V_s, gamma max_u Q_T): value of the pose under value iteration (thesis 4.3.3), by the single best push; with mdp.choice_radius > 0 (the default) the stored value_iteration choice ranks pushes by their neighbourhood's mean instead (docs/MODEL.md (12.15)), and may push another or none"),
        column("v_failed", pa.float64(), "What q counts this pose at when a push leaves the object in it: V1 of docs/MODEL.md (12.13) with mdp.believe_failures (the default), else v_t (mdp.retry_failed) or v_s; so an action's q = sum over next_pose != pose of P v_t(next_pose) + P(next_pose = pose) v_failed"),
        *[
            field
            for policy in POLICIES
            for field in (
                column(f"{policy}_action", pa.int32(), f"Action chosen by the {policy} policy, {NO_OP} = no push{POLICY_NO_PUSH.get(policy, '')}"),
                column(f"{policy}_value", pa.float64(), f"Expected value of the {policy} policy's choice: {POLICY_VALUE[policy]}; v_s when it does not push"),
            )
        ],
    ],
    metadata={"table": "poses", "description": "One row per stable pose of every object"},
)

ACTIONS = pa.schema(
    [
        OBJECT_ID,
        POSE,
        ACTION,
        column("status", pa.string(), "ok, or why the push cannot be executed: too_low, pushes_up, finger_collision"),
        *xyz("point", "Contact point, pose frame", "m"),
        *xyz("normal", "Outward unit surface normal at the contact, pose frame"),
        *xyz("direction", "Unit push direction, pose frame"),
        column("is_max_height", pa.bool_(), "This is the Max-Height baseline's action (thesis 4.3.1)"),
        column("p_topple", pa.float64(), "P(next pose != pose) of the row as stored; the default's rows are recalibrated, smoothed over neighbouring pushes and mapped (docs/MODEL.md C.7, C.12-C.19), so it is not the share of this push's own trials that toppled; null unless status is ok", nullable=True),
        column(
            "mean_force",
            pa.float64(),
            "Mean required push force over this push's own trials that topple over some edge (blocked edges included); null when none does or not ok (p_topple, where smoothed or mapped, need not be 0 there)",
            "N",
            nullable=True,
        ),
        column("q", pa.float64(), "Q_T(pose, action): expected V_T after this push, value iteration planning over the pushes the policies may choose (mdp.min_direction_z); where it leaves the object in its pose, that pose is worth the poses table's v_failed: its grasp V_s if mdp.retry_failed is false, its failed state's value V1 if mdp.believe_failures is true (Q0 of docs/MODEL.md (12.13)); null unless ok", nullable=True),
        column("greedy", pa.float64(), "E[V_s(next pose)], the Greedy policy's score; null unless ok", nullable=True),
    ],
    metadata={"table": "actions", "description": "Every candidate push of every pose; partitioned by object_id"},
)

TRANSITIONS = pa.schema(
    [
        OBJECT_ID,
        POSE,
        ACTION,
        column("next_pose", pa.int32(), "Pose the object comes to rest in (equal to pose: it stayed)"),
        column("probability", pa.float64(), "P(next_pose | pose, action) > 0; sums to 1 over next_pose"),
    ],
    metadata={
        "table": "transitions",
        "description": "P(x' | x, u) in long form, nonzero entries of ok actions only; partitioned by object_id",
    },
)

TABLES = {"objects": OBJECTS, "poses": POSES, "actions": ACTIONS, "transitions": TRANSITIONS}
"""Every table by name."""

PARTITIONED = ("actions", "transitions")
"""Tables stored hive-partitioned by ``PARTITION_KEY``; the others are single files."""


def file_schema(schema: pa.Schema) -> pa.Schema:
    """Schema of one partition file: the table's schema without the partition column."""
    index = schema.get_field_index(PARTITION_KEY)
    return schema.remove(index) if index >= 0 else schema


def describe(schema: pa.Schema) -> str:
    """Markdown table of a schema's columns: name, type, unit, description."""
    lines = ["| column | type | unit | description |", "| --- | --- | --- | --- |"]
    for field in schema:
        meta = {k.decode(): v.decode() for k, v in (field.metadata or {}).items()}
        cells = [f"`{field.name}`", str(field.type), meta.get("unit", ""), meta.get("description", "")]
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |")
    return "\n".join(lines)
