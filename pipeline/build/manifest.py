"""The dataset's manifest and its consolidated tables.

``manifest.json`` says what a dataset directory holds and how it was made: schema
and code versions, every parameter (``Config.to_dict()``), the seed, the corpus
with each mesh's SHA-256, every shard's files with their SHA-256 and counts, the
consolidated tables' checksums, totals, failures with their reasons and timings.
It is written last, atomically (staged, then moved in by the build's commit,
``pipeline.build.dataset``); a directory without one is a build in progress.

``objects.parquet`` and ``poses.parquet`` are concatenated from the shards' rows
in corpus order, so they do not depend on which worker finished first.
"""

from __future__ import annotations

import dataclasses
import datetime
import platform
import subprocess
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from schema import layout, tables
from schema.manifest import Manifest
from schema.version import CODE_VERSION, SCHEMA_VERSION

from ..model.config import Config
from .corpus import Corpus
from .atomic import write_atomic, write_text_atomic
from .shards import PARQUET_COMPRESSION, parameter_files

LIBRARIES = ("numpy", "scipy", "trimesh", "embreex", "python-fcl", "pyarrow", "h5py", "joblib", "pybullet")


def code_version() -> dict[str, Any]:
    """Package version, git commit of the source tree when there is one, Python and
    library versions, and the BLAS kernel (each can change floating-point results;
    ``pipeline.numerics``)."""
    from importlib import metadata

    from ..numerics import blas_kernel, numpy_simd

    def version(name: str) -> str | None:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return None

    return {
        "package": CODE_VERSION,
        "git_commit": _git_commit(),
        "python": platform.python_version(),
        "libraries": {name: version(name) for name in LIBRARIES},
        "blas": blas_kernel(),
        "simd": numpy_simd(),
    }


def _git_commit() -> str | None:
    """HEAD of the repository holding this file (read-only), or None outside git."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def consolidate(
    root: str | Path, object_ids: list[str], sources: dict[str, str | Path] | None = None
) -> dict[str, dict[str, Any]]:
    """Write objects.parquet and poses.parquet under ``root`` from the shards of
    ``object_ids`` (in that order), each read from ``sources[object_id]`` (default
    ``root``); return {file: {"sha256", "rows"}}."""
    root = Path(root)
    sources = sources or {}
    written = {}
    for table, name in (("objects", layout.OBJECTS_FILE), ("poses", layout.POSES_FILE)):
        schema = tables.TABLES[table]
        parts = [
            pq.read_table(Path(sources.get(object_id, root)) / layout.shard_rows_file(table, object_id), schema=schema)
            for object_id in object_ids
        ]
        combined = pa.concat_tables(parts) if parts else schema.empty_table()
        digest = write_atomic(
            root / name,
            lambda path, t=combined: pq.write_table(t, path, compression=PARQUET_COMPRESSION)
        )
        written[name] = {"sha256": digest, "rows": combined.num_rows}
    return written


def make_manifest(
    config: Config,
    corpus: Corpus,
    records: dict[str, dict],
    consolidated: dict[str, dict],
    failures: list[dict],
    run: dict[str, Any],
) -> Manifest:
    """The manifest of a finished build.

    records : object id -> completion record of every shard in the dataset
    failures : {object_id, path, reason, kind} of every object that has no shard
    run : facts about this run (workers, backend, computed/reused, wall time)
    """
    order = [spec.object_id for spec in corpus.specs if spec.object_id in records]
    counts = {"objects": len(order), "failed": len(failures)}
    for key in ("poses", "actions", "ok_actions", "transitions"):
        counts[key] = sum(records[i]["counts"][key] for i in order)
    cpu_by_stage: dict[str, float] = {}
    for object_id in order:
        for stage, seconds in records[object_id].get("timings", {}).items():
            cpu_by_stage[stage] = cpu_by_stage.get(stage, 0.0) + seconds
    return Manifest.model_validate({
        "schema_version": SCHEMA_VERSION,
        "code_version": code_version(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "seed": config.seed,
        "parameters": config.to_dict(),
        "corpus": {
            "name": corpus.name,
            "objects": [dataclasses.asdict(spec) for spec in corpus.specs],
        },
        "counts": counts,
        "tables": consolidated,
        "shards": {
            object_id: {
                "files": records[object_id]["files"],
                "counts": records[object_id]["counts"],
                "fingerprint": records[object_id]["fingerprint"],
            }
            for object_id in order
        },
        "failures": failures,
        "timings": {
            "wall_s": run.pop("wall_s"),
            "cpu_s_by_stage": {k: round(v, 3) for k, v in sorted(cpu_by_stage.items())},
            "cpu_s_total": round(sum(cpu_by_stage.values()), 3),
        },
        "run": run,
        "parameter_files": parameter_files(config),
    })


def write_manifest(root: str | Path, manifest: Manifest) -> None:
    write_text_atomic(Path(root) / layout.MANIFEST, manifest.to_json())
