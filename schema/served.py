"""The served tables: the dataset laid out as the service reads it, memory-mapped.

The Parquet tables are for analysts (compressed, nulls, one partition per object).  A
server process instead wants every array it answers from ready in memory at once, and
several workers on one machine want to share one copy.  So the pipeline also writes
``served/*.arrow``: Arrow IPC files, uncompressed, one record batch each, which
``read_served`` maps into memory without decoding anything (``pyarrow.memory_map``):
start-up takes milliseconds, and the pages are the operating system's file cache,
shared by every worker and loaded only where requests touch them.

Rows are in corpus order (objects), then pose, then action, so each object's rows are
one contiguous slice (the ``objects`` table's ``*_start`` and ``n_*`` columns).  Missing
values are NaN (never nulls: a column with a validity bitmap cannot be viewed as numpy
without a copy).  Vectors are fixed-size lists: ``(n, 3)`` or ``(n, 16)`` views.

=============  =====================================================================
table          one row per
=============  =====================================================================
objects        object: id, source, sha256, mass, scale, com (3), and where its rows
               start in the other tables (``pose_start``, ``action_start``,
               ``transition_start``, ``match_start``, ``hull_start``) with their counts
poses          stable pose: probability, transform (16), down (3), height, com_height,
               v_s, v_t, grasp_point (3), grasp_axis (3), n_actions, n_ok_actions,
               ``action_start`` (object-local), ``<policy>_action``, ``<policy>_value``
               and ``<policy>_p_topple_neighbourhood`` (``schema.neighbourhood``: the
               mean P(topple) around the policy's push, NaN when it does not push)
matches        orientation that is a pose (``poses.equivalent_transforms``): pose
               (object-local), down (3), transform (16), inverse (16)
actions        candidate push: status (int8, index into ``STATUS_NAMES``), is_max_height
               (int8), p_topple, mean_force (float32), q, greedy (float64), point,
               normal, direction (3 x float32), ``transition_start`` (object-local)
transitions    nonzero P(next | pose, action): next_pose (int32), probability (float32)
hulls          convex hull vertex, object frame: vertex (3), m
=============  =====================================================================

float32 where the model has no more precision (geometry: the contact noise alone is
0.5 mm; probabilities); float64 for ``q`` and ``greedy`` so that ranking them agrees
with the pipeline's.  ``served_tables`` builds them from the Parquet tables (the
pipeline, and the service when a dataset has no served files), checking as it goes
that the tables fit together; the manifest records each file's SHA-256 and rows, and
``read_current`` checks both as it maps them.
"""

from __future__ import annotations

import hashlib
import mmap
from pathlib import Path

import numpy as np
import pyarrow as pa

from schema.neighbourhood import chosen_means
from schema.vocabulary import POLICIES, STATUS_NAMES

SERVED_DIR = "served"
NAMES = ("objects", "poses", "matches", "actions", "transitions", "hulls")
FILES = {name: f"{SERVED_DIR}/{name}.arrow" for name in NAMES}
"""Table name -> path relative to the dataset root."""


class ServedError(ValueError):
    """The tables do not fit together, or a served file is missing or not what the manifest says."""


def _vec(size: int, value: pa.DataType | None = None) -> pa.DataType:
    """A fixed-size list of ``size`` values (float64 unless given)."""
    return pa.list_(value or pa.float64(), size)


SCHEMAS = {
    "objects": pa.schema([
        ("object_id", pa.string()), ("source", pa.string()), ("sha256", pa.string()),
        ("mass", pa.float64()), ("scale", pa.float64()), ("com", _vec(3)),
        ("pose_start", pa.int64()), ("n_poses", pa.int64()),
        ("action_start", pa.int64()), ("n_actions", pa.int64()),
        ("transition_start", pa.int64()), ("n_transitions", pa.int64()),
        ("match_start", pa.int64()), ("n_matches", pa.int64()),
        ("hull_start", pa.int64()), ("n_hull_vertices", pa.int64()),
    ]),
    "poses": pa.schema([
        ("probability", pa.float64()), ("transform", _vec(16)), ("down", _vec(3)),
        ("height", pa.float64()), ("com_height", pa.float64()), ("v_s", pa.float64()), ("v_t", pa.float64()),
        ("grasp_point", _vec(3)), ("grasp_axis", _vec(3)),
        ("n_actions", pa.int32()), ("n_ok_actions", pa.int32()), ("action_start", pa.int64()),
        *[(f"{p}_{kind}", t) for p in POLICIES for kind, t in (("action", pa.int32()), ("value", pa.float64()))],
        *[(f"{p}_p_topple_neighbourhood", pa.float64()) for p in POLICIES],
    ]),
    "matches": pa.schema([("pose", pa.int32()), ("down", _vec(3)), ("transform", _vec(16)), ("inverse", _vec(16))]),
    "actions": pa.schema([
        ("status", pa.int8()), ("is_max_height", pa.int8()), ("p_topple", pa.float32()), ("mean_force", pa.float32()),
        ("q", pa.float64()), ("greedy", pa.float64()),
        ("point", _vec(3, pa.float32())), ("normal", _vec(3, pa.float32())), ("direction", _vec(3, pa.float32())),
        ("transition_start", pa.int64()),
    ]),
    "transitions": pa.schema([("next_pose", pa.int32()), ("probability", pa.float32())]),
    "hulls": pa.schema([("vertex", _vec(3))]),
}

