"""``toppledb play``: a push-outcome log made by the push player (thesis 4.4.2).

For every chosen object and each of its most probable stable poses, the robust
model evaluates the pose's candidate pushes; ``--actions`` distinct ``ok`` pushes
are drawn with probability proportional to P(topple) + eps (the thesis's sampling,
which favours pushes the model expects to topple without leaving out the rest), and
each is played ``--repeats`` times in pybullet under the model's noise on friction,
contact point and push direction.  Every played push is one row of the push log
(``schema.pushlog``), the same table a robot team logs its own pushes in.

Objects: ``corpus`` draws from the dataset's default corpus (to calibrate on);
``heldout`` from pybullet_data's objects outside it: the named meshes it does not
list, then random objects it does not list, in an order shuffled by the seed.  Any
other value is a corpus of one's own, as ``toppledb dataset --corpus`` takes it (a CSV
list file or a directory of meshes), played in its own order; its objects whose file
is missing or changed are reported and left out.

    toppledb play --objects corpus --count 40 --out data/logs/corpus
    toppledb play --objects heldout --count 40 --out data/logs/heldout
    toppledb play --objects my_objects.csv --out data/logs/mine

The log is a directory: one Parquet file per object (``<object_id>.parquet``, written
atomically once the object is done, with the parameters it was made with in its
metadata) and ``_play.json`` (the run's parameters and counts; readers skip names
starting with ``_`` or ``.``).  A killed run resumes: the same command skips every
object whose file exists with the same parameters.  Every random draw comes from
``rng.stream(seed, object_id, pose, "play")``, so the log does not depend on the
number of workers.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema.pushlog import PUSHLOG, PUSHLOG_VERSION, row_problems
from schema.vocabulary import STATUS_OK

from ..build.atomic import write_atomic, write_text_atomic
from ..build.corpus import (
    DEFAULT_LIST,
    PYBULLET_SOURCE,
    CorpusError,
    ObjectSpec,
    candidate_specs,
    is_pybullet_source,
    load_corpus,
    pybullet_data_dir,
    read_list,
    write_list,
)
from ..model.config import PRESETS, Config, parameter_table
from ..model.rng import stream
from .logreader import PLAY_METADATA_KEY, LogError, log_files, match_downs, object_downs, read_tables
from .pushsim import (
    DEFAULT_PLAYER,
    FINGER_SPEED,
    PlayedPush,
    PlayerSettings,
    add_player_options,
    body_model,
    draw_noise,
    play_push,
    player_from_args,
    player_parameters,
)

OBJECT_MODES = ("corpus", "heldout")
PURPOSE = "play"
"""Random stream purpose of the push draws, and of their noise in a log."""
REPLAY_PURPOSE = "replay"
"""Random stream purpose of the noise of a replay (``PlayParams.noise_draws`` > 0)."""
SELECTION_STREAM = -1
"""``pose`` argument of the stream that orders the candidate objects (a per-object draw)."""
PUSH_ID_SPAN = 10_000
"""push_id = pose * PUSH_ID_SPAN + action: unique within an object, readable, the same for a push's repeats."""
DEFAULT_EPS = 0.05
RUN_FILE = "_play.json"
SOURCE = "pybullet"


class PlayError(ValueError):
    """Bad play input (unknown mode, a log directory made with other parameters); one line."""


# ---------------------------------------------------------------- parameters


@dataclass(frozen=True)
class PlayParams:
    """What decides a part file's content (besides the object itself).

    actions : pushes drawn per pose;  repeats : noisy plays of each push
    eps : added to every P(topple) before sampling;  max_poses : most probable poses per object (all: None)
    seed : root of the play's draws (the model's own candidates use ``config.seed``)
    noise_draws : 0: the noise comes from the stream the pushes were drawn from (a log);
      k > 0: the same pushes, played with the k-th independent set of noise draws (a replay
      of a log, which the report scores as physics predicting itself)
    player : the player's numerics (``pushsim.PlayerSettings``); every log of the docs has the default, and
      another plays the same pushes with the same noise draws (the judge against its own numerics)
    """

    actions: int = 3
    repeats: int = 10
    eps: float = DEFAULT_EPS
    max_poses: int | None = 4
    seed: int = 0
    config: Config = field(default_factory=Config)
    noise_draws: int = 0
    player: PlayerSettings = DEFAULT_PLAYER

    def record(self) -> dict:
        """The parameters as JSON-ready values (with the player's constants and the log version)."""
        record = {
            "actions": self.actions,
            "repeats": self.repeats,
            "eps": self.eps,
            "max_poses": self.max_poses,
            "seed": self.seed,
            "config": self.config.to_dict(),
            "player": player_parameters(self.player),
            "pushlog_version": PUSHLOG_VERSION,
        }
        if self.noise_draws:  # absent means 0, so the part files of logs made before the option are reused
            record["noise_draws"] = self.noise_draws
        return record

    def noise_stream(self, object_id: str, pose: int, play_rng: np.random.Generator) -> np.random.Generator:
        """Where the noise of one pose's plays comes from: the play's own stream (after the
        push draws), or the ``noise_draws``-th child of the pose's ``replay`` stream."""
        if not self.noise_draws:
            return play_rng
        return stream(self.seed, object_id, pose, REPLAY_PURPOSE).spawn(self.noise_draws)[-1]

    def key(self, spec: ObjectSpec) -> dict:
        """Everything that makes one object's rows; a part file is reused only when this is equal."""
        return {"object_id": spec.object_id, "mesh_sha256": spec.sha256, "scale": spec.scale, "mass": spec.mass, **self.record()}


