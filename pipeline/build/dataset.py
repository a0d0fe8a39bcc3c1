"""Building a dataset: which objects still need work, fanning them out, writing
their shards as they finish, then the consolidated tables and the manifest.

A finished dataset is never damaged by a later run.  New shards, the consolidated
tables and the new manifest are written to a staging directory beside the dataset
(``.<name>.staging``, see ``staging_dir``); only when all of it exists does a
*commit* move them in: the commit plan is written first (the commit point), then
the files are renamed into place, files of objects the new manifest no longer
lists are removed, and the manifest is replaced last.  A run that fails or is
killed before the commit point leaves the previous dataset exactly as it was
(verifiable and servable) and its finished shards in the staging directory, where
the next run reuses them; a run killed after it is rolled forward by the next run
(or by ``toppledb add``) before anything else.  A run with nothing to compute
writes nothing and never contacts a scheduler.

A rerun skips every shard that is complete, verified (SHA-256 of its files) and
made from the same inputs (``shards.fingerprint``: schema version, parameters,
mesh checksum).  It refuses to mix: complete shards of other parameters or of
objects outside the corpus make it stop with a message, unless ``force``
(recompute everything; the old dataset is replaced only at the commit).

Workers compute (``compute_shard``: the object's evaluation and its tables); this
process alone writes, so a cluster needs no shared file system and every write
is atomic.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
import re
import shutil
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from schema import layout, served, tables
from schema.layout import object_id_key
from schema.manifest import Manifest, ManifestError, read_manifest

from ..model.config import Config
from ..model.outcomes import ObjectResult
from . import fanout, manifest, rows, shards
from .atomic import fsync_directory, write_text_atomic
from .corpus import Corpus, ObjectSpec
from .served import write_served

Process = Callable[[ObjectSpec, Config], ObjectResult]


class BuildError(RuntimeError):
    """The build cannot go on; the message is one line for the user."""


class OutputError(BuildError):
    """The output directory cannot be created or written (a bad path, permissions), or
    holds shards this build must not mix with or delete (other inputs, other objects):
    the user's path to change, exit status 2."""


class InputError(BuildError):
    """An input the user gave cannot be used (``add``'s mesh): bad input, exit status 2."""


class StrictFailure(BuildError):
    """``strict``: an object failed, and the build stopped there (``failure``: which, and why)."""

    def __init__(self, failure: Failure):
        super().__init__(f"--strict: {_named(failure)}")
        self.failure = failure


@dataclass
class Failure:
    """An object that has no shard, and why."""

    object_id: str
    reason: str
    kind: str = "error"
    """``mesh`` (rejected mesh), ``corpus`` (missing or changed file), ``error`` (anything else)."""
    detail: str = ""
    """Last lines of the traceback for unexpected errors, to find the bug."""


def compute_shard(spec: ObjectSpec, config: Config, process: Process | None = None) -> rows.ShardData | Failure:
    """Evaluate one object and build its shard's tables; runs in a worker.

    Never raises for a problem of this object: a rejected mesh or any other
    exception comes back as a ``Failure`` so that the run goes on.
    """
    from ..model.mesh import MeshError

    if process is None:
        from ..model.evaluation import process_object as process
    try:
        result = process(spec, config)
        return rows.build_shard(spec, result, config.topple.trials)
    except MeshError as err:
        return Failure(spec.object_id, _one_line(str(err)), "mesh")
    except Exception as err:  # any bug or numerical failure in one object must not end the run
        detail = "".join(traceback.format_exception(err)[-6:])
        return Failure(spec.object_id, _one_line(f"{type(err).__name__}: {err}"), "error", detail)


def _named(failure: Failure) -> str:
    """``id: reason`` (mesh errors already start with the id)."""
    prefix = f"{failure.object_id}: "
    return failure.reason if failure.reason.startswith(prefix) else prefix + failure.reason


def _one_line(text: str) -> str:
    return " ".join(text.split())[:500]


MAX_FAILURE_LINES = 10
"""The summary lists at most this many failed objects one by one (the manifest has all)."""


