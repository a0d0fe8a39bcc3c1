"""One object's shard: its rows of every table and its HDF5 file, written atomically.

``build_shard`` turns an ``ObjectResult`` into Arrow tables and arrays (in the
worker, so the parent only writes).  ``write_shard`` writes each file under a
temporary name, reads it back, renames it into place, and writes the completion
record, with the SHA-256 of every file, last.  A process killed at any point
leaves either a complete shard or one without a record, which the next run
redoes.  File locations are in ``schema.layout``, columns in ``schema.tables``,
the HDF5 layout in ``schema.hdf5``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema import hdf5, layout, tables
from schema.version import SCHEMA_VERSION

from .config import Config
from .corpus import ObjectSpec, file_sha256
from .results import STATUS_NAMES, STATUS_OK, ObjectResult

PARQUET_COMPRESSION = "zstd"
HDF5_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
COMPRESS_ABOVE_BYTES = 16 * 1024
"""Smaller HDF5 arrays are stored contiguous: compression would only add overhead."""


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


# --- ObjectResult -> tables and arrays ------------------------------------------------------


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
        missing = set(tables.POLICIES) - set(values.policies)
        if missing:
            raise ShardError(f"{where}: no choice of policy {sorted(missing)}")

        ok = np.asarray(actions.status) == STATUS_OK
        action_parts.append(_action_columns(i, actions, topple, values))
        transition_parts.append(_transition_columns(i, topple.next_pose, ok))
        pose_rows.append(_pose_row(spec.object_id, pose, len(actions.status), int(ok.sum()), suction, values))
        pose_arrays.append(
            {
                "transform": pose.transform,
                "down": pose.down,
                "base_edges": np.asarray(pose.base_edges).reshape(-1, 2, 3),
                "edge_final_pose": pose.edge_final_pose,
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


def _action_columns(pose_index: int, actions, topple, values) -> dict[str, Any]:
    n = len(actions.status)
    status = np.asarray(actions.status)
    if n and (status.min() < 0 or status.max() >= len(STATUS_NAMES)):
        raise ShardError(f"pose {pose_index}: unknown action status code {int(status.max())}")
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


def _pose_row(object_id: str, pose, n_actions: int, n_ok: int, suction, values) -> dict[str, Any]:
    row = {
        "object_id": object_id,
        "pose": int(pose.index),
        "probability": float(pose.probability),
        "transform": np.asarray(pose.transform, dtype=np.float64).reshape(16).tolist(),
        **{f"down_{a}": float(x) for a, x in zip("xyz", np.asarray(pose.down).reshape(3))},
        "height": float(pose.height),
        "com_height": float(pose.com_height),
        "n_base_edges": int(len(pose.base_edges)),
        "n_actions": n_actions,
        "n_ok_actions": n_ok,
        "v_s": float(suction.quality),
        **{f"grasp_point_{a}": x for a, x in zip("xyz", _vector_or_none(suction.point))},
        **{f"grasp_axis_{a}": x for a, x in zip("xyz", _vector_or_none(suction.axis))},
        "v_t": float(values.value),
    }
    for policy in tables.POLICIES:
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
        "repairs": [str(r) for r in result.repairs],
    }


# --- identity of a shard's inputs ---------------------------------------------------------


def shard_inputs(spec: ObjectSpec, config: Config) -> dict[str, Any]:
    """Everything that determines a shard's content: schema version, every parameter,
    and the object (mesh checksum, scale, mass, id, source).  The mesh's location is
    left out: the same file elsewhere gives the same shard."""
    identity = {k: v for k, v in dataclasses.asdict(spec).items() if k != "path"}
    return {"schema_version": SCHEMA_VERSION, "config": config.to_dict(), "object": identity}


def fingerprint(inputs: dict[str, Any]) -> str:
    """SHA-256 of ``shard_inputs``: equal fingerprints, equal shards."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def input_differences(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """What changed between two ``shard_inputs``, as ``key: old -> new`` lines."""
    lines = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            lines += input_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            lines.append(f"{prefix}{key}: {_short(a)} -> {_short(b)}")
    return lines


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


# --- writing --------------------------------------------------------------------------------


def write_shard(root: str | Path, shard: ShardData, inputs: dict[str, Any]) -> dict:
    """Write one shard atomically; return its completion record.

    The old record goes first, so from then until the new record is in place the
    shard reads as incomplete; each file is written to a temporary name, read back
    and renamed; the record (files with SHA-256, counts, timings) is written last.
    """
    root = Path(root)
    started = time.process_time()
    object_id = layout.check_object_id(shard.object_id)
    record_path = root / layout.completion_record(object_id)
    record_path.unlink(missing_ok=True)

    files = {}
    for table in tables.PARTITIONED:
        relative = layout.partition_file(table, object_id)
        files[relative] = write_atomic(root / relative, _parquet_writer(shard.rows[table]), _parquet_reader(shard.rows[table]))
    for table in ("objects", "poses"):
        relative = layout.shard_rows_file(table, object_id)
        files[relative] = write_atomic(root / relative, _parquet_writer(shard.rows[table]), _parquet_reader(shard.rows[table]))
    relative = layout.arrays_file(object_id)
    files[relative] = write_atomic(root / relative, lambda path: _write_hdf5(path, shard), lambda path: _check_hdf5(path, shard))

    timings = dict(shard.timings)
    timings["write"] = time.process_time() - started
    record = {
        "object_id": object_id,
        "schema_version": SCHEMA_VERSION,
        "fingerprint": fingerprint(inputs),
        "files": files,
        "counts": shard.counts,
        "timings": timings,
        "inputs": inputs,
    }
    text = json.dumps(record, indent=1, sort_keys=True)
    write_atomic(record_path, lambda path: Path(path).write_text(text))
    return record


def write_atomic(path: Path, write: Callable[[Path], None], check: Callable[[Path], None] | None = None) -> str:
    """Write via ``write(temp)``, ``check(temp)`` it (read back), flush it to disk, rename it to
    ``path``; return its SHA-256.  The temp file is removed if anything fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}{layout.TEMP_SUFFIX}")
    try:
        write(temp)
        if check is not None:
            check(temp)
        with open(temp, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
            os.fsync(f.fileno())
        os.replace(temp, path)
    finally:
        temp.unlink(missing_ok=True)
    return digest


def _parquet_writer(table: pa.Table) -> Callable[[Path], None]:
    return lambda path: pq.write_table(table, path, compression=PARQUET_COMPRESSION)


def _parquet_reader(table: pa.Table) -> Callable[[Path], None]:
    def check(path: Path) -> None:
        stored = pq.read_metadata(path)
        if stored.num_rows != table.num_rows:
            raise OSError(f"{path}: read back {stored.num_rows} rows, wrote {table.num_rows}")

    return check


def _write_hdf5(path: Path, shard: ShardData) -> None:
    with h5py.File(path, "w") as f:
        for name, value in shard.attributes.items():
            f.attrs[name] = value
        for spec in hdf5.OBJECT_ARRAYS:
            _dataset(f, spec.name, shard.object_arrays[spec.name], spec.dtype)
        for pose, arrays in enumerate(shard.pose_arrays):
            for spec in hdf5.POSE_ARRAYS:
                _dataset(f, f"{hdf5.pose_group(pose)}/{spec.name}", arrays[spec.name], spec.dtype)


def _dataset(f: h5py.File, name: str, values, dtype: np.dtype) -> None:
    array = np.ascontiguousarray(np.asarray(values).astype(dtype, copy=False))
    options = HDF5_COMPRESSION if array.nbytes > COMPRESS_ABOVE_BYTES else {}
    f.create_dataset(name, data=array, **options)


def _check_hdf5(path: Path, shard: ShardData) -> None:
    with h5py.File(path, "r") as f:
        problems = hdf5.check_file(f, _expected_attributes(shard.attributes, shard.rows["poses"]))
    if problems:
        raise ShardError(f"{shard.object_id}: HDF5 does not match its layout: {problems[0]}")


def _expected_attributes(attributes: dict, poses: pa.Table) -> dict:
    expected = {k: attributes[k] for k in ("schema_version", "object_id", "n_poses", "n_trials")}
    expected["A"] = poses.column("n_actions").to_pylist()
    return expected


# --- reading and checking -------------------------------------------------------------------


def read_record(root: str | Path, object_id: str) -> dict | None:
    """The shard's completion record, or None when absent or unreadable."""
    try:
        return json.loads((Path(root) / layout.completion_record(object_id)).read_text())
    except (OSError, ValueError):
        return None


def checksum_problems(root: str | Path, record: dict) -> list[str]:
    """Files of a record that are missing or whose SHA-256 differs."""
    problems = []
    for relative, expected in record.get("files", {}).items():
        actual = file_sha256(Path(root) / relative)
        if not actual:
            problems.append(f"{relative}: missing")
        elif actual != expected:
            problems.append(f"{relative}: sha256 {actual[:12]}... differs from the record's {expected[:12]}...")
    return problems


def is_complete(root: str | Path, object_id: str, shard_fingerprint: str) -> dict | None:
    """The record of a complete, verified shard made from the same inputs, else None."""
    record = read_record(root, object_id)
    if record is None or record.get("fingerprint") != shard_fingerprint:
        return None
    if record.get("schema_version") != SCHEMA_VERSION or checksum_problems(root, record):
        return None
    return record


def content_problems(root: str | Path, record: dict) -> list[str]:
    """Deep check of a shard: Parquet schemas and row counts, HDF5 layout (after checksums)."""
    root = Path(root)
    object_id = record["object_id"]
    counts = record.get("counts", {})
    problems = []
    expected_rows = {
        layout.partition_file("actions", object_id): (tables.file_schema(tables.ACTIONS), counts.get("actions")),
        layout.partition_file("transitions", object_id): (tables.file_schema(tables.TRANSITIONS), counts.get("transitions")),
        layout.shard_rows_file("objects", object_id): (tables.OBJECTS, 1),
        layout.shard_rows_file("poses", object_id): (tables.POSES, counts.get("poses")),
    }
    for relative, (schema, rows) in expected_rows.items():
        problems += parquet_problems(root / relative, relative, schema, rows)
    if problems:
        return problems
    poses = pq.read_table(root / layout.shard_rows_file("poses", object_id))
    relative = layout.arrays_file(object_id)
    try:
        with h5py.File(root / relative, "r") as f:
            expected = {
                "schema_version": SCHEMA_VERSION,
                "object_id": object_id,
                "n_poses": counts.get("poses"),
                "A": poses.column("n_actions").to_pylist(),
            }
            problems += [f"{relative}: {p}" for p in hdf5.check_file(f, expected)]
    except OSError as err:
        problems.append(f"{relative}: not a readable HDF5 file ({err})")
    return problems


def parquet_problems(path: Path, name: str, schema: pa.Schema, rows: int | None) -> list[str]:
    """A Parquet file that is unreadable, has another schema, or another row count."""
    try:
        stored = pq.read_schema(path)
        n_rows = pq.read_metadata(path).num_rows
    except (OSError, pa.ArrowException) as err:
        return [f"{name}: not a readable Parquet file ({' '.join(str(err).split())[:120]})"]
    if not stored.equals(schema, check_metadata=False):
        return [f"{name}: schema differs from schema.tables (columns {stored.names})"]
    if rows is not None and n_rows != rows:
        return [f"{name}: {n_rows} rows, the manifest says {rows}"]
    return []


def remove_temp_files(root: str | Path) -> int:
    """Delete temporary files left by a killed run; return how many."""
    removed = 0
    for path in Path(root).rglob(f".*{layout.TEMP_SUFFIX}"):
        path.unlink(missing_ok=True)
        removed += 1
    return removed