# ---------------------------------------------------------------- which objects


@functools.lru_cache(maxsize=4)
def corpus_specs(default_mass: float) -> tuple[ObjectSpec, ...]:
    """The default corpus's objects whose files are present and unchanged."""
    corpus = read_list(DEFAULT_LIST, default_mass, name="default")
    return tuple(s for s in corpus.specs if s.object_id not in corpus.problems)


@functools.lru_cache(maxsize=4)  # hashing pybullet_data's ~1,000 meshes takes seconds
def heldout_specs(default_mass: float) -> tuple[ObjectSpec, ...]:
    """pybullet_data's candidate objects that the default corpus does not list.

    An object is excluded when its id, its mesh file or its mesh's SHA-256 is the
    corpus's, so a renamed copy of a corpus mesh is not held out either.
    """
    corpus = read_list(DEFAULT_LIST, default_mass, name="default").specs
    ids = {s.object_id for s in corpus}
    paths = {str(Path(s.path).resolve()) for s in corpus}
    digests = {s.sha256 for s in corpus if s.sha256}
    return tuple(
        s
        for s in candidate_specs(default_mass)
        if s.object_id not in ids and str(Path(s.path).resolve()) not in paths and s.sha256 not in digests and s.sha256
    )


def own_specs(corpus: str | Path, default_mass: float) -> list[ObjectSpec]:
    """A corpus of one's own, read as ``toppledb dataset --corpus`` reads a CSV list file or a directory of meshes
    (its sidecar's units and masses; there are no --units flags here), in its order; entries whose file is
    missing or changed are left out, each reported on stderr."""
    path = Path(corpus)
    if not path.exists():
        raise PlayError(f"--objects {corpus}: not 'corpus', 'heldout', a corpus list file or a directory of meshes")
    found = load_corpus(str(path), default_mass)
    for object_id, reason in found.problems.items():
        print(f"not played: {object_id}: {reason}", file=sys.stderr)
    usable = [s for s in found.specs if s.object_id not in found.problems]
    if not usable:
        raise PlayError(f"--objects {corpus}: none of its {len(found.specs)} objects has its mesh file as listed")
    return usable


def select_objects(mode: str, count: int | None, seed: int, default_mass: float, skip: int = 0) -> list[ObjectSpec]:
    """``count`` objects (all when None) in a seeded order; a larger count extends a smaller one.

    corpus : the default corpus, shuffled;  heldout : the named meshes outside it first
    (there are few and they are the realistic ones), then the random objects outside it, shuffled;
    any other mode : a corpus list file or a directory of meshes (``own_specs``), in its own order.
    skip : objects of that order passed over first, so a second log holds none of an earlier
      one's (``--skip 100 --count 50`` after a log or dataset of ``--count 100``)
    """
    if skip < 0:
        raise PlayError(f"--skip must be 0 or more, got {skip}")
    if mode in OBJECT_MODES:
        specs = corpus_specs(default_mass) if mode == "corpus" else heldout_specs(default_mass)
        named = [s for s in specs if mode == "heldout" and not s.object_id.startswith("random_")]
        rest = [s for s in specs if s not in named]
        order = stream(seed, f"select:{mode}", SELECTION_STREAM, PURPOSE).permutation(len(rest))
        chosen = named + [rest[i] for i in order]
    else:
        specs = chosen = own_specs(mode, default_mass)
    chosen = chosen[skip:]
    if not chosen:
        raise PlayError(f"--skip {skip} passes over all {len(specs)} {mode} objects")
    return chosen[:count]  # all of them when count is None