@dataclass
class Summary:
    """What a build did; ``manifest`` is the written manifest.

    repairs : object id -> what loading repaired, for objects computed in this run
    """

    manifest: Manifest
    computed: int
    reused: int
    wall_s: float
    repairs: dict[str, list[str]] = dataclasses.field(default_factory=dict)
    committed: bool = True
    """False when every object failed: nothing was written, ``out`` is as it was."""

    @property
    def all_failed(self) -> bool:
        return self.manifest.counts.objects == 0 and self.manifest.counts.failed > 0

    def text(self) -> str:
        counts, timings = self.manifest.counts, self.manifest.timings
        lines = [
            f"objects   {counts.objects} ({self.computed} computed, {self.reused} reused), failed {counts.failed}",
            f"poses     {counts.poses}",
            f"actions   {counts.actions} ({counts.ok_actions} ok), transitions {counts.transitions}",
            f"wall      {self.wall_s:.1f} s",
            f"cpu       {timings.cpu_s_total:.1f} s over all objects: "
            + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in timings.cpu_s_by_stage.items())
            # Nothing computed: the manifest's timings are those of the run that built the shards.
            + ("" if self.computed else " (when the shards were computed; none was this run)"),
        ]
        for object_id, repairs in self.repairs.items():
            # Merging duplicate vertices is routine (every STL stores each triangle's own);
            # objects.parquet keeps it, the console only what changed the shape or its reading.
            notable = [r for r in repairs if not r.startswith("merged ")]
            if notable:
                lines.append(f"repaired  {object_id}: {'; '.join(notable)}")
        failures = self.manifest.failures
        for failure in failures[:MAX_FAILURE_LINES]:
            lines.append(f"failed    {failure.object_id}: {failure.reason.removeprefix(failure.object_id + ': ')}")
        if len(failures) > MAX_FAILURE_LINES:
            lines.append(f"failed    ... and {len(failures) - MAX_FAILURE_LINES} more (every one is in manifest.json)")
        if len(failures) > 1:
            lines.append("failures by reason:")
            reasons = {f.object_id: f.reason for f in failures}
            for reason, ids in failure_groups(list(reasons.items())).items():
                examples = ", ".join(ids[:3]) + (", ..." if len(ids) > 3 else "")
                hints = {m.group(1) for i in ids if (m := re.search(r"use (--units \w+)", reasons[i]))}
                hint = f"; try {hints.pop()}" if len(hints) == 1 else ""
                lines.append(f"  {len(ids):5d}  {reason} ({examples}){hint}")
        return "\n".join(lines)


def failure_groups(failures: list[tuple[str, str]]) -> dict[str, list[str]]:
    """Failed object ids grouped by the kind of their reason, most common first.

    The kind is the reason without its object id, cut at the first detail (':' or
    '('), with file names and numbers masked so that reasons differing only in them
    group together: "too large for a tabletop", "cannot read <file>", "mesh file not found".
    The masks say what was there, since the console shows the kind.
    """
    groups: dict[str, list[str]] = {}
    for object_id, reason in failures:
        text = reason.removeprefix(f"{object_id}: ")
        kind = re.split(r"[:(;]", text, maxsplit=1)[0].strip()
        kind = re.sub(r"\S*[\d./\\]\S*", _mask, kind) or text[:60]
        groups.setdefault(kind, []).append(object_id)
    return dict(sorted(groups.items(), key=lambda item: -len(item[1])))


def _mask(token: re.Match) -> str:
    """``failure_groups``' stand-in for a number or a file name in a reason's kind."""
    return "<n>" if re.fullmatch(r"[-+]?[\d.,]+%?", token.group(0)) else "<file>"


