"""The push-outcome log: one row per executed push, simulated or real.

The same table serves pushes played in pybullet (``toppledb play``) and pushes
logged on a real robot, so a robot team can validate and calibrate toppledb
against its own finger and table (``toppledb report``, ``toppledb calibrate``).
A log is one or more Parquet files with this schema; docs/VALIDATION.md is the
contract for people.

Frames: "object" is the mesh's own frame after the corpus scale (metres), as in
the dataset.  Poses are 4x4 row-major transforms object -> world, world z up
with the table at z = 0.  The push is given in the object frame so that the row
does not depend on where the object stood on the table.

What identifies the object: ``object_id`` plus ``mesh_sha256`` (the file the
model reads), and ``mesh_path``, ``scale``, ``mass`` so that a log can be
re-evaluated without the dataset it came from (``mesh_path`` may be relative to
pybullet_data when ``mesh_source`` is ``pybullet_data``, like corpus lists).

Nothing is trusted: a reader checks every row (``row_problems``) and reports the
bad ones with a reason, never drops them silently.

A robot's own pushes: ``dataset_meshes`` names each object as the dataset's build read it,
``robot_row`` turns a ``/plan`` answer the robot executed, and the poses it observed before and
after, into a row, and ``write_log`` writes a session's rows as one log, checked and all or nothing.
"""

from __future__ import annotations

import json
import operator
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema.files import write_atomic
from schema.manifest import read_manifest
from schema.tables import column, xyz

PUSHLOG_VERSION = "1.0"

PUSHLOG = pa.schema(
    [
        column("object_id", pa.string(), "Object identifier (as in the corpus / dataset)"),
        column("mesh_sha256", pa.string(), "SHA-256 of the mesh file the object was loaded from"),
        column("mesh_source", pa.string(), "'pybullet_data' (mesh_path relative to it) or 'file' (absolute or log-relative path)"),
        column("mesh_path", pa.string(), "Mesh file, see mesh_source"),
        column("scale", pa.float64(), "Factor from mesh units to metres"),
        column("mass", pa.float64(), "Object mass", "kg"),
        column("push_id", pa.int64(), "Identifier of the push (the same for its repeats)"),
        column("repeat", pa.int32(), "Repeat index of this push (0, 1, ...)"),
        column("start_pose", pa.int32(), "Stable pose the object started in (model's pose index), if known", nullable=True),
        column("start_transform", pa.list_(pa.float64(), 16), "Object -> world at the start, 4x4 row-major"),
        *xyz("point", "Contact point the finger aims at, object frame", "m"),
        *xyz("direction", "Unit push direction, object frame"),
        column("action", pa.int32(), "Action id in the dataset's pose, when the push is one of its candidates", nullable=True),
        column("finger_speed", pa.float64(), "Finger speed along the push", "m/s"),
        column("approach_offset", pa.float64(), "The finger starts this far before the contact along the push", "m"),
        column("push_depth", pa.float64(), "The finger stops this far past the contact along the push", "m"),
        column("finger_radius", pa.float64(), "Radius of the finger tip", "m"),
        column("final_transform", pa.list_(pa.float64(), 16), "Object -> world once at rest, 4x4 row-major (observed)"),
        column("mu_table", pa.float64(), "Measured (or simulated) table friction coefficient", nullable=True),
        column("mu_finger", pa.float64(), "Measured (or simulated) finger friction coefficient", nullable=True),
        column("source", pa.string(), "Who executed it: 'pybullet', or 'robot:<name>'"),
        column("seed", pa.int64(), "Seed of the simulated noise draws, if simulated", nullable=True),
    ],
    metadata={"pushlog_version": PUSHLOG_VERSION},
)

RIGID_TOLERANCE = 1e-3
"""Largest |R^T R - I| entry and |det R - 1| accepted for a logged pose."""