# ---------------------------------------------------------------- one object


def sample_actions(p_topple: np.ndarray, status: np.ndarray, k: int, rng: np.random.Generator, eps: float) -> np.ndarray:
    """Up to ``k`` distinct ``ok`` actions, drawn with probability proportional to P(topple) + eps (thesis 4.4.2).

    p_topple : (A,) float (NaN for actions that are not ok);  status : (A,) int8
    returns : (min(k, #ok),) int, action indices, ascending
    """
    ok = np.flatnonzero(status == STATUS_OK)
    if len(ok) == 0 or k < 1:
        return ok[:0]
    weights = np.nan_to_num(p_topple[ok]) + eps
    return np.sort(rng.choice(ok, size=min(k, len(ok)), replace=False, p=weights / weights.sum()))


def mesh_location(spec: ObjectSpec) -> tuple[str, str]:
    """(mesh_source, mesh_path) of a log row: relative to pybullet_data when it comes from there."""
    if is_pybullet_source(spec.source):
        try:
            return PYBULLET_SOURCE, Path(spec.path).resolve().relative_to(pybullet_data_dir().resolve()).as_posix()
        except (ValueError, CorpusError):
            pass
    return "file", str(Path(spec.path).resolve())


@dataclass
class ObjectLog:
    """One object's played pushes: its log rows (``table``) and what happened, or why it failed."""

    object_id: str
    table: pa.Table
    key: dict
    summary: dict


def play_object(spec: ObjectSpec, params: PlayParams) -> ObjectLog:
    """Choose and play one object's pushes (runs in a worker); never raises for a bad object."""
    from ..model.evaluation import evaluate, load_object
    from ..model.mesh import MeshError
    from ..model.poses import settle, stable_poses

    config = params.config
    key = params.key(spec)
    try:
        obj = load_object(spec, config)
        pose_set = stable_poses(obj, config.poses)
    except MeshError as err:
        return ObjectLog(spec.object_id, empty_log(), key, {"failure": str(err), "pushes": 0, "moved_before": 0})
    body = body_model(obj)
    source, path = mesh_location(spec)
    columns: dict[str, list] = {f.name: [] for f in PUSHLOG}
    n_poses = len(pose_set.poses) if params.max_poses is None else min(params.max_poses, len(pose_set.poses))
    toppled = at_rest = outside = moved_before = 0
    for pose in range(n_poses):
        rng = stream(params.seed, spec.object_id, pose, PURPOSE)
        table = evaluate(obj, pose_set, pose, variant="robust", seed=config.seed, config=config)
        chosen = sample_actions(table.table.p_topple, table.actions.status, params.actions, rng, params.eps)
        noise = params.noise_stream(spec.object_id, pose, rng)
        transform = pose_set.poses[pose].transform
        to_object = np.linalg.inv(transform)
        for action in chosen:
            point = to_object[:3, :3] @ table.actions.points[action] + to_object[:3, 3]
            direction = to_object[:3, :3] @ table.actions.directions[action]
            for repeat in range(params.repeats):
                played = play_push(body, transform, point, direction, config, draw_noise(config, noise, noise=True),
                                   settings=params.player)
                final_pose = settle(pose_set, obj, played.final_transform[:3, :3])
                toppled += int(final_pose != pose)
                outside += int(final_pose < 0)
                at_rest += int(played.at_rest)
                moved_before += int(left_pose(played.start_transform, pose_set.poses[pose].down, config.poses.same_pose_angle))
                append_row(columns, spec, source, path, pose * PUSH_ID_SPAN + int(action), repeat, pose, int(action),
                            point, direction, played, config, params.seed, params.player.finger_speed)
    table = pa.Table.from_pydict(columns, schema=PUSHLOG)
    summary = {"poses": n_poses, "pushes": table.num_rows, "toppled": toppled, "outside": outside, "at_rest": at_rest,
               "moved_before": moved_before}
    return ObjectLog(spec.object_id, table, key, summary)


def left_pose(start_transform: np.ndarray, down: np.ndarray, tolerance: float) -> bool:
    """Whether the object left its stable pose while resting, before the finger came.

    Some poses the model finds stable are not in Bullet (a barely stable facet, rounded
    edges); such rows are still written, with the observed start, and a log reader
    counts them as not matching their start pose.
    start_transform : (4, 4) observed;  down : (3,) unit, the pose's down vector, object frame;  tolerance : rad
    """
    matched, _ = match_downs(object_downs(start_transform[None]), down[None], tolerance)
    return bool(matched[0] < 0)