def build_dataset(
    corpus: Corpus,
    config: Config,
    out: str | Path,
    workers: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    strict: bool = False,
    progress: bool = True,
    process: Process | None = None,
    log: Callable[[str], None] = print,
    previous_failures: dict[str, Failure] | None = None,
) -> Summary:
    """Build (or finish building, or extend) the dataset of ``corpus`` under ``out``.

    workers : local processes (default: all cores); ignored with ``scheduler``
    scheduler : address of a dask.distributed scheduler to run the tasks on
    force : recompute every object (the old dataset stays until the new one is committed)
    strict : stop at the first failed object (its reason is the error)
    process : the per-object computation, ``pipeline.model.evaluation.process_object`` by default
    previous_failures : objects that failed before and are not to be retried (``add_object``)
    """
    started = time.perf_counter()
    out = Path(out)
    # The directories this run makes (--out and any missing parent), removed again if it writes nothing.
    created = [d for d in (out, *out.parents) if not d.exists()]
    _make_directory(out, "output directory")
    staging = staging_dir(out)

    with _exclusive(out):
        staging_existed = staging.exists()
        try:
            summary = _build_locked(corpus, config, out, staging, started, workers, scheduler, force, strict, progress,
                                    process, log, previous_failures or {})
        except BaseException:
            # --strict, an unreachable scheduler, Ctrl-C, a mesh `add` rejects: neither a staging directory
            # with nothing to resume nor a fresh --out this run made is left behind empty (staged shards
            # stay, for the same command to resume from).  Only while holding the lock: a run that never
            # got it must not remove what the one that has it is writing.
            _discard_idle_staging(staging, created_now=not staging_existed)
            if created:
                _remove_if_only_lock(out, created)
            raise
        if not summary.committed and created:
            _remove_if_only_lock(out, created)
    return summary


def _build_locked(
    corpus: Corpus,
    config: Config,
    out: Path,
    staging: Path,
    started: float,
    workers: int | None,
    scheduler: str | None,
    force: bool,
    strict: bool,
    progress: bool,
    process: Process | None,
    log: Callable[[str], None],
    previous: dict[str, Failure],
) -> Summary:
    """``build_dataset``'s work once it holds the lock on ``out``: reuse, compute, commit."""
    if finish_interrupted_commit(out):
        log(f"finished the commit of an interrupted run in {out}")
    inputs = {spec.object_id: shards.shard_inputs(spec, config) for spec in corpus.specs}
    fingerprints = {object_id: shards.fingerprint(i) for object_id, i in inputs.items()}
    forced = _forced_run() if force else None
    if force and not _resumes(staging, forced):
        # A new --force run recomputes everything; only the same code's killed --force run resumes.
        shutil.rmtree(staging, ignore_errors=True)
    else:
        _refuse_foreign_shards(out, inputs)  # before computing anything: a refused run changes nothing
    _discard_stale_staging(staging, fingerprints)
    shards.remove_temp_files(out)  # left by builds of earlier versions, never part of a dataset

    records: dict[str, dict] = {}
    staged: dict[str, dict] = {}
    failures: dict[str, Failure] = {}
    todo: list[ObjectSpec] = []
    for spec in corpus.specs:
        if spec.object_id in corpus.problems:
            failures[spec.object_id] = Failure(spec.object_id, corpus.problems[spec.object_id], "corpus")
            continue
        key = fingerprints[spec.object_id]
        record = None if force else shards.is_complete(out, spec.object_id, key)
        if record is not None:
            records[spec.object_id] = record
        elif (record := shards.is_complete(staging, spec.object_id, key)) is not None:
            staged[spec.object_id] = record
        else:
            todo.append(spec)
    reused = len(records) + len(staged)
    if strict and failures:
        raise StrictFailure(next(iter(failures.values())))
    failures.update({spec.object_id: previous[spec.object_id] for spec in todo if spec.object_id in previous})
    todo = [spec for spec in todo if spec.object_id not in previous]

    current = _current_manifest(out)
    if not todo and not staged and not force and _up_to_date(out, current, config, corpus, records, failures):
        damaged = _damaged_tables(out, current)
        if not damaged:
            log(f"up to date: all {len(records)} objects of {out} are complete; nothing to do")
            _discard_idle_staging(staging, created_now=False)  # the stale files just removed may have been all it held
            return Summary(current, computed=0, reused=len(records), wall_s=time.perf_counter() - started)
        log(f"{out}: every shard is complete but {damaged[0]}{f' (and {len(damaged) - 1} more)' if len(damaged) > 1 else ''}; "
            "writing the tables again from the shards")
    if reused:
        # Name the directory that holds them: a killed run's shards wait in the staging directory,
        # and --out may not exist yet.
        if not staged:
            where = f"in {out}"
        elif not records:
            where = f"in {staging}"
        else:
            where = f"({len(records)} in {out}, {len(staged)} in {staging})"
        log(f"resuming: {reused} of {len(corpus.specs)} objects already complete {where}")

    _make_directory(staging, "staging directory")
    if forced is not None:
        write_text_atomic(staging / FORCED_RUN, forced)
    repairs: dict[str, list[str]] = {}
    if todo:
        staged.update(
            _compute(todo, config, process, staging, inputs, failures, workers, scheduler, strict, progress, reused, repairs)
        )

    order = [spec.object_id for spec in corpus.specs if spec.object_id in records or spec.object_id in staged]
    sources = {object_id: (staging if object_id in staged else out) for object_id in order}
    consolidated = manifest.consolidate(staging, order, sources)
    consolidated.update(write_served(staging, order, sources))
    wall = time.perf_counter() - started
    paths = {spec.object_id: spec.path for spec in corpus.specs}
    failure_list = [
        {
            "object_id": f.object_id,
            "path": paths[f.object_id],
            "reason": f.reason,
            "kind": f.kind,
            **({"detail": f.detail} if f.detail else {}),
        }
        for f in (failures[s.object_id] for s in corpus.specs if s.object_id in failures)
    ]
    run = {
        "workers": workers or (fanout.default_workers() if scheduler is None else None),
        "backend": "dask" if scheduler else "loky",
        "scheduler": scheduler,
        "computed": len(todo),
        "reused": reused,
        "wall_s": round(wall, 3),
    }
    written = manifest.make_manifest(config, corpus, {**records, **staged}, consolidated, failure_list, run)
    committed = bool(order) or not failures
    if committed:
        manifest.write_manifest(staging, written)
        commit(out, staging, staged, keep=set(order))
    else:
        # Every object failed (a forgotten --units, a wrong corpus): a dataset of nothing would
        # replace whatever ``out`` holds, so the run commits nothing and says so.
        shutil.rmtree(staging, ignore_errors=True)
    order_repairs = {s.object_id: repairs[s.object_id] for s in corpus.specs if s.object_id in repairs}
    return Summary(written, computed=len(todo), reused=reused, wall_s=wall, repairs=order_repairs, committed=committed)