ACTION_COLUMNS = [
    "pose", "action", "status", "is_max_height", "p_topple", "mean_force", "q", "greedy",
    *(f"{v}_{a}" for v in ("point", "normal", "direction") for a in "xyz"),
]
TRANSITION_COLUMNS = ["pose", "action", "next_pose", "probability"]
DOWN = np.array([0.0, 0.0, -1.0])


# --- reading --------------------------------------------------------------------------------


def read_served(root: str | Path, checksums: dict[str, str] | None = None,
                mapped: dict[str, tuple[mmap.mmap, str]] | None = None) -> dict[str, pa.Table]:
    """Every served table of the dataset at ``root``, memory-mapped (no copy, no decoding).

    checksums : table name -> the hex SHA-256 its file must have; a file not in ``mapped`` is
      then read through once and hashed, and mapped from the same open file, so the bytes
      checked are the file served
    mapped : table name -> (read-only mapping of its file, SHA-256 of its bytes): files the caller
      mapped and hashed already (``service.prefetch``, while the service imports)

    ServedError when a file is missing, unreadable or not the recorded bytes (the caller falls
    back to the Parquet tables, or rebuilds)."""
    out = {}
    for name, relative in FILES.items():
        path = Path(root) / relative
        try:
            if (mapped is None or name not in mapped) and path.exists() and not path.is_file():
                raise ServedError(f"{path}: not a regular file")  # opening a named pipe would wait for a writer
        except OSError as err:  # served/ this user may not enter (Python 3.11's exists raises there)
            raise ServedError(f"{path}: unreadable: {err.strerror or err}") from None
        try:
            if mapped is not None and name in mapped:
                view, actual = mapped[name]
            else:
                with open(path, "rb") as f:
                    actual = hashlib.file_digest(f, "sha256").hexdigest() if checksums is not None else None
                    view = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # outlives the descriptor
            table = pa.ipc.open_file(pa.py_buffer(view)).read_all()
        except FileNotFoundError:
            raise ServedError(f"{path}: missing") from None
        except (OSError, ValueError, pa.ArrowException) as err:  # ValueError: mmap of an empty file
            raise ServedError(f"{path}: unreadable: {' '.join(str(err).split())[:200]}") from None
        if checksums is not None and actual != checksums[name]:
            # Damaged after the build (a disk, a copy, a hand): an Arrow file has no checksums of its own.
            raise ServedError(f"{relative}: sha256 {actual[:12]}... differs from the manifest's {checksums[name][:12]}... "
                              "(changed after the build; a rerun of the build rewrites it)")
        if not table.schema.equals(SCHEMAS[name]):
            raise ServedError(f"{path}: not the served {name} table of this code (schema differs)")
        out[name] = table
    return out


def read_current(root: str | Path, manifest, verify: bool = True,
                 mapped: dict[str, tuple[mmap.mmap, str]] | None = None) -> dict[str, pa.Table]:
    """``read_served``, and ServedError unless they are the files this manifest's build wrote
    (each recorded, with the recorded rows, and with ``verify`` the recorded SHA-256).

    manifest : ``schema.manifest.Manifest`` of ``root``
    verify : check every file's SHA-256 (about 0.1 s for the default dataset from the file cache,
      0.5 s from disk); off only where the caller checks the bytes itself.  A file written into
      after the load is not seen: a rebuild replaces files (``pipeline.build.atomic``), it never
      writes into them
    mapped : as ``read_served``'s, files mapped and hashed already
    """
    entries = {name: manifest.tables.get(relative) for name, relative in FILES.items()}
    for name, entry in entries.items():
        if entry is None:
            raise ServedError(f"manifest.json records no {FILES[name]} (built by an older toppledb)")
    tables = read_served(root, {name: entry.sha256 for name, entry in entries.items()} if verify else None, mapped)
    for name, relative in FILES.items():
        if entries[name].rows != tables[name].num_rows:
            raise ServedError(f"{relative} holds {tables[name].num_rows} rows, manifest.json says {entries[name].rows}")
    return tables


