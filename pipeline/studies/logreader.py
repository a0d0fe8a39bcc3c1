"""Reading a push-outcome log (``schema.pushlog``) against the model.

A log row is one executed push.  To compare it with the toppling model the reader
loads each logged object's mesh (after checking its SHA-256), computes its stable
poses with the same ``config.poses`` the dataset uses, matches the observed start
transform to a stable pose (``schema.frames.match_pose``'s rule, vectorised) and settles
the observed final transform into one (``pipeline.model.poses.settle``'s rule; a rest pose
outside the pose set is its own bucket).  Repeats of one push (same object and ``push_id``)
become one empirical next-pose distribution.  Push ids are unique within one log (a file, or a
directory and every Parquet file under it), not across logs: the same id in two logs is two pushes
(``Push.log``), unless they are the very same rows (a log that is part of another), which are read
once.  A directory that holds no Parquet file of its own but directories that do (``data/logs``) is
read as those logs, one per subdirectory (``logs_under``).

Nothing is dropped silently and nothing crashes: every row that cannot be used is
counted under a one-line reason (``PushLog.rejected``), with the first few rows of
each reason kept as examples.

    log = read_log(["data/logs/calibration"], Config())
    log.pushes        # list[Push], one per push_id with its repeats
    log.rejected      # reason -> number of rows
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema.frames import DOWN, transform_points, unit
from schema.pushlog import POSES_METADATA_KEY, PUSHLOG, row_problems

from ..build.atomic import file_sha256
from ..build.corpus import Corpus, CorpusError, is_pybullet_source, pybullet_data_dir
from ..model.config import Config, PoseConfig
from ..model.mesh import MeshError, ObjectModel, load_mesh
from ..model.poses import PoseSet, face_below, stable_poses

OUTSIDE = -1
"""Final pose outside the model's pose set: the last bucket of every distribution."""
SAME_PUSH_TOLERANCE = 1e-6
"""m (points) and unit-vector components (directions): repeats of one push must agree this closely."""
START_TILTED, START_MERGED_COPY = -1, -2
"""Start pose codes of rows that match no stable pose."""
EXAMPLES_PER_REASON = 5
"""Rejected rows kept as examples per reason (all are counted)."""


def empirical_distribution(outcomes: np.ndarray, n_poses: int) -> np.ndarray:
    """Next-pose frequencies of observed outcomes.

    outcomes : (R,) int, pose indices or ``OUTSIDE``
    returns : (n_poses + 1,) float, the last bucket is ``OUTSIDE``; sums to 1
    """
    buckets = np.where(np.asarray(outcomes) < 0, n_poses, outcomes)
    return np.bincount(buckets, minlength=n_poses + 1) / len(outcomes)


STROKE_TOLERANCE = 1e-6
"""m; a row's push_depth within this of ``topple.stroke`` is the model's push (float32 logs round)."""


class LogError(ValueError):
    """A log that cannot be read at all (missing file, not Parquet, wrong columns); one line."""


@dataclass
class LoggedObject:
    """One object of the log, loaded and checked.

    model : the mesh as the toppling model sees it;  poses : its stable poses
    sha256 : the mesh file's digest;  in_corpus : whether the object is in the given corpus
    """

    object_id: str
    model: ObjectModel
    poses: PoseSet
    sha256: str
    in_corpus: bool | None = None


@dataclass
class Push:
    """One push and what its repeats did.

    object_id, push_id : identifiers;  pose : start pose index
    point, direction : (3,) float, pose frame (m, unit)
    outcomes : (R,) int, final pose of each repeat (``OUTSIDE`` when not in the pose set)
    log : which log the push was read from, an index into ``PushLog.logs`` (push ids are unique only
      within one)
    repeats : (R,) int, the log's repeat number of each outcome (None for a push not read from a log)
    """

    object_id: str
    push_id: int
    pose: int
    point: np.ndarray
    direction: np.ndarray
    outcomes: np.ndarray
    log: int = 0
    repeats: np.ndarray | None = None

    @property
    def key(self) -> tuple[int, str, int]:
        """(log, object id, push id): what names this push among the logs read together."""
        return self.log, self.object_id, self.push_id

    def empirical(self, n_poses: int) -> np.ndarray:
        """(n_poses + 1,) float: frequency of each final pose, the last entry for ``OUTSIDE``."""
        return empirical_distribution(self.outcomes, n_poses)

    @property
    def topple_rate(self) -> float:
        """Fraction of repeats that left the start pose (outside the pose set counts as toppled)."""
        return float(np.mean(self.outcomes != self.pose))


