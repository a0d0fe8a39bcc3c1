"""Building a dataset: which objects still need work, fanning them out, writing
their shards as they finish, then the consolidated tables and the manifest.

A rerun skips every shard that is complete, verified (SHA-256 of its files) and
made from the same inputs (``shards.fingerprint``: schema version, parameters,
mesh checksum); it redoes shards left incomplete by a killed run.  It refuses to
mix: complete shards of other parameters or of objects outside the corpus make
it stop with a message, unless ``force`` (rebuild everything).

Workers compute (``compute_shard``: the object's evaluation and its tables); this
process alone writes, so a cluster needs no shared file system and every write
is atomic.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from schema import layout, tables
from schema.manifest import Manifest

from . import fanout, manifest, rows, shards
from ..model.config import Config
from .corpus import Corpus, ObjectSpec
from ..model.outcomes import ObjectResult

Process = Callable[[ObjectSpec, Config], ObjectResult]


class BuildError(RuntimeError):
    """The build cannot go on; the message is one line for the user."""


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


def _one_line(text: str) -> str:
    return " ".join(text.split())[:500]


@dataclass
class Summary:
    """What a build did; ``manifest`` is the written manifest."""

    manifest: Manifest
    computed: int
    reused: int
    wall_s: float

    def text(self) -> str:
        counts, timings = self.manifest.counts, self.manifest.timings
        lines = [
            f"objects   {counts.objects} ({self.computed} computed, {self.reused} reused), failed {counts.failed}",
            f"poses     {counts.poses}",
            f"actions   {counts.actions} ({counts.ok_actions} ok), transitions {counts.transitions}",
            f"wall      {self.wall_s:.1f} s",
            f"cpu       {timings.cpu_s_total:.1f} s over all objects: "
            + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in timings.cpu_s_by_stage.items()),
        ]
        for failure in self.manifest.failures:
            lines.append(f"failed    {failure.object_id}: {failure.reason}")
        return "\n".join(lines)


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
) -> Summary:
    """Build (or finish building) the dataset of ``corpus`` under ``out``.

    workers : local processes (default: all cores); ignored with ``scheduler``
    scheduler : address of a dask.distributed scheduler to run the tasks on
    force : discard whatever ``out`` holds and compute every object
    strict : stop at the first failed object (its reason is the error)
    process : the per-object computation, ``pipeline.model.evaluation.process_object`` by default
    """
    started = time.perf_counter()
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise BuildError(f"cannot create output directory {out}: {err.strerror}") from None

    with _exclusive(out):
        inputs = {spec.object_id: shards.shard_inputs(spec, config) for spec in corpus.specs}
        fingerprints = {object_id: shards.fingerprint(i) for object_id, i in inputs.items()}
        if force:
            _remove_dataset_files(out)
        else:
            _refuse_foreign_shards(out, inputs)  # before touching anything: a refused run changes nothing
        manifest.remove_manifest(out)  # from here on the directory is a build in progress
        shards.remove_temp_files(out)

        records: dict[str, dict] = {}
        failures: dict[str, Failure] = {}
        todo: list[ObjectSpec] = []
        for spec in corpus.specs:
            if spec.object_id in corpus.problems:
                failures[spec.object_id] = Failure(spec.object_id, corpus.problems[spec.object_id], "corpus")
                continue
            record = shards.is_complete(out, spec.object_id, fingerprints[spec.object_id])
            if record is not None:
                records[spec.object_id] = record
            else:
                todo.append(spec)
        reused = len(records)
        if strict and failures:
            first = next(iter(failures.values()))
            raise BuildError(f"--strict: {first.object_id}: {first.reason}")
        if reused:
            log(f"resuming: {reused} of {len(corpus.specs)} objects already complete in {out}")

        bar = fanout.Progress(
            total=len(corpus.specs),
            already_done=reused + len(failures),
            already_poses=sum(r["counts"]["poses"] for r in records.values()),
            enabled=progress,
        )
        try:
            # Largest meshes first: the slowest tasks start early and the run ends evenly.
            todo.sort(key=lambda s: -_size(s.path))
            tasks = [(spec, config, process) for spec in todo]
            for outcome in fanout.map_unordered(compute_shard, tasks, workers, scheduler):
                if isinstance(outcome, Failure):
                    _remove_object_files(out, outcome.object_id)
                    if strict:
                        raise BuildError(f"--strict: {outcome.object_id}: {outcome.reason}")
                    failures[outcome.object_id] = outcome
                    bar.object_done(0, failed=True)
                    continue
                records[outcome.object_id] = shards.write_shard(out, outcome, inputs[outcome.object_id])
                bar.object_done(outcome.counts["poses"])
        except fanout.SchedulerError as err:
            raise BuildError(str(err)) from None
        finally:
            bar.close()

        order = [spec.object_id for spec in corpus.specs if spec.object_id in records]
        consolidated = manifest.consolidate(out, order)
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
        written = manifest.make_manifest(config, corpus, records, consolidated, failure_list, run)
        manifest.write_manifest(out, written)
    return Summary(written, computed=len(todo), reused=reused, wall_s=wall)


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out`` so that two builds never write it at once;
    the kernel drops the lock when the process dies, even by SIGKILL."""
    with open(out / ".lock", "w") as lock:
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
    raise BuildError(f"{out} holds {what}; use --force to rebuild it or choose another --out")


def _remove_object_files(out: Path, object_id: str) -> None:
    (out / layout.completion_record(object_id)).unlink(missing_ok=True)
    for table in tables.PARTITIONED:
        shutil.rmtree(out / Path(layout.partition_file(table, object_id)).parent, ignore_errors=True)
    (out / layout.arrays_file(object_id)).unlink(missing_ok=True)
    shutil.rmtree(out / layout.shard_dir(object_id), ignore_errors=True)


def _remove_dataset_files(out: Path) -> None:
    """Everything a build writes (and nothing else that may be in ``out``)."""
    for name in (layout.MANIFEST, layout.OBJECTS_FILE, layout.POSES_FILE):
        (out / name).unlink(missing_ok=True)
    for directory in (*tables.PARTITIONED, layout.ARRAYS_DIR, layout.SHARDS_DIR):
        shutil.rmtree(out / directory, ignore_errors=True)