def column(table: pa.Table, name: str) -> np.ndarray:
    """A served column as a read-only numpy view of its buffer: (n,) for scalars, (n, k)
    for fixed-size lists.  (``np.frombuffer``: pyarrow's ``to_numpy`` imports pandas, a
    second or so of a server's start-up.)"""
    chunked = table.column(name)
    array = chunked.chunk(0) if chunked.num_chunks == 1 else chunked.combine_chunks()
    size = 1
    if pa.types.is_fixed_size_list(array.type):
        size = array.type.list_size
        offset, length, array = array.offset * size, len(array) * size, array.values
    else:
        offset, length = 0, len(array)
    if array.null_count:
        raise ServedError(f"served column {name} has nulls (served tables use NaN)")
    dtype = np.dtype(array.type.to_pandas_dtype()) if not pa.types.is_boolean(array.type) else None
    if dtype is None:
        raise ServedError(f"served column {name}: bit-packed booleans cannot be viewed; the served tables use int8")
    values = np.frombuffer(array.buffers()[1], dtype=dtype, count=array.offset + offset + length)[array.offset + offset:]
    return values.reshape(-1, size) if size > 1 else values


# --- writing --------------------------------------------------------------------------------


def write_table(path: Path, table: pa.Table) -> None:
    """One served table as an uncompressed Arrow IPC file of one record batch."""
    with pa.OSFile(str(path), "wb") as sink, pa.ipc.new_file(sink, table.schema) as writer:
        writer.write_table(table.combine_chunks(), max_chunksize=max(table.num_rows, 1))


def _fixed(values: np.ndarray, dtype=np.float64) -> pa.Array:
    values = np.ascontiguousarray(values, dtype=dtype)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def _nan(column_: pa.ChunkedArray | pa.Array, dtype) -> np.ndarray:
    """A numeric column as numpy with nulls as NaN."""
    import pyarrow.compute as pc  # here: a server that maps served files never needs it (80 ms of start-up)

    return column_.to_numpy(zero_copy_only=False).astype(dtype, copy=False) if column_.null_count == 0 else \
        pc.fill_null(column_.cast(pa.float64()), np.nan).to_numpy(zero_copy_only=False).astype(dtype)


def _xyz(table: pa.Table, prefix: str, dtype=np.float64) -> np.ndarray:
    return np.stack([_nan(table.column(f"{prefix}_{a}"), dtype) for a in "xyz"], axis=1)


def _matrices(column_: pa.ChunkedArray) -> np.ndarray:
    """A fixed-size-list<16> column as (n, 4, 4)."""
    return column_.combine_chunks().flatten().to_numpy().astype(np.float64).reshape(-1, 4, 4)