def append_row(columns, spec, source, path, push_id, repeat, pose, action, point, direction, played: PlayedPush, config, seed,
               finger_speed: float = FINGER_SPEED) -> None:
    """Append one played push to ``columns`` (column name -> values, ``PUSHLOG``'s names).

    spec : the object;  source, path : ``mesh_location(spec)``;  point, direction : (3,) float,
    object frame, the push as commanded (the noise is in ``played``);  config : its finger geometry
    finger_speed : float, m/s, what the finger was played at
    """
    c = config.contacts
    row = {
        "object_id": spec.object_id,
        "mesh_sha256": spec.sha256,
        "mesh_source": source,
        "mesh_path": path,
        "scale": float(spec.scale),
        "mass": float(spec.mass),
        "push_id": push_id,
        "repeat": repeat,
        "start_pose": pose,
        "start_transform": played.start_transform.ravel().tolist(),
        "action": action,
        "finger_speed": finger_speed,
        "approach_offset": c.approach_offset,
        "push_depth": c.push_depth,
        "finger_radius": c.finger_radius,
        "final_transform": played.final_transform.ravel().tolist(),
        "mu_table": played.noise.mu_table,
        "mu_finger": played.noise.mu_finger,
        "source": SOURCE,
        "seed": seed,
    }
    for axis, p, d in zip("xyz", point, direction):
        row[f"point_{axis}"], row[f"direction_{axis}"] = float(p), float(d)
    for name, value in row.items():
        columns[name].append(value)


def empty_log() -> pa.Table:
    return PUSHLOG.empty_table()


# ---------------------------------------------------------------- the log directory


def part_path(out: Path, object_id: str) -> Path:
    return out / f"{object_id}.parquet"


def write_part(out: Path, log: ObjectLog) -> None:
    """One object's rows, atomically, with its key and summary in the file's metadata."""
    problems = [p for p in row_problems(log.table) if p is not None]
    if problems:  # a player bug, not bad input: never write a row the contract rejects
        raise RuntimeError(f"{log.object_id}: the player made {len(problems)} invalid row(s): {problems[0]}")
    metadata = dict(PUSHLOG.metadata)
    metadata[PLAY_METADATA_KEY] = json.dumps({"key": log.key, "summary": log.summary}, sort_keys=True).encode()
    table = log.table.replace_schema_metadata(metadata)
    write_atomic(part_path(out, log.object_id), lambda temp: pq.write_table(table, temp), check=lambda temp: pq.read_metadata(temp))


def read_part_record(path: Path) -> dict | None:
    """A part file's recorded key and summary; None when it is unreadable or not ours."""
    try:
        metadata = pq.read_schema(path).metadata or {}
        return json.loads(metadata[PLAY_METADATA_KEY])
    except (OSError, KeyError, ValueError, pa.ArrowException):
        return None


MODEL_FIELDS = {
    "seed": None,
    "mesh": None,
    "poses": None,
    "contacts": None,
    "topple": ("n_trials", "gravity", "mu_table_mean", "mu_table_std", "mu_finger_mean", "mu_finger_std",
               "contact_std", "direction_std", "rotation_std", "ray_offset"),
}
"""The config a log depends on: loading, stable poses, candidate pushes, and of ``topple`` what
the thesis's robust model (which chooses the pushes) and the player's noise read.  Other
fields (variants, corrections, chunk sizes) never change a log, so a part file made before
they were added or changed is still reused.  None: the whole section."""


def relevant(key: dict) -> dict:
    """The part of a part file's key that decides its rows (``MODEL_FIELDS`` of its config)."""
    config = key.get("config", {})
    kept = {}
    for name, names in MODEL_FIELDS.items():
        value = config.get(name)
        kept[name] = value if names is None or not isinstance(value, dict) else {n: value.get(n) for n in names}
    return {**{k: v for k, v in key.items() if k != "config"}, "config": kept}


def _canonical(value):
    """JSON round trip, so that a key compares equal to the key read back from a file."""
    return json.loads(json.dumps(value, sort_keys=True))