def _discard_idle_staging(staging: Path, created_now: bool) -> None:
    """After a failed or interrupted run: remove ``staging`` when it holds nothing a rerun would use,
    so that no empty hidden ``.<name>.staging`` is left beside ``--out``.  Kept when it holds a
    complete shard (the same command resumes from it) or a commit plan (the next run rolls the
    commit forward).  One that was there before this run is removed only when it holds no file at
    all: what an earlier run left is that run's to judge, not this one's."""
    if not staging.is_dir() or _worth_resuming(staging):
        return
    if created_now or not any(path.is_file() for path in staging.rglob("*")):
        shutil.rmtree(staging, ignore_errors=True)


def _worth_resuming(staging: Path) -> bool:
    """Whether ``staging`` holds work a rerun would reuse: a begun commit or a complete shard."""
    return (staging / COMMIT_PLAN).exists() or any(
        shards.read_record(staging, object_id) is not None for object_id in _shard_ids_on_disk(staging)
    )


def _remove_if_only_lock(out: Path, created: list[Path]) -> None:
    """Remove ``out`` (which this run made, and whose lock it holds) when it holds nothing but
    its lock file, then the parents this run made, deepest first, while they are empty; a file
    another process wrote there since keeps it."""
    with contextlib.suppress(OSError):
        (out / ".lock").unlink()
        for directory in created:  # out first, then its parents
            directory.rmdir()


def _compute(
    todo: list[ObjectSpec],
    config: Config,
    process: Process | None,
    staging: Path,
    inputs: dict[str, dict],
    failures: dict[str, Failure],
    workers: int | None,
    scheduler: str | None,
    strict: bool,
    progress: bool,
    already_done: int,
    repairs: dict[str, list[str]],
) -> dict[str, dict]:
    """Compute ``todo`` and write each shard into ``staging`` as it arrives; add the
    objects that fail to ``failures`` and what loading repaired to ``repairs``;
    return the new shards' records."""
    written: dict[str, dict] = {}
    bar = fanout.Progress(
        total=already_done + len(failures) + len(todo),
        already_done=already_done + len(failures),
        enabled=progress,
    )
    try:
        # Largest meshes first: the slowest tasks start early and the run ends evenly.
        todo = sorted(todo, key=lambda s: -_size(s.path))
        tasks = [(spec, config, process) for spec in todo]
        # closing(): an exception here (--strict, Ctrl-C) stops the workers at once, not at garbage collection.
        with contextlib.closing(fanout.map_unordered(compute_shard, tasks, workers, scheduler)) as outcomes:
            for outcome in outcomes:
                if isinstance(outcome, Failure):
                    _remove_object_files(staging, outcome.object_id)
                    if strict:
                        raise StrictFailure(outcome)
                    failures[outcome.object_id] = outcome
                    bar.object_done(0, failed=True)
                    continue
                written[outcome.object_id] = shards.write_shard(staging, outcome, inputs[outcome.object_id])
                repaired = outcome.rows["objects"].column("repairs").to_pylist()[0]
                if repaired:
                    repairs[outcome.object_id] = repaired
                bar.object_done(outcome.counts["poses"])
    except fanout.SchedulerError as err:
        raise BuildError(str(err)) from None
    finally:
        bar.close()
    return written