def row_problems(table: pa.Table) -> list[str | None]:
    """Per row, why it cannot be used (None when it can): NaN or infinite numbers,
    poses that are not rigid transforms, zero push directions, non-positive mass or scale.

    Semantic checks that need the model (unknown object, changed mesh, a start pose
    that matches no stable pose) belong to the reader that loads the meshes.
    """
    n = table.num_rows
    problems: list[str | None] = [None] * n

    def flag(mask: np.ndarray, reason: str) -> None:
        for i in np.flatnonzero(mask):
            if problems[i] is None:
                problems[i] = reason

    for name in ("start_transform", "final_transform"):
        values = table.column(name).combine_chunks()
        matrices = np.asarray(values.flatten().to_numpy(zero_copy_only=False), dtype=float)
        if values.null_count or len(matrices) != 16 * n:
            # A row without a whole matrix is named; every other row is still checked (a null inside a
            # matrix reads as NaN, as it does on the fast path).
            cells = values.to_pylist()
            whole = np.array([cell is not None and len(cell) == 16 for cell in cells], dtype=bool)
            flag(~whole, f"{name} missing")
            matrices = np.array([[np.nan if v is None else v for v in cell] if ok else np.eye(4).ravel()
                                 for cell, ok in zip(cells, whole)], dtype=float)
        matrices = matrices.reshape(n, 4, 4)
        flag(~np.isfinite(matrices).all(axis=(1, 2)), f"{name} has NaN or infinite entries")
        flag(~rigid(matrices), f"{name} is not a rigid transform (rotation with det +1, last row 0 0 0 1)")
    for prefix in ("point", "direction"):
        vector = np.stack([table.column(f"{prefix}_{a}").to_numpy(zero_copy_only=False) for a in "xyz"], axis=1).astype(float)
        flag(~np.isfinite(vector).all(axis=1), f"{prefix} has NaN or infinite entries")
        if prefix == "direction":
            flag(np.linalg.norm(vector, axis=1) < 1e-9, "direction is zero")
    for name in ("mass", "scale", "finger_speed", "push_depth", "approach_offset", "finger_radius"):
        value = table.column(name).to_numpy(zero_copy_only=False).astype(float)
        positive = name in ("mass", "scale", "finger_speed")
        bad = ~np.isfinite(value) | ((value <= 0) if positive else (value < 0))
        flag(bad, f"{name} must be {'positive' if positive else 'non-negative'} and finite")
    return problems