@dataclass
class PushLog:
    """A log read against the model.

    objects : object id -> ``LoggedObject`` (only objects with at least one usable row)
    pushes : usable pushes, sorted by (object, pose, log, push_id)
    rejected : reason -> rows;  examples : reason -> [(file, row, object_id, push_id), ...]
    rows : rows read in all;  files : the files read
    logs : the logs read, each a file or directory (``logs_under``), in ``Push.log``'s numbering
    """

    objects: dict[str, LoggedObject]
    pushes: list[Push]
    rejected: Counter = field(default_factory=Counter)
    examples: dict[str, list[tuple[str, int, str, int]]] = field(default_factory=dict)
    rows: int = 0
    files: list[str] = field(default_factory=list)
    logs: list[str] = field(default_factory=list)

    def log_name(self, number: int) -> str:
        """How to name log ``number`` (``Push.log``) to a user: its file or directory, when known."""
        return self.logs[number] if number < len(self.logs) else f"number {number + 1}"

    @property
    def rows_used(self) -> int:
        return int(sum(len(p.outcomes) for p in self.pushes))

    def counts(self) -> dict:
        """Counts for reports: rows read / used / rejected by reason, pushes, repeats, objects, poses."""
        repeats = [len(p.outcomes) for p in self.pushes]
        return {
            "rows": self.rows,
            "rows_used": self.rows_used,
            "rows_rejected": int(sum(self.rejected.values())),
            "rejected_by_reason": dict(sorted(self.rejected.items(), key=lambda kv: -kv[1])),
            "pushes": len(self.pushes),
            "repeats_min": int(min(repeats)) if repeats else 0,
            "repeats_max": int(max(repeats)) if repeats else 0,
            "objects": len({p.object_id for p in self.pushes}),
            "start_poses": len({(p.object_id, p.pose) for p in self.pushes}),
        }

    def subset(self, object_ids) -> PushLog:
        """The same log restricted to some objects (counts of rejected rows are kept whole)."""
        keep = set(object_ids)
        return PushLog(
            {k: v for k, v in self.objects.items() if k in keep},
            [p for p in self.pushes if p.object_id in keep],
            self.rejected,
            self.examples,
            self.rows,
            self.files,
            self.logs,
        )


# ---------------------------------------------------------------- files


def same_push(a: Push, b: Push) -> bool:
    """Whether two logs' pushes are one push: the same start pose, and point and direction (pose frame)
    within ``SAME_PUSH_TOLERANCE``."""
    return a.pose == b.pose and bool(np.allclose(a.point, b.point, rtol=0, atol=SAME_PUSH_TOLERANCE)
                                     and np.allclose(a.direction, b.direction, rtol=0, atol=SAME_PUSH_TOLERANCE))


def log_files(paths: list[str | Path]) -> list[Path]:
    """Parquet files named by ``paths``: files as given, directories searched recursively
    (skipping names that start with "_" or ".")."""
    files: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = _files_under(path)
            if not found:
                raise LogError(f"no .parquet files under {path}")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise LogError(f"push log not found: {path}")
    return files


def logs_under(path: str | Path) -> list[tuple[Path, list[Path]]]:
    """The logs ``path`` names, each (its file or directory, its Parquet files per ``log_files``).

    A file is one log, and so is a directory with Parquet files of its own, with every file under
    it.  A directory with none of its own but subdirectories that hold them (``data/logs``) is its
    subdirectories' logs, one each with every file under it, in name order; subdirectories whose
    names start with "_" or "." are skipped, as such files are.
    """
    path = Path(path)
    if not path.is_dir() or any(_is_log_file(p) for p in path.glob("*.parquet")):
        return [(path, log_files([path]))]
    children = sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith(("_", ".")))
    logs = [(child, files) for child in children if (files := _files_under(child))]
    if not logs:
        raise LogError(f"no .parquet files under {path}")
    return logs


def _is_log_file(path: Path) -> bool:
    """A Parquet file of a log: not one of the writer's own ("_" or "." names, run records and temporaries)."""
    return path.is_file() and not path.name.startswith(("_", "."))


def _files_under(directory: Path) -> list[Path]:
    return sorted(p for p in directory.rglob("*.parquet") if _is_log_file(p))