# --- staging and commit ---------------------------------------------------------------------

CONSOLIDATED_FILES = (layout.OBJECTS_FILE, layout.POSES_FILE, *served.FILES.values())
"""Made from every shard at the end of a build, moved in just before the manifest."""
COMMIT_PLAN = "commit.json"
"""In the staging directory: written when everything is staged; its presence means
the commit has begun and must be finished (rolled forward)."""


FORCED_RUN = "forced.json"
"""In the staging directory of a --force run: the code that computed its shards (``_forced_run``).
The same command, killed and run again by the same code, reuses them; any other --force run starts over."""


def _forced_run() -> str:
    """What a --force run's staged shards are computed by, as the JSON text of ``FORCED_RUN``: the
    package, git commit, libraries and BLAS kernel (``manifest.code_version``) and a digest of the
    source files, which an uncommitted edit changes."""
    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for path in sorted([*root.glob("pipeline/**/*.py"), *root.glob("schema/**/*.py")]):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    version = manifest.code_version()
    # The kernel computed with, not who named it: a run whose numpy loaded before ``pipeline`` (a test,
    # a Python session) computes with the same kernel as ``python -m pipeline`` on this machine.
    version["blas"] = {k: v for k, v in version["blas"].items() if k != "requested"}
    return json.dumps({"code_version": version, "sources_sha256": digest.hexdigest()}, sort_keys=True)


def _resumes(staging: Path, forced: str) -> bool:
    """Whether ``staging`` holds the shards of a killed --force run of this very code."""
    try:
        return (staging / FORCED_RUN).read_text() == forced
    except OSError:
        return False


def staging_dir(out: str | Path) -> Path:
    """Where a run stages its work: ``.<name>.staging`` beside ``out`` (same file system,
    so renames are atomic; outside ``out``, so readers and ``verify`` never see it)."""
    out = Path(out).resolve()
    return out.with_name(f".{out.name}.staging")


def commit(out: Path, staging: Path, staged: dict[str, dict], keep: set[str]) -> None:
    """Move the staged shards (object id -> completion record), the consolidated tables
    and the manifest from ``staging`` into ``out``; remove shards of objects not in ``keep``."""
    object_ids = sorted(staged)
    moves = [relative for object_id in object_ids for relative in staged[object_id]["files"]]
    moves += [layout.completion_record(object_id) for object_id in object_ids]  # records after their files
    moves += [*CONSOLIDATED_FILES, layout.MANIFEST]  # the manifest last
    plan = {"moves": moves, "keep": sorted(keep)}
    write_text_atomic(staging / COMMIT_PLAN, json.dumps(plan, indent=1))  # the commit point
    _apply(out, staging, plan)


def finish_interrupted_commit(out: str | Path) -> bool:
    """Roll forward a commit that a killed run began; True when there was one."""
    out = Path(out)
    staging = staging_dir(out)
    try:
        plan = json.loads((staging / COMMIT_PLAN).read_text())
    except (OSError, ValueError):
        return False  # no commit begun (an unreadable plan was never complete: write_atomic)
    _apply(out, staging, plan)
    return True


