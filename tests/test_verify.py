"""``toppledb verify`` (pipeline/build/verify.py) on a small dataset built in this process: an
intact dataset has no problem, and each kind of damage (a manifest whose totals do not add up,
a consolidated or served table missing, changed or unrecorded, a shard's record missing or not
the manifest's, a shard file changed, anything in the dataset's directories that no shard owns)
is named in one line, and nothing else is.

The dataset is two random objects with a few pushes and trials, built with one worker (which
runs in this process, so mutation testing sees the build), in about a second; each test damages
its own copy.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from shapes import DATA

from pipeline.build import shards
from pipeline.build.atomic import file_sha256
from pipeline.build.corpus import Corpus, ObjectSpec
from pipeline.build.dataset import build_dataset
from pipeline.build.verify import verify_dataset
from schema import layout, served
from tests.test_rows import SMALL

OBJECTS = ("random_000", "random_001")


def small_corpus(names=OBJECTS) -> Corpus:
    specs = []
    for name in names:
        path = f"{DATA}/random_urdfs/{name[-3:]}/{name[-3:]}.obj"
        specs.append(ObjectSpec(object_id=name, path=path, scale=0.015, mass=0.1, source="pybullet_data/random_urdfs",
                                sha256=file_sha256(path)))
    return Corpus(name="small", specs=specs)


def build_small(out: Path, names=OBJECTS) -> Path:
    """A finished dataset of ``names`` under ``out``, computed in this process."""
    summary = build_dataset(small_corpus(names), SMALL, out, workers=1, progress=False, log=lambda line: None)
    assert summary.committed and summary.computed == len(names)
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    return build_small(tmp_path_factory.mktemp("small") / "dataset")


@pytest.fixture
def copy(built, tmp_path) -> Path:
    """A copy of the small dataset for one test to damage."""
    return Path(shutil.copytree(built, tmp_path / "dataset"))


def edit_manifest(root: Path, edit) -> None:
    manifest = json.loads((root / layout.MANIFEST).read_text())
    edit(manifest)
    (root / layout.MANIFEST).write_text(json.dumps(manifest))


def record_new_bytes(root: Path, relative: str) -> None:
    """After a file was rewritten: the manifest's entry (and a shard's record) say its new SHA-256."""
    digest = file_sha256(root / relative)

    def edit(manifest):
        if relative in manifest["tables"]:
            manifest["tables"][relative]["sha256"] = digest
        for object_id, entry in manifest["shards"].items():
            if relative in entry["files"]:
                entry["files"][relative] = digest
                record = json.loads((root / layout.completion_record(object_id)).read_text())
                record["files"][relative] = digest
                (root / layout.completion_record(object_id)).write_text(json.dumps(record))

    edit_manifest(root, edit)


def test_an_intact_dataset_has_no_problem(built):
    assert verify_dataset(built) == []
    assert sorted(json.loads((built / layout.MANIFEST).read_text())["shards"]) == sorted(OBJECTS)


def test_a_missing_or_unreadable_manifest_is_the_one_problem(copy, tmp_path):
    assert verify_dataset(tmp_path / "nowhere") == [f"{tmp_path / 'nowhere'}: no such directory"]
    assert verify_dataset(copy / layout.MANIFEST) == [f"{copy / layout.MANIFEST}: not a directory"]
    (copy / layout.MANIFEST).write_text('{"schema_version": ')
    (problem,) = verify_dataset(copy)
    assert "manifest" in problem
    (copy / layout.MANIFEST).unlink()
    (problem,) = verify_dataset(copy)
    assert "manifest" in problem


@pytest.mark.parametrize("key", ["poses", "actions", "ok_actions", "transitions"])
def test_totals_that_do_not_add_up_are_named(copy, key):
    counts = json.loads((copy / layout.MANIFEST).read_text())["counts"]
    edit_manifest(copy, lambda m: m["counts"].__setitem__(key, m["counts"][key] + 2))
    expected = [f"manifest: {key} total {counts[key] + 2} but the shards add up to {counts[key]}"]
    if key == "poses":  # poses.parquet holds as many rows as the manifest's total says
        expected.append(f"{layout.POSES_FILE}: {counts['poses']} rows, the manifest says {counts['poses'] + 2}")
    assert verify_dataset(copy) == expected


def test_objects_counted_but_without_a_shard_are_named(copy):
    edit_manifest(copy, lambda m: m["counts"].__setitem__("objects", 3))
    assert verify_dataset(copy) == ["manifest: 3 objects but 2 shards"]


@pytest.mark.parametrize("name", [layout.OBJECTS_FILE, layout.POSES_FILE, *served.FILES.values()])
def test_each_consolidated_and_served_table_is_checked_against_the_manifest(built, tmp_path, name):
    def damaged(how: str, edit) -> list[str]:
        root = Path(shutil.copytree(built, tmp_path / how))
        edit(root)
        return verify_dataset(root)

    recorded = json.loads((built / layout.MANIFEST).read_text())["tables"][name]["sha256"]
    assert damaged("unrecorded", lambda root: edit_manifest(root, lambda m: m["tables"].pop(name))) == [
        f"manifest: no entry for {name}"]
    assert damaged("missing", lambda root: (root / name).unlink()) == [f"{name}: missing"]

    def append(root):
        with open(root / name, "ab") as f:
            f.write(b"\0")

    assert damaged("changed", append) == [
        f"{name}: sha256 {file_sha256(tmp_path / 'changed' / name)[:12]}... differs from the manifest's {recorded[:12]}..."]


def test_a_consolidated_table_of_other_rows_or_columns_is_named(copy):
    objects = pq.read_table(copy / layout.OBJECTS_FILE)
    pq.write_table(objects.slice(0, 1), copy / layout.OBJECTS_FILE)
    record_new_bytes(copy, layout.OBJECTS_FILE)
    assert verify_dataset(copy) == [f"{layout.OBJECTS_FILE}: 1 rows, the manifest says 2"]

    pq.write_table(objects, copy / layout.OBJECTS_FILE)
    record_new_bytes(copy, layout.OBJECTS_FILE)
    assert verify_dataset(copy) == [], "rewritten with the same rows and schema, and recorded: intact"

    poses = pq.read_table(copy / layout.POSES_FILE)
    pq.write_table(poses.drop_columns(["v_t"]), copy / layout.POSES_FILE)
    record_new_bytes(copy, layout.POSES_FILE)
    assert verify_dataset(copy) == [
        f"{layout.POSES_FILE}: schema differs from schema.tables (columns {poses.drop_columns(['v_t']).column_names})"]
    pq.write_table(objects, copy / layout.POSES_FILE)
    record_new_bytes(copy, layout.POSES_FILE)
    assert verify_dataset(copy) == [f"{layout.POSES_FILE}: schema differs from schema.tables (columns {objects.column_names})"], \
        "each table is checked against its own schema"


def test_served_tables_of_other_rows_than_recorded_are_named(copy):
    relative = served.FILES["actions"]
    rows = served.read_served(copy)["actions"].num_rows
    edit_manifest(copy, lambda m: m["tables"][relative].__setitem__("rows", rows + 1))
    assert verify_dataset(copy) == [f"{relative} holds {rows} rows, manifest.json says {rows + 1}"]


def test_a_shard_without_a_record_or_with_another_one_is_named(copy):
    first, second = OBJECTS
    (copy / layout.completion_record(first)).unlink()
    (copy / layout.completion_record(second)).write_text("{")
    assert verify_dataset(copy) == [
        f"{layout.completion_record(first)}: missing or unreadable: shard {first} is incomplete",
        f"{layout.completion_record(second)}: missing or unreadable: shard {second} is incomplete",
    ]


@pytest.mark.parametrize("part", ["files", "counts"])
def test_a_record_that_is_not_the_manifests_entry_is_named(copy, part):
    path = copy / layout.completion_record(OBJECTS[1])
    record = json.loads(path.read_text())
    if part == "files":
        record["files"].pop(layout.arrays_file(OBJECTS[1]))
    else:
        record["counts"]["ok_actions"] -= 1
    path.write_text(json.dumps(record))
    assert verify_dataset(copy) == [f"{layout.completion_record(OBJECTS[1])}: differs from the manifest's entry for {OBJECTS[1]}"]


def test_a_changed_shard_file_is_named_by_its_checksum_then_by_its_content(copy):
    actions = layout.partition_file("actions", OBJECTS[0])
    table = pq.read_table(copy / actions)
    pq.write_table(table.drop_columns(["greedy"]), copy / actions)
    (problem,) = verify_dataset(copy)
    assert problem.startswith(f"{actions}: sha256 ") and "differs from the record's" in problem
    record_new_bytes(copy, actions)
    assert verify_dataset(copy) == [
        f"{actions}: schema differs from schema.tables (columns {table.drop_columns(['greedy']).column_names})"]


def test_files_no_shard_owns_are_named(copy):
    first = OBJECTS[0]
    strays = [
        ".objects.parquet.0123.tmp",
        f"actions/object_id={first}/.part-0.parquet.4567.tmp",  # named once, as a temporary file
        "actions/object_id=stranger/part-0.parquet",
        "transitions/object_id=stranger/part-0.parquet",
        f"actions/pose={first}/part-0.parquet",
        f"transitions/object_id={first}/notes.txt",
        f"transitions/object_id={first}/.hidden",  # readers skip dot-files
        "arrays/stranger.h5",
        f"arrays/{first}.txt",
        f"arrays/.{first}.h5.89ab.tmp",  # named once, as a temporary file
        "arrays/.hidden",  # readers skip dot-files here too
    ]
    for relative in strays:
        (copy / relative).parent.mkdir(parents=True, exist_ok=True)
        (copy / relative).write_text("")
    assert verify_dataset(copy) == [
        ".objects.parquet.0123.tmp: temporary file left behind",
        f"actions/object_id={first}/.part-0.parquet.4567.tmp: temporary file left behind",
        f"arrays/.{first}.h5.89ab.tmp: temporary file left behind",
        "actions/object_id=stranger: not a shard in the manifest",
        f"actions/pose={first}: not a shard in the manifest",
        f"transitions/object_id={first}: unexpected files ['notes.txt']",
        "transitions/object_id=stranger: not a shard in the manifest",
        f"arrays/{first}.txt: not a shard in the manifest",
        "arrays/stranger.h5: not a shard in the manifest",
    ]


def test_verify_agrees_with_the_shards_own_checks(built):
    """Every shard of an intact dataset is complete by its record and its content is sound."""
    for object_id in OBJECTS:
        record = shards.read_record(built, object_id)
        assert shards.is_complete(built, object_id, record["fingerprint"]) == record
        assert shards.content_problems(built, record) == []