def read_tables(files: list[Path], logs: list[int] | None = None) -> pa.Table:
    """All files concatenated, with a ``_file``, ``_row``, ``_log`` and ``_world`` column (``logs``: the log each
    file belongs to, 0 for all when not given; ``_world``: ``recorded_world`` of the file's metadata); raises
    ``LogError`` on unreadable files."""
    tables = []
    required = set(PUSHLOG.names)
    for number, file in enumerate(files):
        try:
            table = pq.read_table(file)
        except (OSError, pa.ArrowInvalid) as err:
            raise LogError(f"{file}: not a readable Parquet file ({str(err).splitlines()[0]})") from None
        world = recorded_world(table.schema.metadata)
        missing = sorted(required - set(table.column_names))
        if missing:
            raise LogError(f"{file}: not a push log, missing column(s) {', '.join(missing)}")
        empty = [f"{field.name} ({table.column(field.name).null_count})" for field in PUSHLOG
                 if not field.nullable and table.column(field.name).null_count]
        if empty:  # a file another tool wrote; the cast would only say it cannot
            raise LogError(f"{file}: null values in column(s) a push log requires in every row: {', '.join(empty)}")
        try:
            table = table.select(PUSHLOG.names).cast(PUSHLOG)
        except (ValueError, TypeError, pa.ArrowException) as err:  # ArrowInvalid is a ValueError, ArrowTypeError a TypeError
            raise LogError(f"{file}: columns do not have the push-log types ({str(err).splitlines()[0]})") from None
        n = table.num_rows
        table = table.append_column("_file", pa.array([str(file)] * n, type=pa.string())).append_column("_row", pa.array(np.arange(n), type=pa.int64()))
        table = table.append_column("_log", pa.array(np.full(n, logs[number] if logs else 0), type=pa.int64()))
        table = table.append_column("_world", pa.array([world] * n, type=pa.string()))
        tables.append(table)
    return pa.concat_tables(tables)


PLAY_METADATA_KEY = b"toppledb_play"
"""Parquet metadata key of a ``toppledb play`` part file: its per-object parameters and summary (JSON)."""


def recorded_world(metadata: dict[bytes, bytes] | None) -> str | None:
    """The pose parameters a ``toppledb play`` part file was played with, or the dataset a robot's log was
    planned on (``schema.pushlog.write_log``), from its schema ``metadata``, whose numbering its start_pose column
    uses, as the JSON text of a ``PoseConfig``; None for a log that does not record them, which is read in the
    reader's."""
    metadata = metadata or {}
    try:
        if POSES_METADATA_KEY in metadata:
            recorded = json.loads(metadata[POSES_METADATA_KEY])
        else:
            recorded = json.loads(metadata[PLAY_METADATA_KEY])["key"]["config"]["poses"]
        poses = PoseConfig(**{f.name: recorded[f.name] for f in fields(PoseConfig) if f.name in recorded})
    except (KeyError, TypeError, ValueError):
        return None
    return json.dumps(asdict(poses), sort_keys=True)


def same_numbering(logged: PoseConfig, reader: PoseConfig, poses: PoseSet) -> bool:
    """Whether a log played with ``logged`` numbers an object's stable poses as ``reader`` does (``poses``, the
    object's set under ``reader``): the same parameters, or only the merging differs and the reader, merging, found
    nothing to merge."""
    if logged == reader:
        return True
    only_merging = logged == replace(reader, merge_symmetric=logged.merge_symmetric)
    return only_merging and reader.merge_symmetric and poses.equivalents is None


def resolve_mesh(source: str, path: str, log_file: str) -> Path:
    """The mesh file a row names: relative to pybullet_data, absolute, or relative to the log file."""
    if is_pybullet_source(source):
        return pybullet_data_dir() / path
    candidate = Path(path)
    return candidate if candidate.is_absolute() else Path(log_file).parent / candidate


# ---------------------------------------------------------------- reading against the model


class _Rejections:
    def __init__(self) -> None:
        self.counts: Counter = Counter()
        self.examples: dict[str, list] = {}

    def add(self, reason: str, file: str, row: int, object_id: str, push_id: int) -> None:
        self.counts[reason] += 1
        examples = self.examples.setdefault(reason, [])
        if len(examples) < EXAMPLES_PER_REASON:
            examples.append((file, int(row), object_id, int(push_id)))