def served_tables(objects: pa.Table, poses: pa.Table, actions: list[pa.Table], transitions: list[pa.Table]) -> dict[str, pa.Table]:
    """The served tables from the Parquet ones.

    objects, poses : the consolidated tables (``schema.tables`` OBJECTS, POSES)
    actions, transitions : per object, in ``objects`` order, its partition's rows
      (columns ``ACTION_COLUMNS`` / ``TRANSITION_COLUMNS`` at least)
    Raises ServedError when they do not fit together (rows missing, out of order, unknown
    status, transitions to poses or actions that do not exist).
    """
    given = objects.select(["object_id", "source", "sha256", "mass", "scale", "com_x", "com_y", "com_z", "n_poses",
                            "hull_vertices"]).to_pylist()
    if len(actions) != len(given) or len(transitions) != len(given):
        raise ServedError(f"{len(given)} objects but {len(actions)} action and {len(transitions)} transition tables")
    pose_rows: dict[str, list[int]] = {}
    for index, object_id in enumerate(poses.column("object_id").to_pylist()):
        pose_rows.setdefault(object_id, []).append(index)

    parts: dict[str, list[dict]] = {name: [] for name in NAMES if name != "objects"}
    starts = {name: 0 for name in parts}
    object_rows = []
    for i, obj in enumerate(given):
        object_id = obj["object_id"]
        own = _object_poses(object_id, int(obj["n_poses"]), poses, pose_rows.get(object_id, []))
        pose_columns = _pose_columns(own)
        part = {
            "poses": pose_columns,
            "matches": _match_columns(object_id, own),
            **_action_and_transition_columns(object_id, pose_columns["n_actions"], actions[i], transitions[i]),
            "hulls": {"vertex": np.asarray(obj["hull_vertices"], dtype=np.float64).reshape(-1, 3)},
        }
        part["poses"].update(_chosen_neighbourhood(part["poses"], part["actions"]))
        row = {key: obj[key] for key in ("object_id", "source", "sha256", "mass", "scale")}
        row["com"] = [obj[f"com_{a}"] for a in "xyz"]
        for name, columns in part.items():
            parts[name].append(columns)
            rows = len(next(iter(columns.values())))
            row[f"{_SINGULAR[name]}_start"], row[f"n_{_COUNTED[name]}"] = starts[name], rows
            starts[name] += rows
        object_rows.append(row)

    out = {"objects": pa.Table.from_pylist(object_rows, schema=SCHEMAS["objects"])}
    for name, chunks in parts.items():
        arrays = []
        for field in SCHEMAS[name]:
            fixed = pa.types.is_fixed_size_list(field.type)
            values = np.concatenate([c[field.name] for c in chunks]) if chunks else np.zeros(
                (0, field.type.list_size) if fixed else 0)
            arrays.append(_fixed(values, field.type.value_type.to_pandas_dtype()) if fixed
                          else pa.array(np.asarray(values, dtype=field.type.to_pandas_dtype())))
        out[name] = pa.Table.from_arrays(arrays, schema=SCHEMAS[name])
    return out


_SINGULAR = {"poses": "pose", "matches": "match", "actions": "action", "transitions": "transition", "hulls": "hull"}
_COUNTED = {"poses": "poses", "matches": "matches", "actions": "actions", "transitions": "transitions", "hulls": "hull_vertices"}
"""Per served table, the names of its ``<x>_start`` and ``n_<y>`` columns in ``objects``."""


def _object_poses(object_id: str, n_poses: int, poses: pa.Table, rows: list[int]) -> pa.Table:
    """The object's rows of poses.parquet, by pose; ServedError unless they are 0..n_poses - 1."""
    own = poses.take(pa.array(rows, pa.int64())).sort_by("pose")
    if own.num_rows != n_poses or own.column("pose").to_pylist() != list(range(n_poses)):
        raise ServedError(f"{object_id}: poses.parquet holds poses {own.column('pose').to_pylist()}, expected 0..{n_poses - 1}")
    return own


