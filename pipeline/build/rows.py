"""One object's ``ObjectResult`` as rows of the four tables and arrays of its
HDF5 file (``ShardData``), ready for ``pipeline.build.shards`` to write.

Runs in the worker, so the parent only writes.  Columns are ``schema.tables``',
arrays ``schema.hdf5``'s; missing values become nulls, never NaN.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from schema import tables
from schema.version import SCHEMA_VERSION
from schema.vocabulary import POLICIES, STATUS_NAMES, STATUS_OK

from ..model.outcomes import ObjectResult
from .corpus import ObjectSpec


class ShardError(ValueError):
    """An ObjectResult that cannot be stored (inconsistent shapes, unknown policy)."""


@dataclass
class ShardData:
    """Everything a shard stores for one object, ready to write.

    rows : table name -> Arrow table (objects, poses: with object_id; actions,
      transitions: without it, the partition directory holds it)
    object_arrays : HDF5 path -> array, see ``schema.hdf5.OBJECT_ARRAYS``
    pose_arrays : per pose, name -> array, see ``schema.hdf5.POSE_ARRAYS``
    attributes : HDF5 root attributes
    counts : poses, actions, ok_actions, transitions
    timings : seconds per stage, from the compute plus ``tables``
    """

    object_id: str
    rows: dict[str, pa.Table]
    object_arrays: dict[str, np.ndarray]
    pose_arrays: list[dict[str, np.ndarray]]
    attributes: dict[str, Any]
    counts: dict[str, int]
    timings: dict[str, float] = field(default_factory=dict)


def build_shard(spec: ObjectSpec, result: ObjectResult, n_trials: int) -> ShardData:
    """Tables and arrays of one object.  ``n_trials``: trials per action actually run
    (``config.topple.trials``), the T of the outcome arrays."""
    started = time.process_time()
    n_poses = len(result.poses)
    for name in ("actions", "topple", "suction", "values"):
        if len(getattr(result, name)) != n_poses:
            raise ShardError(f"{spec.object_id}: {len(getattr(result, name))} {name} for {n_poses} poses")
    if n_poses == 0:
        raise ShardError(f"{spec.object_id}: no stable poses")

    pose_rows, action_parts, transition_parts, pose_arrays = [], [], [], []
    for i, (pose, actions, topple, suction, values) in enumerate(
        zip(result.poses, result.actions, result.topple, result.suction, result.values)
    ):
        where = f"{spec.object_id} pose {i}"
        n_actions = len(actions.status)
        _expect_shape(where, "actions.points", actions.points, (n_actions, 3))
        _expect_shape(where, "actions.normals", actions.normals, (n_actions, 3))
        _expect_shape(where, "actions.directions", actions.directions, (n_actions, 3))
        _expect_shape(where, "topple.next_pose", topple.next_pose, (n_actions, n_poses))
        _expect_shape(where, "topple.outcomes", topple.outcomes, (n_actions, n_trials))
        for name, array in (("topple.p_topple", topple.p_topple), ("topple.mean_force", topple.mean_force),
                            ("values.q", values.q), ("values.greedy", values.greedy)):
            _expect_shape(where, name, array, (n_actions,))
        missing = set(POLICIES) - set(values.policies)
        if missing:
            raise ShardError(f"{where}: no choice of policy {sorted(missing)}")

        ok = np.asarray(actions.status) == STATUS_OK
        action_parts.append(_action_columns(where, i, actions, topple, values))
        transition_parts.append(_transition_columns(i, topple.next_pose, ok))
        equivalents = pose.transform[None] if result.equivalent_transforms is None else result.equivalent_transforms[i]
        pose_rows.append(_pose_row(spec.object_id, pose, equivalents, len(actions.status), int(ok.sum()), suction, values))
        pose_arrays.append(
            {
                "transform": pose.transform,
                "down": pose.down,
                "base_edges": np.asarray(pose.base_edges).reshape(-1, 2, 3),
                "edge_final_pose": pose.edge_final_pose,
                "edge_landed_pose": topple.edge_landed_pose,
                "edge_onward_pose": topple.edge_onward_pose,
                "edge_onward_share": topple.edge_onward_share,
                "edge_blocked": pose.edge_blocked,
                "apex_angle": pose.apex_angle,
                "outcomes": topple.outcomes,
            }
        )

    actions_table = _concat(action_parts, tables.file_schema(tables.ACTIONS))
    transitions_table = _concat(transition_parts, tables.file_schema(tables.TRANSITIONS))
    poses_table = pa.Table.from_pylist(pose_rows, schema=tables.POSES)
    objects_table = pa.Table.from_pylist([_object_row(spec, result)], schema=tables.OBJECTS)

    counts = {
        "poses": n_poses,
        "actions": actions_table.num_rows,
        "ok_actions": int(sum(r["n_ok_actions"] for r in pose_rows)),
        "transitions": transitions_table.num_rows,
    }
    timings = {k: float(v) for k, v in result.timings.items()}
    timings["tables"] = time.process_time() - started
    return ShardData(
        object_id=spec.object_id,
        rows={"objects": objects_table, "poses": poses_table, "actions": actions_table, "transitions": transitions_table},
        object_arrays={
            "center_mass": result.center_mass,
            "hull/vertices": result.hull_vertices,
            "hull/faces": result.hull_faces,
        },
        pose_arrays=pose_arrays,
        attributes={"schema_version": SCHEMA_VERSION, "object_id": spec.object_id, "n_poses": n_poses, "n_trials": n_trials},
        counts=counts,
        timings=timings,
    )


def _expect_shape(where: str, name: str, array, shape: tuple[int, ...]) -> None:
    if np.shape(array) != shape:
        raise ShardError(f"{where}: {name} has shape {np.shape(array)}, expected {shape}")


def _nullable(values) -> pa.Array:
    """float64 array with NaN as null (analysts' aggregates skip nulls, NaN poisons them)."""
    values = np.asarray(values, dtype=np.float64)
    return pa.array(values, type=pa.float64(), mask=np.isnan(values))


def _xyz(prefix: str, vectors) -> dict[str, np.ndarray]:
    vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    return {f"{prefix}_{axis}": vectors[:, k] for k, axis in enumerate("xyz")}


def _action_columns(where: str, pose_index: int, actions, topple, values) -> dict[str, Any]:
    n = len(actions.status)
    status = np.asarray(actions.status)
    unknown = status[(status < 0) | (status >= len(STATUS_NAMES))]
    if len(unknown):
        raise ShardError(f"{where}: unknown action status code {int(unknown[0])}")
    return {
        "pose": np.full(n, pose_index, dtype=np.int32),
        "action": np.arange(n, dtype=np.int32),
        "status": pa.array(np.asarray(STATUS_NAMES, dtype=object)[status], type=pa.string()),
        **_xyz("point", actions.points),
        **_xyz("normal", actions.normals),
        **_xyz("direction", actions.directions),
        "is_max_height": np.arange(n) == actions.max_height,
        "p_topple": _nullable(topple.p_topple),
        "mean_force": _nullable(topple.mean_force),
        "q": _nullable(values.q),
        "greedy": _nullable(values.greedy),
    }


def _transition_columns(pose_index: int, next_pose, ok: np.ndarray) -> dict[str, Any]:
    """Nonzero P(x'|x,u) of ok actions, ordered by action then next pose."""
    probabilities = np.where(ok[:, None], np.nan_to_num(np.asarray(next_pose, dtype=np.float64)), 0.0)
    action, target = np.nonzero(probabilities > 0)
    return {
        "pose": np.full(len(action), pose_index, dtype=np.int32),
        "action": action.astype(np.int32),
        "next_pose": target.astype(np.int32),
        "probability": probabilities[action, target],
    }


def _concat(parts: list[dict[str, Any]], schema: pa.Schema) -> pa.Table:
    columns = {}
    for f in schema:
        pieces = [pa.array(part[f.name], type=f.type) if not isinstance(part[f.name], pa.Array) else part[f.name]
                  for part in parts]
        columns[f.name] = pa.chunked_array(pieces, type=f.type).combine_chunks()
    return pa.Table.from_pydict(columns, schema=schema)


def _vector_or_none(vector) -> list[float | None]:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(vector, dtype=np.float64).reshape(3)]


