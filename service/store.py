"""The dataset in memory: mapped once at start, read-only afterwards.

Per object, pose data are arrays over its P poses and action data are arrays over
all its N candidate pushes, pose after pose in action order: the actions of pose
``p`` are rows ``action_offsets[p] : action_offsets[p + 1]`` (a slice is a view, so
"per pose" arrays cost nothing).  Transitions are CSR over those rows: the next-pose
distribution of row ``i`` is ``next_pose[k]``, ``probability[k]`` for ``k`` in
``transition_offsets[i] : transition_offsets[i + 1]``, empty unless the push is ``ok``.

Every array is a numpy view into the served tables (``schema.served``): Arrow IPC
files the pipeline writes beside the Parquet tables and this module memory-maps, so a
worker starts in milliseconds and every worker on the machine shares one copy of the
pages in the file cache.  Their storage types trade precision the model does not have
for memory (float32 geometry and probabilities, float64 ``q`` and ``greedy`` so that
ranking them agrees with the pipeline's); values leave as float64 through ``widen``,
which serves the float32 0.6 as 0.6.

Imports numpy and pyarrow only: never the geometry stack.
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import mmap
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from schema import horizon, layout, neighbourhood, served
from schema.api import FINGER_FORCE_LIMIT
from schema.files import file_sha256
from schema.manifest import Manifest, ManifestError, read_manifest
from schema.vocabulary import NO_OP, POLICIES, STATUS_NAMES, STATUS_OK

from .errors import NotFound
from .prefetch import Prefetch

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

    Poses (P of them), from served/poses.arrow:
      probability (P,), height (P,) m, com_height (P,) m, v_s (P,), v_t (P,): float64
      transforms (P, 4, 4) float64, object frame -> pose frame
      downs (P, 3) float64, unit, object frame
      grasp_point, grasp_axis (P, 3) float64, pose frame, NaN when the pose has no grasp
      n_actions, n_ok_actions (P,) int32
      policy_action, policy_value: per policy name, (P,) int32 (-1 no push) and float64
      policy_p_topple_neighbourhood: per policy name, (P,) float64, the mean P(topple) around
        its push (schema.neighbourhood), NaN when it does not push
    Orientations that match a pose (M >= P: a symmetric object's merged turns), from matches:
      match_pose (M,) int32, the pose each is; match_downs (M, 3) float64, unit, object frame;
      match_transforms, match_inverses (M, 4, 4) float64, object -> pose frame and back
    Actions (N = sum of n_actions), from served/actions.arrow:
      action_offsets (P + 1,) int64
      status (N,) int8, index into schema.vocabulary.STATUS_NAMES
      points, normals, directions (N, 3) float32, pose frame (m; unit; unit)
      is_max_height (N,) bool
      p_topple, mean_force (N,) float32 (N for the force), NaN unless ok / when none
      q, greedy (N,) float64, NaN unless ok
    Transitions (K nonzero entries), from served/transitions.arrow:
      transition_offsets (N + 1,) int64; next_pose (K,) int32; transition_probability (K,) float32
    Hull: hull_vertices (V, 3) float64, m, object frame
    min_direction_z: the build's ``mdp.min_direction_z``: the pushes greedy and value iteration may take
    budget_direction_z: the build's ``mdp.budget_min_direction_z``: the pushes a budget's choice may take
    failure_power: k of (12.14) when the build plans with its failures (``MDPParameters.failure_power``):
      its budgets then believe a failure as its value iteration does; None: they are (12.8) and believe nothing
    """

    object_id: str
    source: str
    sha256: str
    mass: float
    scale: float
    center_mass: np.ndarray
    probability: np.ndarray
    transforms: np.ndarray
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
    policy_p_topple_neighbourhood: dict[str, np.ndarray]
    match_pose: np.ndarray
    match_downs: np.ndarray
    match_transforms: np.ndarray
    match_inverses: np.ndarray
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
    hull_vertices: np.ndarray
    min_direction_z: float = -1.0
    budget_direction_z: float = -1.0
    failure_power: float | None = None
    _budgets: tuple | None = field(default=None, init=False, repr=False)

    def budget(self, pushes_left: int) -> tuple[np.ndarray, np.ndarray]:
        """Value iteration for a budget of ``pushes_left`` pushes (``schema.horizon``): per pose
        the action (P,) int (NO_OP: grasp now) and V_h (P,) float.  A build that plans with its
        failures (``failure_power``) solves the fresh and failed-here states
        (``horizon.belief_budget_choices``) and this is the fresh one's.

        Solved for every budget at once, by ``Store.solve_budgets`` or else at the object's first
        such request, and kept: the store is read-only, a rebuilt dataset is a new store.  Reads
        only the transitions, so solving every object maps ~25 MB of the served files, not the
        candidates' geometry (the neighbourhood mean is per request: ``neighbourhood_p``).
        """
        actions, fresh, _ = self._solved_budgets()
        if not 1 <= pushes_left <= len(actions):
            raise ValueError(f"pushes_left must be 1..{len(actions)}, got {pushes_left}")
        return actions[pushes_left - 1], fresh[pushes_left - 1]

    def budget_q(self, pose: int, pushes_left: int, after_failure: bool) -> np.ndarray:
        """What ranks the pushes of ``pose`` for a budget of ``pushes_left`` (``horizon.budget_q``:
        Q1_h of (12.14) once a push from it has failed in a build that plans with its failures):
        (A,) float, NaN unless ok."""
        _, fresh, failed = self._solved_budgets()
        return horizon.budget_q(self.v_s, fresh, failed, pushes_left, pose, self.pose_rows(pose), self.transition_offsets,
                                self.next_pose, self.transition_probability, self.failure_power, after_failure)

    def _solved_budgets(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(actions, V0, V1), each (MAX_PUSHES_LEFT, P) (``horizon.solve_budgets``)."""
        if self._budgets is None:
            # one assignment: a concurrent first request computes the same
            csr = (self.action_offsets, self.transition_offsets, self.next_pose, self.transition_probability)
            self._budgets = horizon.solve_budgets(self.v_s, csr, horizon.MAX_PUSHES_LEFT, self.failure_power,
                                                  self.budget_choosable(slice(None)))
        return self._budgets

    def choosable(self, rows: slice | list[int]) -> np.ndarray:
        """(n,) bool, whether greedy and value iteration may choose each action row: ``ok``
        and pushing with u_z at least the build's ``mdp.min_direction_z`` (``schema.horizon``)."""
        return self._ok_above(rows, self.min_direction_z)

    def budget_choosable(self, rows: slice | list[int]) -> np.ndarray:
        """(n,) bool, whether a budget (``pushes_left``) may choose each action row: ``ok`` and pushing
        with u_z at least the build's ``budget_direction_z``."""
        return self._ok_above(rows, self.budget_direction_z)

    def _ok_above(self, rows: slice | list[int], min_direction_z: float) -> np.ndarray:
        """(n,) bool: ``ok`` and u_z at least ``min_direction_z`` (``schema.horizon.choosable_pushes``)."""
        return (self.status[rows] == STATUS_OK) & horizon.choosable_pushes(self.directions[rows, 2], min_direction_z)

    def neighbourhood_p(self, pose: int, action: int) -> float:
        """The mean P(topple) around one push of a pose (``schema.neighbourhood``; the served
        tables hold it for each policy's push, this is for any other, about 80 us)."""
        rows = self.pose_rows(pose)
        mean, _ = neighbourhood.neighbour_mean(self.points[rows], self.directions[rows], self.p_topple[rows], rows=[action])
        return float(mean[0])

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
        self.parameters_sha256 = manifest.parameters_sha256()
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
        self.after_failure_power: float | None = parameters.mdp.after_failure_power
        """k of schema.retry.after_failure; None for a build from before it (then no p_topple_given_failures)."""
        self.retry_failed: bool = parameters.mdp.retry_failed
        """Whether the build's Q_T counts on retrying a failed push (docs/MODEL.md (12.9)); retry.believed_values needs it."""
        self.believe_failures: bool = parameters.mdp.believe_failures
        """Whether the build's Q is Q0 of docs/MODEL.md (12.13); after a failure /plan then ranks by Q1."""
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

    def solve_budgets(self) -> None:
        """Solve every object's budgets (``ObjectData.budget``) ahead of the requests: about
        0.6 s for the full default dataset, 2.3 ms per object (8 ms at most; the table's budget
        of a build that does not believe failures half that) that a first
        request with ``pushes_left`` would otherwise pay.  Call it off the event loop."""
        for obj in self.objects.values():
            obj.budget(1)

    def object(self, object_id: str) -> ObjectData:
        """The object, or NotFound saying whether its build failed."""
        try:
            return self.objects[object_id]
        except KeyError:
            if object_id in self.failures:
                raise NotFound(
                    f"object '{object_id}' is not in the dataset: its build failed ({self.failures[object_id]})"
                ) from None
            raise NotFound(f"unknown object {_quoted(object_id)} ({len(self.objects)} objects; GET /objects lists them)") from None

    @classmethod
    def load(cls, root: str | Path, prefetch: Prefetch | None = None) -> Store:
        """Map a finished dataset's served tables (``schema.served``); DatasetError if it is
        not a dataset this service reads.  A dataset without them (or whose served files do
        not match its manifest) is served from its Parquet tables, converted in memory:
        seconds instead of milliseconds, and in this process's memory, not the file cache
        (workers forked afterwards share it; a reload converts again in each).

        A rebuild commits its files one rename at a time, the manifest last: a load in between
        finds new files under the old manifest, which the checksums refuse, and is made again
        once the manifest has changed (up to ``LOAD_ATTEMPTS`` times).

        prefetch : the served files mapped and hashed while the service was starting
          (``service.prefetch``), used if they are this directory's under this manifest"""
        root = Path(root)
        for _ in range(LOAD_ATTEMPTS - 1):
            stamp = manifest_stamp(root)
            try:
                return cls._load_once(root, prefetch)
            except DatasetError:
                if manifest_stamp(root) == stamp:
                    raise
        return cls._load_once(root, prefetch)

    @classmethod
    def _load_once(cls, root: Path, prefetch: Prefetch | None = None) -> Store:
        """One load of the dataset as its files are now (``load``)."""
        started = time.perf_counter()
        try:
            raw = (root / layout.MANIFEST).read_bytes()  # hashed and parsed once: a rebuild may replace it meanwhile
        except OSError:
            raw = None  # read_manifest below says what is wrong
        manifest_sha256 = hashlib.sha256(raw).hexdigest() if raw is not None else ""
        try:
            manifest = read_manifest(root, raw)
        except ManifestError as err:
            raise DatasetError(str(err)) from None
        try:
            tables = served.read_current(root, manifest, mapped=_mapped(root, manifest_sha256, prefetch))
        except served.ServedError as err:
            log.warning("%s; reading the Parquet tables instead (slower start, a copy in memory)", err)
            tables = _tables_from_parquet(root, manifest)
        mdp = manifest.parameters.mdp
        objects = _objects(tables, mdp.min_direction_z, mdp.failure_power, mdp.budget_min_direction_z)
        store = cls(root, manifest, objects, time.perf_counter() - started, manifest_sha256)
        expected = {k: getattr(manifest.counts, k) for k in store.counts}
        if expected != store.counts:
            raise DatasetError(
                f"{root}: the tables hold {store.counts} but manifest.json says {expected}; "
                f"check it with `toppledb verify {root}`"
            )
        return store


def _mapped(root: Path, manifest_sha256: str, prefetch: Prefetch | None) -> dict[str, tuple[mmap.mmap, str]]:
    """Table name -> (mapping, SHA-256) of the served files ``prefetch`` mapped and hashed, if they are
    this build's; ``read_served`` maps and hashes the others (and says why one cannot be)."""
    prefetched = prefetch.mapped(root, manifest_sha256) if prefetch is not None else {}
    return {name: prefetched[relative] for name, relative in served.FILES.items() if relative in prefetched}


def _tables_from_parquet(root: Path, manifest: Manifest) -> dict[str, pa.Table]:
    """The served tables converted from the Parquet tables, each file of which must be the bytes the
    manifest records (as ``read_current`` checks the served files); DatasetError otherwise."""
    from schema.reader import Dataset, DatasetUnreadable  # pyarrow.parquet: only on this path

    read = [layout.OBJECTS_FILE, layout.POSES_FILE,
            *(layout.partition_file(table, object_id) for object_id in manifest.shards for table in ("actions", "transitions"))]
    for relative in read:
        recorded, actual = manifest.recorded_sha256(relative), file_sha256(root / relative)
        if recorded is None or actual != recorded:
            found = "missing or unreadable" if not actual else "not recorded" if recorded is None else \
                f"sha256 {actual[:12]}... differs from the manifest's {recorded[:12]}..."
            raise DatasetError(f"{root}: {relative}: {found}; check it with `toppledb verify {root}`")
    try:
        return served.served_from_parquet(Dataset(root, manifest))
    except (served.ServedError, DatasetUnreadable) as err:
        raise DatasetError(f"{root}: {err}") from None


def _objects(tables: dict[str, pa.Table], min_direction_z: float = -1.0, failure_power: float | None = None,
             budget_direction_z: float = -1.0) -> dict[str, ObjectData]:
    """ObjectData of every object: views into the served tables' columns (no copies but
    two small offset arrays per object); ``min_direction_z`` and ``failure_power`` are the build's (``ObjectData``)."""
    col = {name: {f.name: served.column(table, f.name) for f in table.schema if not pa.types.is_string(f.type)}
           for name, table in tables.items()}
    numbers, poses, matches, actions, transitions, hulls = (col[name] for name in served.NAMES)

    def rows(i: int, start: str, count: str) -> slice:
        """Object ``i``'s rows of a table: ``objects.<start>`` onwards, ``objects.<count>`` of them."""
        first = int(numbers[start][i])
        return slice(first, first + int(numbers[count][i]))

    out = {}
    for i, row in enumerate(tables["objects"].select(["object_id", "source", "sha256"]).to_pylist()):
        p, m = rows(i, "pose_start", "n_poses"), rows(i, "match_start", "n_matches")
        a, t = rows(i, "action_start", "n_actions"), rows(i, "transition_start", "n_transitions")
        h = rows(i, "hull_start", "n_hull_vertices")
        n_actions, n_transitions = a.stop - a.start, t.stop - t.start
        out[row["object_id"]] = ObjectData(
            object_id=row["object_id"],
            source=row["source"],
            sha256=row["sha256"],
            mass=float(numbers["mass"][i]),
            scale=float(numbers["scale"][i]),
            center_mass=numbers["com"][i],
            probability=poses["probability"][p],
            transforms=poses["transform"][p].reshape(-1, 4, 4),
            downs=poses["down"][p],
            height=poses["height"][p],
            com_height=poses["com_height"][p],
            v_s=poses["v_s"][p],
            v_t=poses["v_t"][p],
            grasp_point=poses["grasp_point"][p],
            grasp_axis=poses["grasp_axis"][p],
            n_actions=poses["n_actions"][p],
            n_ok_actions=poses["n_ok_actions"][p],
            policy_action={name: poses[f"{name}_action"][p] for name in POLICIES},
            policy_value={name: poses[f"{name}_value"][p] for name in POLICIES},
            policy_p_topple_neighbourhood={name: poses[f"{name}_p_topple_neighbourhood"][p] for name in POLICIES},
            match_pose=matches["pose"][m],
            match_downs=matches["down"][m],
            match_transforms=matches["transform"][m].reshape(-1, 4, 4),
            match_inverses=matches["inverse"][m].reshape(-1, 4, 4),
            action_offsets=np.append(poses["action_start"][p], n_actions),
            status=actions["status"][a],
            points=actions["point"][a],
            normals=actions["normal"][a],
            directions=actions["direction"][a],
            is_max_height=actions["is_max_height"][a].view(bool),
            p_topple=actions["p_topple"][a],
            mean_force=actions["mean_force"][a],
            q=actions["q"][a],
            greedy=actions["greedy"][a],
            transition_offsets=np.append(actions["transition_start"][a], n_transitions),
            next_pose=transitions["next_pose"][t],
            transition_probability=transitions["probability"][t],
            hull_vertices=hulls["vertex"][h],
            min_direction_z=min_direction_z,
            budget_direction_z=budget_direction_z,
            failure_power=failure_power,
        )
    return out


def manifest_stamp(root: Path) -> tuple | None:
    """(inode, size, mtime_ns) of manifest.json, None when absent: a rebuild replaces the file
    (the pipeline writes it last, atomically), so any change of the stamp is a new build."""
    try:
        st = os.stat(Path(root) / layout.MANIFEST)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


LOAD_ATTEMPTS = 3
"""Loads of a dataset whose manifest changed while it was read (``Store.load``)."""


class LiveStore:
    """The store a worker serves now, swapped atomically for a rebuilt dataset.

    A request takes ``live.store`` once (``dependencies.get_store``) and uses that object to
    the end, so a swap never mixes two builds in one answer nor fails a request in flight;
    the old store is freed when its last request finishes.  A failed reload (half-written
    rebuild, wrong schema) keeps the old store, is logged once per manifest stamp, counted in
    ``failed_reloads`` and kept in ``reload_error`` (what /health shows) until a reload succeeds
    or finds the served build again.
    """

    def __init__(self, store: Store):
        self.store = store
        self.reloads = 0
        self.failed_reloads = 0
        self.reload_error: str | None = None
        self.on_failure: Callable[[], None] | None = None
        """Called (in the reloading thread, under the reload's lock) once per build that fails to load."""
        self._stamp = manifest_stamp(store.root)
        self._failed_stamp: tuple | None = None
        self._lock = threading.Lock()

    def changed(self) -> bool:
        stamp = manifest_stamp(self.store.root)
        if stamp == self._stamp and self.reload_error is not None:
            # The served build's manifest is back (renamed into place): nothing is wrong any more.
            self.reload_error, self._failed_stamp = None, None
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
                fresh.solve_budgets()  # here, in the reload's thread: not in a request on the event loop
            except DatasetError as err:
                if stamp != self._failed_stamp:
                    log.warning("reload of %s failed, still serving manifest %s: %s", self.store.root,
                                self.store.manifest_sha256[:12], err)
                    self.failed_reloads += 1
                    if self.on_failure is not None:
                        self.on_failure()
                self._failed_stamp = stamp
                self.reload_error = str(err)
                return False
            self.reload_error = None
            if fresh.manifest_sha256 == self.store.manifest_sha256 and not force:
                self._stamp = stamp
                return False
            self.store, self._stamp, self._failed_stamp = fresh, stamp, None
            self.reloads += 1
            log.warning("now serving %s manifest %s (%d objects, loaded in %.1f s)", fresh.root,
                        fresh.manifest_sha256[:12], fresh.counts["objects"], fresh.load_seconds)
            return True


ECHOED_ID = 64
"""The most characters of an unknown id an error repeats: a request may carry kilobytes of one."""


def _quoted(object_id: str) -> str:
    """``object_id`` in quotes for an error message, cut to its first ``ECHOED_ID`` characters."""
    if len(object_id) <= ECHOED_ID:
        return f"'{object_id}'"
    return f"'{object_id[:ECHOED_ID]}...' ({len(object_id)} characters)"