def _chosen_neighbourhood(pose_columns: dict[str, np.ndarray], action_columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per policy, (P,) float: the mean P(topple) around each pose's chosen push
    (``schema.neighbourhood``, from the served float32 values), NaN where it does not push.
    Computed here once so that /plan reads one number instead of scanning ~1,000 candidates."""
    chosen = np.stack([pose_columns[f"{policy}_action"] for policy in POLICIES], axis=1)  # (P, policies)
    offsets = np.concatenate([[0], np.cumsum(pose_columns["n_actions"], dtype=np.int64)])
    means = chosen_means(offsets, action_columns["point"], action_columns["direction"], action_columns["p_topple"], chosen)
    return {f"{policy}_p_topple_neighbourhood": means[:, i] for i, policy in enumerate(POLICIES)}


def _pose_columns(own: pa.Table) -> dict[str, np.ndarray]:
    transforms = _matrices(own.column("transform"))
    n_actions = own.column("n_actions").to_numpy().astype(np.int64)
    return {
        "probability": _nan(own.column("probability"), np.float64),
        "transform": transforms.reshape(-1, 16),
        "down": _xyz(own, "down"),
        **{name: _nan(own.column(name), np.float64) for name in ("height", "com_height", "v_s", "v_t")},
        "grasp_point": _xyz(own, "grasp_point"),
        "grasp_axis": _xyz(own, "grasp_axis"),
        "n_actions": n_actions.astype(np.int32),
        "n_ok_actions": own.column("n_ok_actions").to_numpy().astype(np.int32),
        "action_start": np.concatenate([[0], np.cumsum(n_actions)[:-1]]).astype(np.int64),
        **{f"{p}_action": own.column(f"{p}_action").to_numpy().astype(np.int32) for p in POLICIES},
        **{f"{p}_value": _nan(own.column(f"{p}_value"), np.float64) for p in POLICIES},
    }


def _match_columns(object_id: str, own: pa.Table) -> dict[str, np.ndarray]:
    """Every orientation that is a pose (``equivalent_transforms``, the pose's own first)."""
    equivalents = [np.asarray(e, dtype=np.float64).reshape(-1, 4, 4) for e in own.column("equivalent_transforms").to_pylist()]
    if any(len(e) == 0 for e in equivalents):
        raise ServedError(f"{object_id}: a pose without equivalent_transforms (its own transform comes first)")
    transforms = np.concatenate(equivalents)
    return {
        "pose": np.concatenate([np.full(len(e), p, dtype=np.int32) for p, e in enumerate(equivalents)]),
        "down": np.einsum("mji,j->mi", transforms[:, :3, :3], DOWN),
        "transform": transforms.reshape(-1, 16),
        "inverse": np.linalg.inv(transforms).reshape(-1, 16),
    }


def _action_and_transition_columns(object_id: str, n_actions: np.ndarray, actions: pa.Table, transitions: pa.Table) -> dict[str, dict]:
    """The object's actions in (pose, action) order and its transitions as CSR over them;
    ServedError when they do not fit its poses (``n_actions`` per pose)."""
    import pyarrow.compute as pc  # here: a server that maps served files never needs it

    n_poses = len(n_actions)
    action_start = np.concatenate([[0], np.cumsum(n_actions, dtype=np.int64)])

    actions = actions.sort_by([("pose", "ascending"), ("action", "ascending")])
    pose_of = actions.column("pose").to_numpy()
    expected_action = np.arange(len(pose_of)) - action_start[np.clip(pose_of, 0, n_poses - 1)]
    if len(pose_of) != action_start[-1] or not np.array_equal(actions.column("action").to_numpy(), expected_action):
        raise ServedError(f"{object_id}: the actions partition does not hold actions 0..n_actions - 1 of every pose")
    status = pc.index_in(actions.column("status"), value_set=pa.array(STATUS_NAMES))
    if status.null_count:
        raise ServedError(f"{object_id}: unknown action status; known: {', '.join(STATUS_NAMES)}")

    transitions = transitions.sort_by([("pose", "ascending"), ("action", "ascending"), ("next_pose", "ascending")])
    t_pose = transitions.column("pose").to_numpy().astype(np.int64)
    t_action = transitions.column("action").to_numpy().astype(np.int64)
    next_pose = transitions.column("next_pose").to_numpy().astype(np.int32)
    if len(t_pose) and (
        t_pose.min() < 0 or t_pose.max() >= n_poses or next_pose.min() < 0 or next_pose.max() >= n_poses
        or (t_action < 0).any() or (t_action >= n_actions[t_pose]).any()
    ):
        raise ServedError(f"{object_id}: transitions refer to poses or actions that do not exist")
    per_action = np.bincount(action_start[t_pose] + t_action, minlength=int(action_start[-1]))
    return {
        "actions": {
            "status": status.to_numpy(zero_copy_only=False).astype(np.int8),
            "is_max_height": actions.column("is_max_height").to_numpy(zero_copy_only=False).astype(np.int8),
            "p_topple": _nan(actions.column("p_topple"), np.float32),
            "mean_force": _nan(actions.column("mean_force"), np.float32),
            "q": _nan(actions.column("q"), np.float64),
            "greedy": _nan(actions.column("greedy"), np.float64),
            **{v: _xyz(actions, v, np.float32) for v in ("point", "normal", "direction")},
            "transition_start": np.concatenate([[0], np.cumsum(per_action)[:-1]]).astype(np.int64),
        },
        "transitions": {"next_pose": next_pose, "probability": _nan(transitions.column("probability"), np.float32)},
    }


def served_from_parquet(dataset) -> dict[str, pa.Table]:
    """``served_tables`` of a finished dataset read through ``schema.reader.Dataset``."""
    objects = dataset.table("objects")
    ids = objects.column("object_id").to_pylist()
    return served_tables(
        objects,
        dataset.table("poses"),
        [dataset.object_rows("actions", i, ACTION_COLUMNS) for i in ids],
        [dataset.object_rows("transitions", i, TRANSITION_COLUMNS) for i in ids],
    )
