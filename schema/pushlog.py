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
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

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
            flag(np.array([v is None for v in values.to_pylist()]), f"{name} missing")
            continue
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
