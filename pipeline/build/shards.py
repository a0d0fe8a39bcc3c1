"""One object's shard on disk: its rows of every table and its HDF5 file, written
atomically, and the checks that tell a complete shard from an unfinished one.

``write_shard`` writes each file of a ``ShardData`` (``pipeline.build.rows``) under
a temporary name, reads it back, renames it into place, and writes the completion
record, with the SHA-256 of every file, last.  A process killed at any point
leaves either a complete shard or one without a record, which the next run
redoes.  File locations are in ``schema.layout``, columns in ``schema.tables``,
the HDF5 layout in ``schema.hdf5``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema import hdf5, layout, tables
from schema.version import SCHEMA_VERSION

from ..model.boosted_map import load_trees
from ..model.config import Config
from ..model.topple import ENGINE_REVISION
from .atomic import file_sha256, write_atomic, write_text_atomic
from .corpus import ObjectSpec
from .rows import ShardData, ShardError

PARQUET_COMPRESSION = "zstd"
HDF5_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
COMPRESS_ABOVE_BYTES = 16 * 1024
"""Smaller HDF5 arrays are stored contiguous: compression would only add overhead."""


# --- identity of a shard's inputs ---------------------------------------------------------


SERVING_ONLY = {"mdp": ("after_failure_power", "believe_failures")}
"""Parameters the build does not use, which the manifest carries for the service (section ->
keys): they are no part of a shard's identity, so a new value asks for no rebuild and a dataset
built before one existed can still be added to.  Both are used only by a build whose value
iteration believes failures with a map (``mdp.believe_failures`` and k != 1, docs/MODEL.md
(12.13)); any other build's shards keep the identity they had before the two existed."""


BUDGET_ONLY = {"mdp": ("budget_min_direction_z",)}
"""Parameters only the served budgets read (``pushes_left``, solved by the service from the tables): never
part of a shard's identity, so a dataset built before one existed keeps its shards and a new value only
rewrites the manifest."""


UNUSED_WHEN_OFF = {
    "landing_spread": ("landing_spread", "landing_spread_poses"),
    "landing_onward": ("landing_onward", "landing_onward_below"),
    "boosted_map": ("boosted_map",),
}
"""``topple`` parameters of a correction or map that, switched off (its ``topple.applied_*`` 0 or empty,
which the thesis's variants always are), change no shard (correction or map -> keys): left out of a shard's
identity then, so the shards of a dataset built before they existed keep theirs (docs/MODEL.md
C.17, C.18, C.19)."""

NEIGHBOURHOOD_CHOICE = {"mdp": ("choice_radius", "choice_angle", "choice_neighbours")}
"""Value iteration's choice by neighbourhood (docs/MODEL.md (12.15)), which its argmax (``mdp.choice_radius``
0, the thesis) does not read: left out of a shard's identity then, so a dataset of the argmax built before
they existed keeps its shards."""


REPEAT_CHOICE = {"mdp": ("choose_for_repeats", "repeats_then_grasp")}
"""The stored push chosen for the client that repeats it (docs/MODEL.md (12.16), (12.17); opt-in): left out of a
shard's identity while ``choose_for_repeats`` is off, so a dataset built before the fields existed keeps its shards."""


def unused_by_shards(config: Config) -> dict[str, tuple[str, ...]]:
    """The parameters this configuration's shards do not depend on (section -> keys):
    ``BUDGET_ONLY``, ``SERVING_ONLY`` unless the build plans with failures, ``REPEAT_CHOICE`` while it is off,
    ``NEIGHBOURHOOD_CHOICE`` under the argmax, and those of each landing correction that is off."""
    unused = {} if config.mdp.plans_with_failures else dict(SERVING_ONLY)
    unused["mdp"] = unused.get("mdp", ()) + BUDGET_ONLY["mdp"]
    if not config.mdp.choose_for_repeats:
        unused["mdp"] += REPEAT_CHOICE["mdp"]
    if config.mdp.choice_radius == 0:
        unused["mdp"] += NEIGHBOURHOOD_CHOICE["mdp"]
    off = tuple(key for name, keys in UNUSED_WHEN_OFF.items() if not getattr(config.topple, f"applied_{name}") for key in keys)
    if off:
        unused["topple"] = unused.get("topple", ()) + off
    return unused


def shard_inputs(spec: ObjectSpec, config: Config) -> dict[str, Any]:
    """Everything that determines a shard's content: schema version, every parameter the
    build uses (``unused_by_shards`` left out), and the object (mesh checksum, scale, mass, id,
    source), and the engine's revision, so that a shard of an engine that computed other numbers is not
    resumed.  The mesh's location is left out: the same file elsewhere gives the same shard."""
    identity = {k: v for k, v in dataclasses.asdict(spec).items() if k != "path"}
    parameters = config.to_dict()
    for section, keys in unused_by_shards(config).items():
        parameters[section] = {k: v for k, v in parameters[section].items() if k not in keys}
    inputs = {"schema_version": SCHEMA_VERSION, "engine_revision": ENGINE_REVISION, "config": parameters, "object": identity}
    files = parameter_files(config)
    if files:
        # The parameter names a file: its content, not its name or place, makes the shard (docs/MODEL.md C.19).
        parameters["topple"].pop("boosted_map")
        inputs["boosted_map_sha256"] = files["topple.boosted_map"]
    return inputs


def parameter_files(config: Config) -> dict[str, str]:
    """SHA-256 of the content of each file a parameter of ``config`` names and the build reads, by the
    parameter's dotted name (the boosted map's trees when applied; ``Manifest.parameter_files``)."""
    if not config.topple.applied_boosted_map:
        return {}
    return {"topple.boosted_map": load_trees(config.topple.applied_boosted_map).sha256}


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

    parquet = [(layout.partition_file(table, object_id), table) for table in tables.PARTITIONED]
    parquet += [(layout.shard_rows_file(table, object_id), table) for table in ("objects", "poses")]
    files = {}
    for relative, table in parquet:
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
    write_text_atomic(record_path, text)
    return record


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
    """The shard's completion record, or None when absent, unreadable or damaged (no
    fingerprint): such a shard is redone like one a killed run left without a record."""
    try:
        record = json.loads((Path(root) / layout.completion_record(object_id)).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and isinstance(record.get("fingerprint"), str) else None


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