def _apply(out: Path, staging: Path, plan: dict) -> None:
    """Idempotent: a file already moved is skipped, so it can be re-run after a kill."""
    keep = set(plan["keep"])
    for relative in plan["moves"]:
        if relative.endswith("complete.json"):
            break
        _move(staging / relative, out / relative)
    for object_id in _shard_ids_on_disk(out) - keep:
        _remove_object_files(out, object_id)
    for relative in plan["moves"]:
        if relative.endswith("complete.json") or relative in (*CONSOLIDATED_FILES, layout.MANIFEST):
            _move(staging / relative, out / relative)
    for directory in {(out / relative).parent for relative in plan["moves"]}:
        if directory.is_dir():
            fsync_directory(directory)
    shutil.rmtree(staging, ignore_errors=True)


def _move(source: Path, target: Path) -> None:
    if source.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(source, target)


def _discard_stale_staging(staging: Path, fingerprints: dict[str, str]) -> None:
    """Staged shards this run cannot use (other inputs, objects outside the corpus)."""
    for object_id in _shard_ids_on_disk(staging):
        record = shards.read_record(staging, object_id)
        if record is None or record.get("fingerprint") != fingerprints.get(object_id):
            _remove_object_files(staging, object_id)
    if staging.is_dir():
        shards.remove_temp_files(staging)


def _current_manifest(out: Path) -> Manifest | None:
    try:
        return read_manifest(out)
    except ManifestError:
        return None


def _up_to_date(
    out: Path, current: Manifest | None, config: Config, corpus: Corpus, records: dict[str, dict], failures: dict[str, Failure]
) -> bool:
    """The finished manifest already describes exactly this build (same objects, shards,
    parameters and failures): a run would rewrite the same dataset."""
    if current is None:
        return False
    try:
        # This code's served tables (a build by older code rewrites them); their bytes are _damaged_tables' to check.
        served.read_current(out, current, verify=False)
    except served.ServedError:
        return False
    order = [spec.object_id for spec in corpus.specs if spec.object_id in records]
    return (
        list(current.shards) == order
        and all(current.shards[i].fingerprint == records[i]["fingerprint"] for i in order)
        and [o.model_dump() for o in current.corpus.objects] == [dataclasses.asdict(s) for s in corpus.specs]
        and current.parameters.model_dump() == config.to_dict()
        and current.parameter_files == shards.parameter_files(config)  # one from before the field names the file only
        and [(f.object_id, f.reason) for f in current.failures]
        == [(s.object_id, failures[s.object_id].reason) for s in corpus.specs if s.object_id in failures]
    )


def _damaged_tables(out: Path, current: Manifest) -> list[str]:
    """Why the consolidated tables (objects, poses, served) are not the bytes ``current`` records, one
    line each: a file damaged after the build, which a rerun rewrites from the shards."""
    from .verify import checksum_problem

    return [problem for problem in (checksum_problem(out, current, name) for name in CONSOLIDATED_FILES) if problem]


def _make_directory(path: Path, what: str) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create {what} {path}: {err.strerror}") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write to {what} {path}: permission denied")