def read_log(
    paths: list[str | Path],
    config: Config = Config(),
    corpus: Corpus | None = None,
    *,
    corpus_only: bool = False,
    exclude_corpus: bool = False,
) -> PushLog:
    """Read push logs and match every row to the model's stable poses.

    paths : logs: Parquet files, directories of them, or directories of such directories (``logs_under``)
    config : ``config.mesh`` loads the meshes, ``config.poses`` gives the stable poses
    corpus : when given, each object is looked up in it (``LoggedObject.in_corpus``);
      ``corpus_only`` rejects rows of objects outside it (calibration), ``exclude_corpus``
      rejects rows of objects inside it (a held-out report)
    Raises ``LogError`` only when a file cannot be read as a push log at all.
    """
    # Push ids are unique within one log: a directory of several logs is read as those logs.
    logs = [log for path in paths for log in logs_under(path)]
    per_log = [found for _, found in logs]
    files = [file for found in per_log for file in found]
    twice = [file for file, count in Counter(f.resolve() for f in files).items() if count > 1]
    if twice:
        # Each log's pushes are its own (Push.log), so a file read twice would count its pushes twice.
        raise LogError(f"{twice[0]} is named twice among the logs; name each log once")
    table = read_tables(files, [number for number, found in enumerate(per_log) for _ in found])
    n = table.num_rows
    columns = {name: table.column(name).to_pylist() for name in ("object_id", "mesh_sha256", "mesh_source", "mesh_path", "_file")}
    scale = table.column("scale").to_numpy(zero_copy_only=False).astype(float)
    mass = table.column("mass").to_numpy(zero_copy_only=False).astype(float)
    push_id = table.column("push_id").to_numpy(zero_copy_only=False)
    log_of_row = table.column("_log").to_numpy(zero_copy_only=False)
    row_number = table.column("_row").to_numpy(zero_copy_only=False)
    start_pose = table.column("start_pose").to_pylist()
    problems = row_problems(table)
    if "stroke" in config.topple.applied_corrections:
        # The model predicts a push of its own stroke (MODEL.md C.10): a row pushed deeper or
        # shallower is another push, which it would score wrongly.
        depth = table.column("push_depth").to_numpy(zero_copy_only=False).astype(float)
        for i in np.flatnonzero(~(np.abs(depth - config.topple.stroke) <= STROKE_TOLERANCE)):
            problems[i] = problems[i] or (
                f"push_depth {depth[i]:g} m is not the model's stroke (topple.stroke {config.topple.stroke:g} m); "
                "score it with a configuration of that stroke"
            )
    rejections = _Rejections()

    def reject(i: int, reason: str) -> None:
        rejections.add(reason, columns["_file"][i], row_number[i], columns["object_id"][i], push_id[i])

    # Objects: one mesh per object id, checked once.
    loaded: dict[str, LoggedObject] = {}
    object_problem: dict[tuple, str | None] = {}
    identity_of: dict[str, tuple] = {}
    usable = np.zeros(n, dtype=bool)
    for i in range(n):
        if problems[i] is not None:
            reject(i, problems[i])
            continue
        object_id = columns["object_id"][i]
        identity = (columns["mesh_sha256"][i], columns["mesh_source"][i], columns["mesh_path"][i], scale[i], mass[i])
        first = identity_of.setdefault(object_id, identity)
        if first != identity:
            reject(i, "object_id logged with a different mesh, scale or mass than its first row")
            continue
        key = (object_id, *identity, columns["_file"][i] if columns["mesh_source"][i] == "file" else "")
        if key not in object_problem:
            object_problem[key] = _load_object(key, config, corpus, corpus_only, exclude_corpus, loaded)
        if object_problem[key] is not None:
            reject(i, object_problem[key])
            continue
        usable[i] = True

    # Poses: start matched within the same-pose angle, final settled.
    start = _matrices(table, "start_transform")
    final = _matrices(table, "final_transform")
    points = _vectors(table, "point")
    directions = unit(_vectors(table, "direction"))
    start_index = np.full(n, -1)
    logged_index = np.full(n, -1)  # the start's pose as the log's own world numbers its poses
    world_of_row = np.array(table.column("_world").to_pylist(), dtype=object)
    orientation = np.full(n, -1)  # index into the object's PoseSet.match_arrays()
    final_index = np.full(n, OUTSIDE)
    object_of_row = np.array(columns["object_id"], dtype=object)
    for object_id, obj in loaded.items():
        rows = np.flatnonzero(usable & (object_of_row == object_id))
        if len(rows) == 0:
            continue
        # match_pose and settle, vectorised over the object's rows.
        downs = object_downs(start[rows])
        # Every orientation that is a pose, a symmetric object's merged turns included.
        match_down, match_transform, match_owner = obj.poses.match_arrays()
        oriented, _ = match_downs(downs, match_down, config.poses.same_pose_angle)
        matched = np.where(oriented >= 0, match_owner[np.maximum(oriented, 0)], -1)
        orientation[rows] = oriented
        unmatched = np.flatnonzero(matched < 0)
        if len(unmatched):
            # Why not: tilted, or at rest on a facet merged into a pose whose down vector is another
            # (a symmetric object's copy of the pose: the push would need that symmetry to be mapped).
            hull = obj.model.hull
            face = face_below(hull, obj.model.center_mass, downs[unmatched])
            tilt = np.arccos(np.clip(np.einsum("ij,ij->i", downs[unmatched], hull.face_normals[face]), -1.0, 1.0))
            resting = (tilt <= config.poses.same_pose_angle) & (obj.poses.face_pose[face] >= 0)
            matched[unmatched] = np.where(resting, START_MERGED_COPY, START_TILTED)
        face = face_below(obj.model.hull, obj.model.center_mass, object_downs(final[rows]))
        start_index[rows] = matched
        final_index[rows] = obj.poses.face_pose[face]
        # The start_pose column numbers the poses of the world the log was played in.  A part file of
        # ``toppledb play`` records its pose parameters; the thesis's world, where every simulated log is
        # played, does not merge symmetric poses where the default does, and merging renumbers them.
        numbered = matched.copy()
        worlds = world_of_row[rows]
        for world in dict.fromkeys(worlds):
            if world is None:
                continue
            logged = PoseConfig(**json.loads(world))
            if same_numbering(logged, config.poses, obj.poses):
                continue
            in_world = worlds == world
            logged_downs, _, logged_owner = stable_poses(obj.model, logged).match_arrays()
            oriented, _ = match_downs(downs[in_world], logged_downs, logged.same_pose_angle)
            numbered[in_world] = np.where(oriented >= 0, logged_owner[np.maximum(oriented, 0)], -1)
        logged_index[rows] = numbered
    for i in np.flatnonzero(usable):
        if start_index[i] == START_TILTED:
            reject(i, "start pose matches no stable pose (tilted beyond poses.same_pose_angle)")
            usable[i] = False
        elif start_index[i] == START_MERGED_COPY:
            reject(i, "start pose rests on a copy of a stable pose merged into it (symmetry), not the pose's own orientation")
            usable[i] = False
        elif start_pose[i] is not None and start_pose[i] != logged_index[i]:
            reject(i, "start_pose column disagrees with the pose start_transform matches")
            usable[i] = False

    # Pushes: repeats of one (log, object, push_id) must describe the same push.  Two logs may
    # draw the same id for other pushes, or the same push, and each keeps its own repeats; but a
    # row an earlier log already holds, the very same play (a log that is part of another, or a
    # copy of one file in two logs), would count its push twice: it is rejected, and counted.
    repeat = table.column("repeat").to_numpy(zero_copy_only=False)
    played: dict[tuple, int] = {}
    groups: dict[tuple[int, str, int], list[int]] = {}
    for i in np.flatnonzero(usable):
        signature = (columns["object_id"][i], int(push_id[i]), int(repeat[i]),
                     start[i].tobytes(), final[i].tobytes(), points[i].tobytes(), directions[i].tobytes())
        if played.setdefault(signature, int(log_of_row[i])) != log_of_row[i]:
            reject(i, "the same row (push, repeat, start, point, direction, final) as in an earlier log")
            continue
        groups.setdefault((int(log_of_row[i]), columns["object_id"][i], int(push_id[i])), []).append(int(i))
    pushes = []
    for (log, object_id, pid), rows in groups.items():
        rows = np.array(rows)
        _, first_of_repeat = np.unique(repeat[rows], return_index=True)
        for i in np.setdiff1d(np.arange(len(rows)), first_of_repeat):
            reject(rows[i], "duplicate (push_id, repeat)")
        rows = rows[np.sort(first_of_repeat)]
        same = (
            np.all(start_index[rows] == start_index[rows[0]])
            and np.all(orientation[rows] == orientation[rows[0]])
            and np.abs(points[rows] - points[rows[0]]).max() <= SAME_PUSH_TOLERANCE
            and np.abs(directions[rows] - directions[rows[0]]).max() <= SAME_PUSH_TOLERANCE
        )
        if not same:
            for i in rows:
                reject(i, "repeats of one push_id disagree on start pose, point or direction")
            continue
        obj = loaded[object_id]
        pose = obj.poses.poses[int(start_index[rows[0]])]
        to_pose = obj.poses.match_arrays()[1][int(orientation[rows[0]])]  # the pose's transform, or its merged turn's
        pushes.append(
            Push(
                object_id=object_id,
                push_id=pid,
                pose=pose.index,
                point=transform_points(to_pose, points[rows[0]][None])[0],
                direction=directions[rows[0]] @ to_pose[:3, :3].T,
                outcomes=final_index[rows],
                log=log,
                repeats=repeat[rows].astype(int),
            )
        )
    pushes.sort(key=lambda p: (p.object_id, p.pose, p.log, p.push_id))  # by object and pose, then ``Push.key``
    used = {p.object_id for p in pushes}
    return PushLog(
        objects={k: v for k, v in loaded.items() if k in used},
        pushes=pushes,
        rejected=rejections.counts,
        examples=rejections.examples,
        rows=n,
        files=[str(f) for f in files],
        logs=[str(name) for name, _ in logs],
    )