def rigid(matrices: np.ndarray, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """Whether each 4x4 matrix is a rigid transform.

    matrices : (n, 4, 4) float
    returns : (n,) bool
    """
    rotation = matrices[:, :3, :3]
    with np.errstate(invalid="ignore"):
        orthogonal = np.abs(np.einsum("nji,njk->nik", rotation, rotation) - np.eye(3)).max(axis=(1, 2)) <= tolerance
        proper = np.abs(np.linalg.det(np.nan_to_num(rotation)) - 1.0) <= tolerance
        last_row = np.abs(matrices[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1) <= tolerance
    return orthogonal & proper & last_row


# --- a robot's own pushes -----------------------------------------------------------------

PYBULLET_SOURCE = "pybullet_data"
"""``mesh_source`` (and a corpus entry's ``source``, or a path under it) of one of pybullet's meshes."""
POSES_METADATA_KEY = b"toppledb_poses"
"""Parquet metadata key of a log ``write_log`` wrote for a dataset: that dataset's pose parameters
(JSON), the numbering its ``start_pose`` column uses, whatever configuration reads it later."""
LOG_FILE = "pushes.parquet"
"""The file ``write_log`` writes in a session's directory."""


@dataclass(frozen=True)
class LoggedMesh:
    """How a log row names its object: the mesh the model reads, in metres, and the mass.

    mesh_source : 'pybullet_data' (``mesh_path`` relative to it, so the log reads on any machine
      with pybullet installed) or 'file' (``mesh_path`` as the build read it)
    scale : mesh units -> metres;  mass : kg;  mesh_sha256 : hex SHA-256 of the mesh file
    """

    object_id: str
    mesh_source: str
    mesh_path: str
    scale: float
    mass: float
    mesh_sha256: str


def is_pybullet_source(source: str) -> bool:
    """Whether a mesh's ``source`` is pybullet's data (``pybullet_data`` or a path under it), whose mesh paths
    are read relative to wherever pybullet is installed."""
    return source == PYBULLET_SOURCE or source.startswith(PYBULLET_SOURCE + "/")


def below_pybullet_data(path: str) -> str | None:
    """What follows the last ``pybullet_data`` part of a recorded mesh path, as a POSIX path; None when it has
    no such part.  The path may be any machine's install: a build on Windows records C:\\...\\pybullet_data\\...,
    read by its parts, not this machine's."""
    parts = (PureWindowsPath if "\\" in path else PurePosixPath)(path).parts
    if PYBULLET_SOURCE not in parts:
        return None
    return PurePosixPath(*parts[len(parts) - parts[::-1].index(PYBULLET_SOURCE):]).as_posix()


def dataset_meshes(root: str | Path) -> dict[str, LoggedMesh]:
    """Object id -> ``LoggedMesh`` for every object of the dataset at ``root``, as its manifest's
    corpus records it (path, scale, mass and the SHA-256 of the file the build read).

    A mesh the build took from pybullet's data is named relative to it (the reader finds it in
    the pybullet it has installed; a copy that differs is rejected there as a changed mesh).
    ``schema.manifest.ManifestError`` when ``root`` is not a finished dataset of this schema."""
    meshes = {}
    for entry in read_manifest(root).corpus.objects:
        below = below_pybullet_data(entry.path) if is_pybullet_source(entry.source) else None
        source, path = ("file", entry.path) if below is None else (PYBULLET_SOURCE, below)
        meshes[entry.object_id] = LoggedMesh(entry.object_id, source, path, entry.scale, entry.mass, entry.sha256)
    return meshes


def robot_row(
    plan: Mapping[str, Any] | Any,
    start_transform: Any,
    final_transform: Any,
    mesh: LoggedMesh,
    *,
    push_id: int,
    finger_speed: float,
    finger_radius: float,
    source: str,
    repeat: int = 0,
    mu_table: float | None = None,
    mu_finger: float | None = None,
) -> dict[str, Any]:
    """One log row for a push the robot executed as ``/plan`` answered it.

    plan : the ``/plan`` answer (its JSON as a dict, or ``service.client``'s model of it) that
      chose the push; it must have chosen one (``decision`` 'push')
    start_transform : (4, 4) float, object -> world as observed before the push: the very pose sent
      to ``/plan`` (for a ``ros_pose``, ``RosPose(...).matrix()``), in its world frame (table at
      z = 0). The push is mapped into the object frame through it, so another pose (one observed
      again after planning) logs a push the robot did not make, which nothing downstream can tell.
    final_transform : (4, 4) float, object -> world as observed once the object was at rest again
    mesh : the object's ``LoggedMesh`` (``dataset_meshes``); its id must be the plan's
    push_id, repeat : the push's id in this session's log, and which repeat of it this is (integers)
    finger_speed : m/s;  finger_radius : m;  source : 'robot:<name>'
    mu_table, mu_finger : friction coefficients, if measured

    The push is logged in the object frame, with the approach and stroke the plan gave, and the
    plan's pose and action as hints. ValueError when the plan chose no push or names another object."""
    if hasattr(plan, "model_dump"):
        plan = plan.model_dump()
    push = plan.get("push")
    if push is None:
        raise ValueError(f"the plan chose no push (decision {plan.get('decision')!r}): there is nothing to log")
    if plan.get("object_id") != mesh.object_id:
        raise ValueError(f"the plan is for object {plan.get('object_id')!r}, the mesh is {mesh.object_id!r}")
    start = np.asarray(start_transform, dtype=float)
    final = np.asarray(final_transform, dtype=float)
    for name, matrix in (("start_transform", start), ("final_transform", final)):
        if matrix.shape != (4, 4):
            raise ValueError(f"{name} must be a 4x4 matrix, not shape {matrix.shape}")
    to_object = np.linalg.inv(start)
    point = to_object[:3, :3] @ np.asarray(push["point"], dtype=float) + to_object[:3, 3]
    direction = to_object[:3, :3] @ np.asarray(push["direction"], dtype=float)
    return {
        "object_id": mesh.object_id, "mesh_sha256": mesh.mesh_sha256, "mesh_source": mesh.mesh_source,
        "mesh_path": mesh.mesh_path, "scale": float(mesh.scale), "mass": float(mesh.mass),
        "push_id": _integer(push_id, "push_id"), "repeat": _integer(repeat, "repeat"),
        "start_pose": plan.get("match", {}).get("pose"), "start_transform": start.ravel().tolist(),
        "point_x": point[0], "point_y": point[1], "point_z": point[2],
        "direction_x": direction[0], "direction_y": direction[1], "direction_z": direction[2],
        "action": plan.get("action"), "finger_speed": float(finger_speed),
        "approach_offset": float(push["approach_offset"]), "push_depth": float(push["push_depth"]),
        "finger_radius": float(finger_radius), "final_transform": final.ravel().tolist(),
        "mu_table": mu_table, "mu_finger": mu_finger, "source": source, "seed": None,
    }


def write_log(rows: Iterable[Mapping[str, Any]], directory: str | Path, dataset: str | Path | None = None) -> Path:
    """Write a session's push-log rows (``robot_row``'s, or any with ``PUSHLOG``'s columns) as one
    log: ``directory/pushes.parquet``. Returns the file.

    Push ids are unique within one log, so each session gets a directory of its own; the
    directories of several sessions side by side (``logs/robot/session-1``, ``.../session-2``) are read
    as that many logs (``toppledb report logs/robot``).
    dataset : the dataset the plans came from; its pose parameters are recorded in the file, so
      the reader numbers the rows' ``start_pose`` as the dataset did whatever configuration it
      reads with (without it the column is read in the reader's numbering)

    All or nothing: every row is checked first (``row_problems``, and no empty text or id), and a
    ValueError names each bad row and why, with nothing written; the file is flushed to disk and
    appears whole or not at all; a directory that holds anything already is never written into
    (FileExistsError)."""
    directory = Path(directory)
    rows = list(rows)
    if not rows:
        raise ValueError("no rows to write")
    missing = sorted({name for row in rows for name in PUSHLOG.names if name not in row})
    if missing:
        raise ValueError(f"rows lack the columns {missing}")
    bad = []
    for i, row in enumerate(rows):
        for field in PUSHLOG:
            value = row[field.name]
            if value is None and not field.nullable:
                bad.append(f"row {i}: {field.name} is empty")
            elif value is not None and pa.types.is_integer(field.type):
                try:
                    operator.index(value)
                except TypeError:
                    bad.append(f"row {i}: {field.name} must be an integer, not {value!r}")
    if not bad:
        try:
            table = pa.Table.from_pydict({name: [row[name] for row in rows] for name in PUSHLOG.names}, schema=PUSHLOG)
        except (pa.ArrowException, TypeError, ValueError) as err:
            raise ValueError(f"rows do not fit the push log's schema: {' '.join(str(err).split())[:200]}") from None
        bad = [f"row {i}: {problem}" for i, problem in enumerate(row_problems(table)) if problem is not None]
    if bad:
        raise ValueError(f"{len(bad)} problem{'s' * (len(bad) > 1)} in {len(rows)} rows, nothing written: " + "; ".join(bad[:5]))
    if dataset is not None:
        poses = read_manifest(dataset).parameters.poses.model_dump()
        table = table.replace_schema_metadata({**PUSHLOG.metadata, POSES_METADATA_KEY: json.dumps(poses, sort_keys=True).encode()})
    if directory.name.startswith(("_", ".")):
        raise ValueError(f"{directory.name!r}: log readers skip names that start with '_' or '.'")
    if directory.exists() and not directory.is_dir():
        raise NotADirectoryError(f"{directory} is a file: a session's log is a directory")
    if directory.is_dir() and any(directory.iterdir()):
        # Holding a log, or the sessions of one robot: a file here would join them into one log.
        raise FileExistsError(f"{directory} is not empty: write each session to a new directory")
    path = directory / LOG_FILE
    write_atomic(path, lambda temp: pq.write_table(table, temp), exclusive=True)
    return path


def _integer(value: Any, name: str) -> int:
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer, not {value!r}") from None