def _pose_row(object_id: str, pose, equivalents, n_actions: int, n_ok: int, suction, values) -> dict[str, Any]:
    row = {
        "object_id": object_id,
        "pose": int(pose.index),
        "probability": float(pose.probability),
        "transform": np.asarray(pose.transform, dtype=np.float64).reshape(16).tolist(),
        **{f"down_{a}": float(x) for a, x in zip("xyz", np.asarray(pose.down).reshape(3))},
        "equivalent_transforms": np.asarray(equivalents, dtype=np.float64).reshape(-1, 16).tolist(),
        "height": float(pose.height),
        "com_height": float(pose.com_height),
        "n_base_edges": int(len(pose.base_edges)),
        "n_actions": n_actions,
        "n_ok_actions": n_ok,
        "v_s": float(suction.quality),
        **{f"grasp_point_{a}": x for a, x in zip("xyz", _vector_or_none(suction.point))},
        **{f"grasp_axis_{a}": x for a, x in zip("xyz", _vector_or_none(suction.axis))},
        "v_t": float(values.value),
        "v_failed": float(values.failed_value),
    }
    for policy in POLICIES:
        choice = values.policies[policy]
        row[f"{policy}_action"] = int(choice.action)
        row[f"{policy}_value"] = float(choice.value)
    return row


def _object_row(spec: ObjectSpec, result: ObjectResult) -> dict[str, Any]:
    return {
        "object_id": spec.object_id,
        "source": spec.source,
        "sha256": spec.sha256,
        "mass": float(result.mass),
        "scale": float(spec.scale),
        **{f"com_{a}": float(x) for a, x in zip("xyz", np.asarray(result.center_mass).reshape(3))},
        "n_poses": len(result.poses),
        "n_hull_vertices": int(len(result.hull_vertices)),
        "n_faces": int(len(result.hull_faces)),
        "hull_vertices": np.asarray(result.hull_vertices, dtype=np.float64).reshape(-1, 3).tolist(),
        "repairs": [str(r) for r in result.repairs],
    }