def _load_object(key: tuple, config: Config, corpus: Corpus | None, corpus_only: bool, exclude_corpus: bool,
                 loaded: dict[str, LoggedObject]) -> str | None:
    """Load one logged object into ``loaded``; returns the reason it cannot be used, or None."""
    object_id, sha256, source, path, scale, mass, log_file = key
    spec = None
    if corpus is not None:
        spec = next((s for s in corpus.specs if s.object_id == object_id), None)
        if corpus_only and spec is None:
            return "object not in the calibration corpus"
        if exclude_corpus and spec is not None:
            return "object is in the calibration corpus (not held out)"
        if spec is not None and spec.sha256 and spec.sha256 != sha256:
            return "mesh_sha256 differs from the corpus's mesh of this object_id"
    try:
        file = resolve_mesh(source, path, log_file)
    except CorpusError as err:  # pybullet_data is not installed
        return f"unknown object: {err}"
    if not file.is_file():
        return "unknown object: mesh file not found"
    digest = file_sha256(file)
    if digest != sha256:
        return "mesh changed: file sha256 differs from mesh_sha256"
    try:
        model = load_mesh(file, scale=scale, mass=mass, name=object_id, config=config.mesh)
        poses = stable_poses(model, config.poses)
    except MeshError as err:
        return f"mesh unusable: {str(err).split(': ', 1)[-1]}"
    loaded[object_id] = LoggedObject(object_id, model, poses, digest, None if corpus is None else spec is not None)
    return None


