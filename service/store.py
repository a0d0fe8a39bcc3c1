"""The dataset in memory: loaded once at start, read-only afterwards.

Per object, pose data are arrays over its P poses and action data are arrays over
all its N candidate pushes, pose after pose in action order: the actions of pose
``p`` are rows ``action_offsets[p] : action_offsets[p + 1]`` (a slice is a view, so
"per pose" arrays cost nothing).  Transitions are CSR over those rows: the next-pose
distribution of row ``i`` is ``next_pose[k]``, ``probability[k]`` for ``k`` in
``transition_offsets[i] : transition_offsets[i + 1]``, empty unless the push is ``ok``.

Storage types trade precision the model does not have for memory: geometry,
``p_topple``, ``mean_force`` and transition probabilities are float32 (the contact
noise alone is 0.5 mm); ``q`` and ``greedy`` stay float64 so that ranking them agrees
with the pipeline's.  Values leave as float64 through ``widen``, which serves the
float32 0.6 as 0.6.  The default dataset (2.2 M pushes, 2.1 M transitions) takes
about 160 MB of arrays; ``python -m service`` holds about 400 MB resident (130 MB of it
the interpreter, FastAPI and pyarrow themselves).

Imports numpy and pyarrow only: never the geometry stack.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from schema import layout
from schema.api import FINGER_FORCE_LIMIT
from schema.manifest import Manifest
from schema.reader import Dataset, DatasetUnreadable
from schema.vocabulary import NO_OP, POLICIES, STATUS_NAMES, STATUS_OK

from .errors import NotFound

STATUS_CODES = pa.array(STATUS_NAMES)
log = logging.getLogger("service")


class DatasetError(RuntimeError):
    """The directory is not a dataset this service can serve; the message says why."""


def widen(values: np.ndarray) -> np.ndarray:
    """float32 -> float64 through the shortest decimal that gives the same float32, NaN kept.

    So that 0.6 stored as float32 is served as 0.6, not 0.6000000238418579; about 1 us
    per value (numpy's shortest repr, in C).
    """
    return np.asarray(values, dtype=np.float32).astype(str).astype(np.float64)


def optional(value: float) -> float | None:
    """NaN (a null in the tables) -> None."""
    return None if np.isnan(value) else float(value)


@dataclass(eq=False)
class ObjectData:
    """Everything the service serves about one object.

    Poses (P of them), from poses.parquet:
      probability (P,), height (P,) m, com_height (P,) m, v_s (P,), v_t (P,): float64
      transforms (P, 4, 4) float64, object frame -> pose frame; inverse_transforms likewise
      downs (P, 3) float64, unit, object frame
      grasp_point, grasp_axis (P, 3) float64, pose frame, NaN when the pose has no grasp
      n_actions, n_ok_actions (P,) int32
      policy_action, policy_value: per policy name, (P,) int32 (-1 no push) and float64
    Actions (N = sum of n_actions), from actions/object_id=<id>/:
      action_offsets (P + 1,) int64
      status (N,) int8, index into schema.vocabulary.STATUS_NAMES
      points, normals, directions (N, 3) float32, pose frame (m; unit; unit)
      is_max_height (N,) bool
      p_topple, mean_force (N,) float32 (N for the force), NaN unless ok / when none
      q, greedy (N,) float64, NaN unless ok
    Transitions (M nonzero entries), from transitions/object_id=<id>/:
      transition_offsets (N + 1,) int32; next_pose (M,) int32; probability (M,) float32
    """

    object_id: str
    source: str
    sha256: str
    mass: float
    scale: float
    center_mass: np.ndarray
    probability: np.ndarray
    transforms: np.ndarray
    inverse_transforms: np.ndarray
    downs: np.ndarray
    height: np.ndarray
    com_height: np.ndarray
    v_s: np.ndarray
    v_t: np.ndarray
    grasp_point: np.ndarray
    grasp_axis: np.ndarray
    n_actions: np.ndarray
    n_ok_actions: np.ndarray
    policy_action: dict[str, np.ndarray]
    policy_value: dict[str, np.ndarray]
    action_offsets: np.ndarray
    status: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    directions: np.ndarray
    is_max_height: np.ndarray
    p_topple: np.ndarray
    mean_force: np.ndarray
    q: np.ndarray
    greedy: np.ndarray
    transition_offsets: np.ndarray
    next_pose: np.ndarray
    transition_probability: np.ndarray

    @property
    def n_poses(self) -> int:
        return len(self.probability)

    def check_pose(self, pose: int) -> int:
        """``pose``, or NotFound."""
        if not 0 <= pose < self.n_poses:
            raise NotFound(f"object '{self.object_id}' has no pose {pose}: its poses are 0..{self.n_poses - 1}")
        return pose

    def pose_rows(self, pose: int) -> slice:
        """Rows of the action arrays that belong to ``pose`` (action a is row start + a)."""
        self.check_pose(pose)
        return slice(int(self.action_offsets[pose]), int(self.action_offsets[pose + 1]))

    def row(self, pose: int, action: int) -> int:
        """Row of (pose, action) in the action arrays, or NotFound."""
        rows = self.pose_rows(pose)
        count = rows.stop - rows.start
        if not 0 <= action < count:
            raise NotFound(
                f"pose {pose} of object '{self.object_id}' has no action {action}: its actions are 0..{count - 1}"
            )
        return rows.start + action

    def is_ok(self, row: int) -> bool:
        return int(self.status[row]) == STATUS_OK

    def status_name(self, row: int) -> str:
        return STATUS_NAMES[int(self.status[row])]

    def transitions(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        """Next poses (K,) int32 and their probabilities (K,) float64 of one action row."""
        span = slice(int(self.transition_offsets[row]), int(self.transition_offsets[row + 1]))
        return self.next_pose[span], widen(self.transition_probability[span])

    def action_counts(self, pose: int) -> dict[str, int]:
        counts = np.bincount(self.status[self.pose_rows(pose)], minlength=len(STATUS_NAMES))
        return {name: int(n) for name, n in zip(STATUS_NAMES, counts)}


class Store:
    """The loaded dataset: objects by id, the manifest parameters the service needs."""

    def __init__(
        self, root: Path, manifest: Manifest, objects: dict[str, ObjectData], load_seconds: float, manifest_sha256: str = ""
    ):
        self.root = root
        self.manifest = manifest
        self.objects = objects
        self.load_seconds = load_seconds
        self.manifest_sha256 = manifest_sha256
        """SHA-256 of manifest.json's bytes as read before the tables: names the build."""
        self.loaded_at = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        parameters = manifest.parameters
        self.parameters_sha256 = hashlib.sha256(
            json.dumps(parameters.model_dump(mode="json"), sort_keys=True, separators=(",", ":")).encode()
        ).hexdigest()
        code = manifest.code_version
        self.code_version = code.package + (f"+g{code.git_commit[:12]}" if code.git_commit else "")
        manifest_limit = (parameters.topple.model_extra or {}).get("max_finger_force")
        self.manifest_finger_force_limit: float | None = float(manifest_limit) if manifest_limit is not None else None
        """N, the build's topple.max_finger_force (the limit its corrected model applied), when it recorded one."""
        self.schema_version: str = manifest.schema_version
        self.tolerance = parameters.poses.same_pose_angle
        """rad, largest angle between down vectors of one stable pose (pose matching)."""
        self.approach_offset = parameters.contacts.approach_offset
        """m, the finger starts this far outside the contact along the normal."""
        self.push_depth = parameters.contacts.push_depth
        """m, the finger ends this far inside the contact along the normal."""
        self.gamma = parameters.mdp.gamma
        self.failures = {f.object_id: f.reason for f in manifest.failures}
        self.counts = {
            "objects": len(objects),
            "poses": sum(o.n_poses for o in objects.values()),
            "actions": sum(len(o.status) for o in objects.values()),
            "ok_actions": sum(int((o.status == STATUS_OK).sum()) for o in objects.values()),
            "transitions": sum(len(o.next_pose) for o in objects.values()),
        }

    def finger_force_limit(self, override: float | None = None) -> float:
        """N: ``override`` (service setting), else the manifest's, else schema.api.FINGER_FORCE_LIMIT."""
        if override is not None:
            return override
        return self.manifest_finger_force_limit if self.manifest_finger_force_limit is not None else FINGER_FORCE_LIMIT

    def example_object(self) -> tuple[str, int, np.ndarray] | None:
        """(object_id, pose, transform (4, 4)) of the first object with a pushing pose under
        value iteration, else of the first object: the OpenAPI examples come from here."""
        for obj in self.objects.values():
            pushing = np.flatnonzero(obj.policy_action["value_iteration"] != NO_OP)
            if len(pushing):
                return obj.object_id, int(pushing[0]), obj.transforms[int(pushing[0])]
        for obj in self.objects.values():
            return obj.object_id, 0, obj.transforms[0]
        return None

    def object(self, object_id: str) -> ObjectData:
        """The object, or NotFound saying whether its build failed."""
        try:
            return self.objects[object_id]
        except KeyError:
            if object_id in self.failures:
                raise NotFound(
                    f"object '{object_id}' is not in the dataset: its build failed ({self.failures[object_id]})"
                ) from None
            raise NotFound(f"unknown object '{object_id}' ({len(self.objects)} objects; GET /objects lists them)") from None

    @classmethod
    def load(cls, root: str | Path, threads: int | None = None) -> Store:
        """Read a finished dataset directory; DatasetError if it is not one this service reads."""
        started = time.perf_counter()
        root = Path(root)
        try:
            manifest_sha256 = hashlib.sha256((root / layout.MANIFEST).read_bytes()).hexdigest()
        except OSError:
            manifest_sha256 = ""  # Dataset.open below says what is wrong
        try:
            dataset = Dataset.open(root)
            objects_table = dataset.table("objects")
            poses_table = dataset.table("poses")
        except DatasetUnreadable as err:
            raise DatasetError(str(err)) from None
        manifest = dataset.manifest
        pose_rows = _group_rows(poses_table.column("object_id").to_pylist())
        ids = objects_table.column("object_id").to_pylist()
        objects_rows = objects_table.to_pylist()
        # pyarrow releases the GIL while decoding, so threads overlap the per-object reads;
        # two take 25% off the load time, more only fragment memory (+100 MB RSS at 8).
        with ThreadPoolExecutor(threads or min(2, os.cpu_count() or 1)) as pool:
            loaded = list(
                pool.map(lambda i: _load_object(dataset, objects_rows[i], poses_table, pose_rows.get(ids[i], [])), range(len(ids)))
            )
        store = cls(root, manifest, {o.object_id: o for o in loaded}, time.perf_counter() - started, manifest_sha256)
        expected = {k: getattr(manifest.counts, k) for k in store.counts}
        if expected != store.counts:
            raise DatasetError(
                f"{root}: the tables hold {store.counts} but manifest.json says {expected}; "
                f"check it with `toppledb verify {root}`"
            )
        return store


def _group_rows(ids: list[str]) -> dict[str, list[int]]:
    groups: dict[str, list[int]] = {}
    for index, object_id in enumerate(ids):
        groups.setdefault(object_id, []).append(index)
    return groups


def _floats(table: pa.Table, name: str, dtype=np.float64) -> np.ndarray:
    """A numeric column as numpy, nulls as NaN."""
    return table.column(name).to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def _vectors(table: pa.Table, prefix: str, dtype=np.float64) -> np.ndarray:
    """Columns ``<prefix>_x, _y, _z`` as one (n, 3) array."""
    return np.stack([_floats(table, f"{prefix}_{axis}", dtype) for axis in "xyz"], axis=1)


ACTION_COLUMNS = [
    "pose", "action", "status", "is_max_height", "p_topple", "mean_force", "q", "greedy",
    *(f"{v}_{a}" for v in ("point", "normal", "direction") for a in "xyz"),
]


def _load_object(dataset: Dataset, row: dict, poses_table: pa.Table, pose_indices: list[int]) -> ObjectData:
    object_id = row["object_id"]
    poses = poses_table.take(pa.array(pose_indices, pa.int64())).sort_by("pose")
    n_poses = int(row["n_poses"])
    if poses.num_rows != n_poses or poses.column("pose").to_pylist() != list(range(n_poses)):
        raise DatasetError(f"{object_id}: poses.parquet holds poses {poses.column('pose').to_pylist()}, expected 0..{n_poses - 1}")
    n_actions = poses.column("n_actions").to_numpy().astype(np.int32)
    offsets = np.concatenate([[0], np.cumsum(n_actions, dtype=np.int64)])

    try:
        actions = dataset.object_rows("actions", object_id, ACTION_COLUMNS)
        transitions = dataset.object_rows("transitions", object_id, ["pose", "action", "next_pose", "probability"])
    except DatasetUnreadable as err:
        raise DatasetError(str(err)) from None
    keys = _sorted_keys(actions, ["pose", "action"])
    actions = actions.take(keys)
    pose_of = actions.column("pose").to_numpy()
    expected_action = np.arange(len(pose_of)) - offsets[np.clip(pose_of, 0, n_poses - 1)]
    if len(pose_of) != offsets[-1] or not np.array_equal(actions.column("action").to_numpy(), expected_action):
        raise DatasetError(f"{object_id}: the actions partition does not hold actions 0..n_actions - 1 of every pose")
    status = pc.index_in(actions.column("status"), value_set=STATUS_CODES)
    if status.null_count:
        raise DatasetError(f"{object_id}: unknown action status; known: {', '.join(STATUS_NAMES)}")

    transitions = transitions.take(_sorted_keys(transitions, ["pose", "action", "next_pose"]))
    t_pose = transitions.column("pose").to_numpy().astype(np.int64)
    t_action = transitions.column("action").to_numpy().astype(np.int64)
    next_pose = transitions.column("next_pose").to_numpy().astype(np.int32)
    if len(t_pose) and (
        t_pose.min() < 0 or t_pose.max() >= n_poses or next_pose.min() < 0 or next_pose.max() >= n_poses
        or (t_action < 0).any() or (t_action >= n_actions[t_pose]).any()
    ):
        raise DatasetError(f"{object_id}: transitions refer to poses or actions that do not exist")
    per_row = np.bincount(offsets[t_pose] + t_action, minlength=int(offsets[-1]))
    transforms = _transforms(poses)

    return ObjectData(
        object_id=object_id,
        source=row["source"],
        sha256=row["sha256"],
        mass=float(row["mass"]),
        scale=float(row["scale"]),
        center_mass=np.array([row["com_x"], row["com_y"], row["com_z"]], dtype=np.float64),
        probability=_floats(poses, "probability"),
        transforms=transforms,
        inverse_transforms=np.linalg.inv(transforms),
        downs=_vectors(poses, "down"),
        height=_floats(poses, "height"),
        com_height=_floats(poses, "com_height"),
        v_s=_floats(poses, "v_s"),
        v_t=_floats(poses, "v_t"),
        grasp_point=_vectors(poses, "grasp_point"),
        grasp_axis=_vectors(poses, "grasp_axis"),
        n_actions=n_actions,
        n_ok_actions=poses.column("n_ok_actions").to_numpy().astype(np.int32),
        policy_action={p: poses.column(f"{p}_action").to_numpy().astype(np.int32) for p in POLICIES},
        policy_value={p: _floats(poses, f"{p}_value") for p in POLICIES},
        action_offsets=offsets,
        status=status.to_numpy().astype(np.int8),
        points=_vectors(actions, "point", np.float32),
        normals=_vectors(actions, "normal", np.float32),
        directions=_vectors(actions, "direction", np.float32),
        is_max_height=actions.column("is_max_height").to_numpy(zero_copy_only=False).astype(bool),
        p_topple=_floats(actions, "p_topple", np.float32),
        mean_force=_floats(actions, "mean_force", np.float32),
        q=_floats(actions, "q"),
        greedy=_floats(actions, "greedy"),
        transition_offsets=np.concatenate([[0], np.cumsum(per_row)]).astype(np.int32),
        next_pose=next_pose,
        transition_probability=_floats(transitions, "probability", np.float32),
    )


def _sorted_keys(table: pa.Table, keys: list[str]) -> pa.Array:
    """Indices that sort ``table`` by ``keys`` (the pipeline writes them sorted; this makes sure)."""
    return pc.sort_indices(table, sort_keys=[(k, "ascending") for k in keys])


def _transforms(poses: pa.Table) -> np.ndarray:
    """The fixed-size-list ``transform`` column as (P, 4, 4) float64."""
    column = poses.column("transform").combine_chunks()
    return column.flatten().to_numpy().astype(np.float64).reshape(-1, 4, 4)


def manifest_stamp(root: Path) -> tuple | None:
    """(inode, size, mtime_ns) of manifest.json, None when absent: a rebuild replaces the file
    (the pipeline writes it last, atomically), so any change of the stamp is a new build."""
    try:
        st = os.stat(Path(root) / layout.MANIFEST)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


class LiveStore:
    """The store a worker serves now, swapped atomically for a rebuilt dataset.

    A request takes ``live.store`` once (``dependencies.get_store``) and uses that object to
    the end, so a swap never mixes two builds in one answer nor fails a request in flight;
    the old store is freed when its last request finishes.  A failed reload (half-written
    rebuild, wrong schema) keeps the old store and is logged once per manifest stamp.
    """

    def __init__(self, store: Store):
        self.store = store
        self.reloads = 0
        self._stamp = manifest_stamp(store.root)
        self._failed_stamp: tuple | None = None
        self._lock = threading.Lock()

    def changed(self) -> bool:
        stamp = manifest_stamp(self.store.root)
        return stamp is not None and stamp != self._stamp and stamp != self._failed_stamp

    def reload(self, force: bool = False) -> bool:
        """Load the dataset again if its manifest changed (or ``force``); True when swapped.
        Blocking (seconds for a full dataset): call it from a thread, not the event loop."""
        with self._lock:  # one load at a time; a second trigger waits and then finds nothing new
            if not force and not self.changed():
                return False
            stamp = manifest_stamp(self.store.root)
            try:
                fresh = Store.load(self.store.root)
            except DatasetError as err:
                if stamp != self._failed_stamp:
                    log.warning("reload of %s failed, still serving manifest %s: %s", self.store.root,
                                self.store.manifest_sha256[:12], err)
                self._failed_stamp = stamp
                return False
            if fresh.manifest_sha256 == self.store.manifest_sha256 and not force:
                self._stamp = stamp
                return False
            self.store, self._stamp, self._failed_stamp = fresh, stamp, None
            self.reloads += 1
            log.warning("now serving %s manifest %s (%d objects, loaded in %.1f s)", fresh.root,
                        fresh.manifest_sha256[:12], fresh.counts["objects"], fresh.load_seconds)
            return True