def add_object(
    root: str | Path,
    spec: ObjectSpec,
    log: Callable[[str], None] = print,
    progress: bool = False,
) -> Summary:
    """Add one object to a finished dataset: compute only it (in this process), with the
    dataset's own parameters, and commit the new manifest atomically.  The objects that
    failed before stay failures; a failure of the new object changes nothing.
    """
    root = Path(root)
    if finish_interrupted_commit(root):
        log(f"finished the commit of an interrupted run in {root}")
    try:
        current = read_manifest(root)
    except ManifestError as err:
        raise OutputError(f"cannot add to {root}: {err}") from None
    try:
        config = Config.from_dict(current.parameters.model_dump())
    except ValueError as err:
        raise BuildError(f"{root}: its parameters do not fit this code ({err}); rebuild it") from None
    specs = [ObjectSpec(**o.model_dump()) for o in current.corpus.objects]
    same = [s.object_id for s in specs if object_id_key(s.object_id) == object_id_key(spec.object_id)]
    if same:
        raise OutputError(f"{root} already has an object {same[0]!r}; choose another --id"
                          + (" (ids that differ only in case name the same files)" if same[0] != spec.object_id else ""))
    if specs and current.shards:
        # Code that added or changed parameters since the build cannot extend it consistently.
        first = next(iter(current.shards))
        record = shards.read_record(root, first) or {}
        expected = shards.shard_inputs(next(s for s in specs if s.object_id == first), config)
        if record.get("fingerprint") != shards.fingerprint(expected):
            differences = shards.input_differences(record.get("inputs") or {}, expected)
            raise BuildError(
                f"{root} was built with parameters this code no longer gives it ({'; '.join(differences[:3]) or 'schema'}); "
                "`add` needs the code that built it: rebuild the dataset with this code (toppledb dataset --force) first"
            )
    # The mesh, read as ``figures`` reads one: a file toppledb cannot use is the user's input to
    # change (exit 2), said before any computing, with the unit hint of the flags ``add`` has.
    from ..model.mesh import MeshError, load_mesh

    try:
        load_mesh(spec.path, scale=spec.scale, mass=spec.mass, name=spec.object_id, config=config.mesh)
    except MeshError as err:
        raise InputError(str(err)) from None
    previous = {
        f.object_id: Failure(f.object_id, f.reason, f.kind, f.detail) for f in current.failures
    }
    corpus = Corpus(current.corpus.name, [*specs, spec])
    quiet = lambda line: None if line.startswith("resuming:") else log(line)  # noqa: E731 (every other object is reused)
    try:
        return build_dataset(
            corpus, config, root, workers=1, strict=True, progress=progress, log=quiet, previous_failures=previous
        )
    except StrictFailure as err:
        # ``add`` is strict by nature (a failed object adds nothing); the user gave no --strict.
        # A mesh the model rejects (no stable pose, ...) is bad input, as in ``figures``; a crash is a failed build.
        failed = InputError if err.failure.kind in ("mesh", "corpus") else BuildError
        raise failed(_named(err.failure)) from None


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out`` so that two builds never write it at once;
    the kernel drops the lock when the process dies, even by SIGKILL."""
    try:
        lock = open(out / ".lock", "w")
    except OSError as err:
        raise OutputError(f"cannot write to output directory {out}: {err.strerror}") from None
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BuildError(f"another build is writing to {out}") from None
        yield


def _shard_ids_on_disk(out: Path) -> set[str]:
    """Object ids that have any file in ``out`` (complete or not)."""
    ids = set()
    for table in tables.PARTITIONED:
        ids |= {p.name.split("=", 1)[1] for p in (out / table).glob(f"{tables.PARTITION_KEY}=*")}
    ids |= {p.stem for p in (out / layout.ARRAYS_DIR).glob("*.h5")}
    ids |= {p.name for p in (out / layout.SHARDS_DIR).glob("*") if p.is_dir()}
    return ids


def _refuse_foreign_shards(out: Path, inputs: dict[str, dict]) -> None:
    """Stop if ``out`` holds complete shards this build would not reuse (objects
    outside the corpus, other parameters or schema), saying what differs; delete
    incomplete leftovers of objects outside the corpus."""
    outside, changed = [], []
    for object_id in sorted(_shard_ids_on_disk(out)):
        record = shards.read_record(out, object_id)
        if record is None:
            if object_id not in inputs:
                _remove_object_files(out, object_id)  # an interrupted write: nothing to keep
        elif object_id not in inputs:
            outside.append(object_id)
        elif record.get("fingerprint") != shards.fingerprint(inputs[object_id]):
            changed.append(object_id)
    if not outside and not changed:
        return
    if changed:
        old_inputs = shards.read_record(out, changed[0]).get("inputs")
        differences = shards.input_differences(old_inputs, inputs[changed[0]]) if old_inputs else []
        what = f"{len(changed)} shard(s) built from other inputs ({'; '.join(differences[:3]) or 'not recorded'})"
    else:
        what = f"{len(outside)} shard(s) of objects not in this corpus (e.g. {outside[0]})"
    raise OutputError(
        f"{out} holds {what}. To replace it, add --force (the old "
        f"dataset stays until the new one is complete); to keep it, choose another --out, e.g. --out {out}-2"
    )


def _remove_object_files(out: Path, object_id: str) -> None:
    (out / layout.completion_record(object_id)).unlink(missing_ok=True)
    for table in tables.PARTITIONED:
        shutil.rmtree(out / Path(layout.partition_file(table, object_id)).parent, ignore_errors=True)
    (out / layout.arrays_file(object_id)).unlink(missing_ok=True)
    shutil.rmtree(out / layout.shard_dir(object_id), ignore_errors=True)