def object_downs(transforms: np.ndarray) -> np.ndarray:
    """World down (0, 0, -1) in the object frame of each object -> world transform: (n, 4, 4) -> (n, 3)."""
    return np.einsum("nji,j->ni", transforms[:, :3, :3], DOWN)


def match_downs(downs: np.ndarray, pose_downs: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """``schema.frames.match_pose``'s pose choice for many observations: the stable pose with the
    nearest down vector, -1 beyond ``tolerance``.

    downs : (n, 3) float, unit, object frame;  pose_downs : (P, 3) float;  tolerance : rad
    returns : pose (n,) int, angle_error (n,) float, rad
    """
    angles = np.arccos(np.clip(downs @ pose_downs.T, -1.0, 1.0))
    best = np.argmin(angles, axis=1)
    error = angles[np.arange(len(downs)), best]
    return np.where(error <= tolerance, best, -1), error


def _matrices(table: pa.Table, name: str) -> np.ndarray:
    """(n, 4, 4) float; rows with a missing matrix are NaN (row_problems has rejected them)."""
    column = table.column(name).combine_chunks()
    if column.null_count == 0:
        return np.asarray(column.flatten().to_numpy(zero_copy_only=False), dtype=float).reshape(-1, 4, 4)
    values = column.to_pylist()
    return np.array([np.full(16, math.nan) if v is None else v for v in values], dtype=float).reshape(-1, 4, 4)


def _vectors(table: pa.Table, prefix: str) -> np.ndarray:
    return np.stack([table.column(f"{prefix}_{a}").to_numpy(zero_copy_only=False) for a in "xyz"], axis=1).astype(float)
