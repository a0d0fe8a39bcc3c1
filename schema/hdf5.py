"""Layout of the per-object HDF5 file (``arrays/<object_id>.h5``) of dense arrays.

::

    /                       attrs: schema_version, object_id, n_poses, n_trials
    /center_mass            (3,)       float64  m, object frame
    /hull/vertices          (V, 3)     float64  m, object frame
    /hull/faces             (F, 3)     int32    vertex indices, counter-clockwise seen from outside
    /poses/000/transform    (4, 4)     float64  object frame -> pose frame
    /poses/000/down         (3,)       float64  unit, object frame, points onto the table
    /poses/000/base_edges   (E, 2, 3)  float64  m, pose frame, counter-clockwise from above
    /poses/000/edge_final_pose (E,)    int32    pose reached by toppling over the edge (the thesis's landing)
    /poses/000/edge_landed_pose (E,)   int32    pose this build's model lands that topple in (before C.17's spread)
    /poses/000/edge_onward_pose (E,)   int32    pose a share of that landing is carried on to (the landing if none)
    /poses/000/edge_onward_share (E,)  float64  that share, in [0, 1]
    /poses/000/edge_blocked (E,)       bool     another part of the hull meets the table first
    /poses/000/apex_angle   (E,)       float64  rad, rotation about the edge to bring the COM above it
    /poses/000/outcomes     (A, T)     int16    per trial: base edge toppled over, -1 none, -2 not evaluated
    /poses/001/...

Symbolic sizes: V, F per object; E, A per pose (A equals the pose's rows in the
actions table, in action order); T, the trials per action, per file.
``ARRAYS`` is the single definition; the shard writer and the verifier use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArraySpec:
    """One dataset: path inside its group, dtype, shape with symbolic sizes, meaning."""

    name: str
    dtype: np.dtype
    shape: tuple[int | str, ...]
    description: str


OBJECT_ARRAYS = (
    ArraySpec("center_mass", np.dtype("float64"), (3,), "m, centre of mass, object frame"),
    ArraySpec("hull/vertices", np.dtype("float64"), ("V", 3), "m, convex hull vertices, object frame"),
    ArraySpec("hull/faces", np.dtype("int32"), ("F", 3), "convex hull triangles, vertex indices"),
)

POSE_ARRAYS = (
    ArraySpec("transform", np.dtype("float64"), (4, 4), "object frame -> pose frame"),
    ArraySpec("down", np.dtype("float64"), (3,), "unit vector, object frame, pointing onto the table"),
    ArraySpec("base_edges", np.dtype("float64"), ("E", 2, 3), "m, support polygon edges, pose frame"),
    ArraySpec("edge_final_pose", np.dtype("int32"), ("E",), "pose reached by toppling over each edge (the thesis's landing)"),
    ArraySpec("edge_landed_pose", np.dtype("int32"), ("E",), "pose the build's variant lands a topple over each edge in (before C.17's spread)"),
    ArraySpec("edge_onward_pose", np.dtype("int32"), ("E",), "pose a share of that landing is carried on to (C.18); the landing where none is"),
    ArraySpec("edge_onward_share", np.dtype("float64"), ("E",), "share of the landing carried on, in [0, 1]; 0 when none"),
    ArraySpec("edge_blocked", np.dtype("bool"), ("E",), "topple over the edge is blocked by the hull"),
    ArraySpec("apex_angle", np.dtype("float64"), ("E",), "rad, rotation about the edge until the COM is above it"),
    ArraySpec("outcomes", np.dtype("int16"), ("A", "T"), "per trial: edge index, -1 no topple, -2 not evaluated"),
)

ATTRIBUTES = ("schema_version", "object_id", "n_poses", "n_trials")
"""Attributes of the file's root group."""


def pose_group(pose: int) -> str:
    """Group of one pose's arrays; zero-padded so that groups list in pose order."""
    return f"poses/{pose:03d}"


def check_array(path: str, spec: ArraySpec, array_shape: tuple[int, ...], dtype: np.dtype, sizes: dict[str, int]) -> list[str]:
    """Problems of one stored array against its spec; binds symbolic sizes in ``sizes``.

    A symbolic size seen for the first time is recorded in ``sizes``; later arrays
    must agree with it (e.g. ``E`` across one pose's edge arrays).
    """
    if dtype != spec.dtype:
        return [f"{path}: dtype {dtype}, expected {spec.dtype}"]
    if len(array_shape) != len(spec.shape):
        return [f"{path}: shape {array_shape}, expected {spec.shape}"]
    problems = []
    for size, expected in zip(array_shape, spec.shape):
        if isinstance(expected, str):
            expected = sizes.setdefault(expected, size)
        if size != expected:
            problems.append(f"{path}: shape {array_shape}, expected {spec.shape} with {sizes}")
            break
    return problems


def check_file(h5file, expected: dict[str, object]) -> list[str]:
    """Problems of an open ``h5py.File`` against this layout.

    expected : attribute values the file must have (e.g. object_id, n_poses) and,
      under key ``"A"``, a list of the expected number of actions per pose.
    """
    problems = []
    for name in ATTRIBUTES:
        if name not in h5file.attrs:
            problems.append(f"missing attribute {name}")
    for name, value in expected.items():
        if name in h5file.attrs and _plain(h5file.attrs[name]) != value:
            problems.append(f"attribute {name} = {_plain(h5file.attrs[name])!r}, expected {value!r}")
    if problems:
        return problems

    sizes: dict[str, int] = {"T": int(h5file.attrs["n_trials"])}
    for spec in OBJECT_ARRAYS:
        problems += _check_member(h5file, spec.name, spec, sizes)
    n_poses = int(h5file.attrs["n_poses"])
    actions_per_pose = expected.get("A")
    stored_groups = set(h5file["poses"].keys()) if "poses" in h5file else set()
    wanted_groups = {pose_group(i).split("/")[1] for i in range(n_poses)}
    if stored_groups != wanted_groups:
        problems.append(f"pose groups {sorted(stored_groups)}, expected {sorted(wanted_groups)}")
    for pose in range(n_poses):
        pose_sizes = {"T": sizes["T"]}
        if actions_per_pose is not None:
            pose_sizes["A"] = actions_per_pose[pose]
        for spec in POSE_ARRAYS:
            problems += _check_member(h5file, f"{pose_group(pose)}/{spec.name}", spec, pose_sizes)
    return problems


def _check_member(h5file, path: str, spec: ArraySpec, sizes: dict[str, int]) -> list[str]:
    if path not in h5file:
        return [f"missing dataset /{path}"]
    dataset = h5file[path]
    return check_array("/" + path, spec, dataset.shape, dataset.dtype, sizes)


def _plain(value):
    """HDF5 attribute as a plain Python value (numpy scalars and bytes decoded)."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value