@dataclass
class PlaySummary:
    """What a run did: counts over the whole log (reused parts included)."""

    objects: int = 0
    reused: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    poses: int = 0
    pushes: int = 0
    toppled: int = 0
    outside: int = 0
    at_rest: int = 0
    moved_before: int | None = 0
    """None once a reused part file predates the count."""
    wall_s: float = 0.0

    def add(self, summary: dict) -> None:
        self.objects += 1
        for name in ("poses", "pushes", "toppled", "outside", "at_rest"):
            setattr(self, name, getattr(self, name) + int(summary.get(name, 0)))
        known = self.moved_before is not None and "moved_before" in summary
        self.moved_before = self.moved_before + int(summary["moved_before"]) if known else None

    def text(self) -> str:
        rate = self.toppled / self.pushes if self.pushes else float("nan")
        return (
            f"{self.objects} objects ({self.reused} reused, {len(self.failed)} failed to load), {self.poses} poses, "
            f"{self.pushes} pushes: {self.toppled} toppled ({rate:.3f}), {self.outside} into poses outside the set, "
            f"{self.pushes - self.at_rest} still moving at the time cap, "
            f"{'?' if self.moved_before is None else self.moved_before} left their start pose before the push; {self.wall_s:.1f} s"
        )


def play(
    specs: list[ObjectSpec],
    params: PlayParams,
    out: str | Path,
    *,
    workers: int | None = 1,
    progress: bool = False,
    force: bool = False,
    run_info: dict | None = None,
    stop_after: int | None = None,
) -> PlaySummary:
    """Play every object's pushes into ``out`` (one part file per object), resuming what exists.

    force : remove part files of other parameters or of objects not in ``specs`` instead of refusing
    run_info : extra parameters recorded in ``_play.json`` (the command's mode, count, skip)
    stop_after : stop after writing this many new part files (to test resuming)
    """
    from ..build.fanout import map_unordered

    started = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    wanted = {s.object_id for s in specs}
    summary = PlaySummary()
    todo = []
    for existing in sorted(out.glob("*.parquet")):
        if existing.stem not in wanted:
            if not force:
                raise PlayError(f"{out} holds {existing.name}, an object this run does not play; use another --out or --force")
            existing.unlink()
    for spec in specs:
        path = part_path(out, spec.object_id)
        record = read_part_record(path) if path.exists() else None
        if record is not None and relevant(record["key"]) == relevant(_canonical(params.key(spec))):
            summary.add(record["summary"])
            summary.reused += 1
            if "failure" in record["summary"]:
                summary.failed[spec.object_id] = record["summary"]["failure"]
            continue
        if path.exists() and not force:
            raise PlayError(f"{path} was made with other parameters; use another --out or --force")
        todo.append(spec)
    written = 0
    for log in map_unordered(play_object, [(s, params) for s in todo], workers, description="objects", progress=progress):
        write_part(out, log)
        summary.add(log.summary)
        if "failure" in log.summary:
            summary.failed[log.object_id] = log.summary["failure"]
        written += 1
        if stop_after is not None and written >= stop_after:
            break
    summary.wall_s = time.perf_counter() - started
    if stop_after is None or written < stop_after:
        record = {
            "run": run_info or {},
            "parameters": params.record(),
            "objects": [s.object_id for s in specs],
            "summary": dict(summary.__dict__),
        }
        write_text_atomic(out / RUN_FILE, json.dumps(record, indent=1, sort_keys=True) + "\n")
    return summary


def read_log(out: str | Path) -> pa.Table:
    """Every row of a log directory (its part files, in object order), as ``logreader.read_tables`` reads them."""
    try:
        files = log_files([out])
    except LogError:  # no part file yet
        return empty_log()
    return read_tables(files).drop_columns(["_file", "_row", "_log", "_world"])


WORLD_FIELDS = (
    "topple.mu_table_mean", "topple.mu_table_std", "topple.mu_finger_mean", "topple.mu_finger_std",
    "topple.contact_std", "topple.direction_std", "topple.max_finger_force", "topple.gravity",
    "contacts.approach_offset", "contacts.push_depth", "contacts.finger_radius", "mesh.default_mass",
)
"""The settings the player builds its world from: each repeat's friction and noise
(``pushsim.draw_noise``), the finger's force limit, size and stroke, gravity, and the mass of an
object whose URDF gives none."""


