"""Checking a finished dataset against its manifest (``toppledb verify DIR``).

Every shard: its completion record agrees with the manifest, every file exists
with the recorded SHA-256, Parquet files have the schema of ``schema.tables`` and
the manifest's row counts, the HDF5 file has the layout of ``schema.hdf5``.  The
consolidated tables: checksums, schemas, row counts.  Totals add up.  Nothing
else is in the dataset's directories (no partition of an unknown object, no
temporary file left behind).
"""

from __future__ import annotations

from pathlib import Path

from schema import layout, served, tables
from schema.manifest import ManifestError, Shard, read_manifest

from .atomic import file_sha256
from . import shards


def verify_dataset(root: str | Path) -> list[str]:
    """Every problem found, one line each; empty when the dataset is intact."""
    root = Path(root)
    if not root.is_dir():
        return [f"{root}: {'not a directory' if root.exists() else 'no such directory'}"]
    try:
        manifest = read_manifest(root)
    except ManifestError as err:
        return [str(err)]

    problems = []
    entries = manifest.shards
    for object_id, entry in entries.items():
        problems += _shard_problems(root, object_id, entry)

    counts = manifest.counts
    for key in ("poses", "actions", "ok_actions", "transitions"):
        total = sum(getattr(entry.counts, key) for entry in entries.values())
        if getattr(counts, key) != total:
            problems.append(f"manifest: {key} total {getattr(counts, key)} but the shards add up to {total}")
    if counts.objects != len(entries):
        problems.append(f"manifest: {counts.objects} objects but {len(entries)} shards")

    expected_rows = {layout.OBJECTS_FILE: ("objects", len(entries)), layout.POSES_FILE: ("poses", counts.poses)}
    for name, (table, rows) in expected_rows.items():
        problem = checksum_problem(root, manifest, name)
        problems += [problem] if problem else shards.parquet_problems(root / name, name, tables.TABLES[table], rows)

    problems += _served_problems(root, manifest)
    problems += _unexpected_files(root, set(entries))
    return problems


def checksum_problem(root: Path, manifest, name: str) -> str | None:
    """Why the consolidated file ``name`` is not the one the manifest records, or None."""
    entry = manifest.tables.get(name)
    if entry is None:
        return f"manifest: no entry for {name}"
    actual = file_sha256(root / name)
    if not actual:
        return f"{name}: missing"
    if actual != entry.sha256:
        return f"{name}: sha256 {actual[:12]}... differs from the manifest's {entry.sha256[:12]}..."
    return None


def _served_problems(root: Path, manifest) -> list[str]:
    """The served tables: recorded in the manifest, same bytes, readable, rows as recorded."""
    problems = [p for p in (checksum_problem(root, manifest, relative) for relative in served.FILES.values()) if p]
    if problems:
        return problems
    try:
        served.read_current(root, manifest, verify=False)  # the bytes were checked above
    except served.ServedError as err:
        return [str(err)]
    return []


def _shard_problems(root: Path, object_id: str, entry: Shard) -> list[str]:
    record = shards.read_record(root, object_id)
    where = layout.completion_record(object_id)
    if record is None:
        return [f"{where}: missing or unreadable: shard {object_id} is incomplete"]
    if record.get("files") != entry.files or record.get("counts") != entry.counts.model_dump():
        return [f"{where}: differs from the manifest's entry for {object_id}"]
    problems = shards.checksum_problems(root, record)
    if not problems:
        problems = shards.content_problems(root, record)
    return problems


def _unexpected_files(root: Path, object_ids: set[str]) -> list[str]:
    problems = []
    for path in sorted(root.rglob(f".*{layout.TEMP_SUFFIX}")):
        problems.append(f"{path.relative_to(root)}: temporary file left behind")
    for table in tables.PARTITIONED:
        for directory in sorted((root / table).glob("*")):
            key, _, object_id = directory.name.partition("=")
            if key != tables.PARTITION_KEY or object_id not in object_ids:
                problems.append(f"{table}/{directory.name}: not a shard in the manifest")
            else:
                extra = [p.name for p in directory.iterdir() if p.name != Path(layout.partition_file(table, object_id)).name]
                extra = [name for name in extra if not name.startswith(".")]
                if extra:
                    problems.append(f"{table}/{directory.name}: unexpected files {extra}")
    for path in sorted((root / layout.ARRAYS_DIR).glob("*")):
        # A dot-file is a temporary file (named above) or hidden: no reader takes it for a shard.
        if path.name.startswith("."):
            continue
        if path.suffix != ".h5" or path.stem not in object_ids:
            problems.append(f"{layout.ARRAYS_DIR}/{path.name}: not a shard in the manifest")
    return problems