def world_note(config: Config) -> str | None:
    """A note when ``config`` plays pushes in another world than the thesis's, None when it does not.

    The player builds its world from the configuration it is given, so a log played with the
    default model's broad calibrated noise (or another finger, force limit or gravity) is another
    simulated world than the shipped logs' (all played with ``--config thesis``), and a map fitted
    on one is judged on the other."""
    mine = {key: value for key, value, _ in parameter_table(config)}
    thesis = {key: value for key, value, _ in parameter_table(Config.from_toml(PRESETS / "thesis.toml"))}
    differ = [key for key in WORLD_FIELDS if mine[key] != thesis[key]]
    if not differ:
        return None
    values = ", ".join(f"{key.split('.')[1]} {mine[key]:g}" for key in differ)
    return (f"note: the pushes are played in this configuration's world ({values}), not the "
            "thesis's that the shipped logs are played with (--config thesis)")


# ---------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    """``toppledb play``: choose objects, play their pushes, write the log; prints a summary line."""
    from ..cli import UsageError, make_config, path_arg, positive_int

    parser = argparse.ArgumentParser(prog="toppledb play", description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default="corpus", metavar="corpus|heldout|CORPUS",
                        help="'corpus': the default corpus (to calibrate on); 'heldout': pybullet_data objects outside "
                             "it; or a corpus of one's own as `toppledb dataset --corpus` takes it, a CSV list file or "
                             "a directory of meshes, played in its order (default: %(default)s)")
    parser.add_argument("--out", type=path_arg, help="log directory (one Parquet file per object); required unless --list")
    parser.add_argument("--list", type=Path, metavar="FILE.csv",
                        help="write the chosen objects as a corpus list and play nothing: `toppledb dataset --corpus "
                             "FILE.csv` then builds the dataset of the very objects a log of these arguments plays")
    parser.add_argument("--count", type=positive_int, metavar="N", help="objects to play (default: all of the mode's)")
    parser.add_argument("--skip", type=int, default=0, metavar="N",
                        help="pass over the first N objects of the seeded order, e.g. those an earlier log of "
                             "--count N and the same --seed holds: a log on fresh objects (default: %(default)s)")
    parser.add_argument("--max-poses", type=positive_int, default=PlayParams.max_poses, metavar="P",
                        help="each object's P most probable poses (default: %(default)s)")
    parser.add_argument("--actions", type=positive_int, default=PlayParams.actions, metavar="N",
                        help="pushes drawn per pose, P(topple) + eps weighted (default: %(default)s)")
    parser.add_argument("--repeats", type=positive_int, default=PlayParams.repeats, metavar="R",
                        help="noisy plays of each push (default: %(default)s)")
    parser.add_argument("--eps", type=float, default=DEFAULT_EPS, help="added to P(topple) when sampling pushes (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the play's draws (default: %(default)s)")
    parser.add_argument("--noise-draws", type=int, default=0, metavar="K",
                        help="0: a log (default); K > 0: the same pushes as the log of these arguments, played with "
                             "the K-th independent set of noise draws (a replay, for `report --replay`)")
    add_player_options(parser)
    parser.add_argument("--workers", type=positive_int, help="worker processes (default: all cores)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="model and noise parameters from a TOML file")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one parameter, e.g. --set topple.mu_table_std=0.05 (repeatable)")
    parser.add_argument("--force", action="store_true", help="replace part files made with other parameters")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        if not np.isfinite(args.eps) or args.eps <= 0:
            raise UsageError(f"--eps must be positive, got {args.eps}")
        if args.noise_draws < 0:
            raise UsageError(f"--noise-draws must be 0 or more, got {args.noise_draws}")
        if (args.out is None) == (args.list is None):
            raise UsageError("give --out (play a log) or --list (write the objects' corpus list), not both or neither")
        config = make_config(args)
        try:
            player = player_from_args(args)
        except ValueError as err:
            raise UsageError(str(err)) from None
        params = PlayParams(args.actions, args.repeats, args.eps, args.max_poses, args.seed, config, args.noise_draws, player)
        specs = select_objects(args.objects, args.count, args.seed, config.mesh.default_mass, skip=args.skip)
        if args.count is not None and len(specs) < args.count:
            print(f"note: only {len(specs)} {args.objects} objects remain after --skip {args.skip}", file=sys.stderr)
        if args.list is not None:
            write_list(specs, args.list, pybullet_data_dir())
            print(f"{len(specs)} {args.objects} objects -> {args.list}")
            return 0
        if note := world_note(config):
            print(note, file=sys.stderr)
        summary = play(specs, params, args.out, workers=args.workers, progress=not args.no_progress, force=args.force,
                       run_info={"objects": args.objects, "count": args.count, "skip": args.skip})
    except (UsageError, PlayError, CorpusError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    print(summary.text())
    print(f"log: {args.out.resolve()}")
    for object_id, reason in summary.failed.items():
        print(f"not played: {object_id}: {reason}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
