"""The manifest and the consolidated tables (pipeline/build/manifest.py), in process: totals are
the sums of the shards' counts over the corpus's objects, CPU seconds are summed per stage, the
consolidated tables are the shards' rows in the order asked for (not the order workers finished),
and the code version names the commit and library versions a dataset was computed with.
"""

from __future__ import annotations

import copy
import datetime
import json
import re
import subprocess
from importlib import metadata
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.build import manifest
from pipeline.build.atomic import file_sha256
from schema import layout, tables
from schema.manifest import ManifestError, read_manifest
from schema.version import CODE_VERSION, SCHEMA_VERSION
from tests.test_rows import SMALL
from tests.test_verify import OBJECTS, build_small, small_corpus


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    return build_small(tmp_path_factory.mktemp("small") / "dataset")


def record(poses: int, actions: int, ok: int, transitions: int, **timings: float) -> dict:
    """A completion record as far as the manifest reads it."""
    return {"counts": {"poses": poses, "actions": actions, "ok_actions": ok, "transitions": transitions},
            "files": {f"{poses}.parquet": "ab" * 32}, "fingerprint": f"print {poses}", "timings": timings}


def test_totals_and_cpu_time_add_up_over_the_corpus_in_its_order():
    corpus = small_corpus(("random_000", "random_001", "random_002"))
    records = {  # out of corpus order, one object failed, one record of an object outside the corpus
        "random_002": record(2, 20, 15, 30, topple=0.25, write=0.0004),
        "random_000": record(3, 33, 20, 41, topple=1.5, suction=0.1234),
        "elsewhere": record(100, 100, 100, 100, topple=100.0),
    }
    untimed = {k: v for k, v in record(1, 2, 1, 1).items() if k != "timings"}  # a record without timings adds none
    corpus.specs.append(small_corpus(("random_003",)).specs[0])
    records["random_003"] = untimed
    failures = [{"object_id": "random_001", "path": corpus.specs[1].path, "reason": "random_001: zero volume", "kind": "mesh"}]
    run = {"workers": 1, "backend": "loky", "computed": 2, "reused": 0, "wall_s": 1.25}
    built = manifest.make_manifest(SMALL, corpus, records, {}, failures, run)

    assert built.counts.model_dump() == {"objects": 3, "failed": 1, "poses": 6, "actions": 55, "ok_actions": 36, "transitions": 72}
    assert list(built.shards) == ["random_000", "random_002", "random_003"], "corpus order"
    for object_id, entry in built.shards.items():
        assert entry.model_dump() == {k: records[object_id][k] for k in ("files", "counts", "fingerprint")}
    assert "elsewhere" not in built.shards
    assert built.timings.cpu_s_by_stage == {"suction": 0.123, "topple": 1.75, "write": 0.0}
    assert list(built.timings.cpu_s_by_stage) == ["suction", "topple", "write"]
    assert built.timings.cpu_s_total == round(0.25 + 0.0004 + 1.5 + 0.1234, 3)
    assert built.timings.wall_s == 1.25 and built.run == {"workers": 1, "backend": "loky", "computed": 2, "reused": 0}
    assert [f.object_id for f in built.failures] == ["random_001"] and built.failures[0].kind == "mesh"
    assert [o.object_id for o in built.corpus.objects] == [spec.object_id for spec in corpus.specs]
    assert built.corpus.name == "small" and built.corpus.objects[0].sha256 == corpus.specs[0].sha256
    assert built.schema_version == SCHEMA_VERSION and built.seed == SMALL.seed
    assert built.parameters.model_dump() == SMALL.to_dict()
    created = datetime.datetime.fromisoformat(built.created)
    assert created.utcoffset() == datetime.timedelta(0) and created.microsecond == 0
    assert abs((datetime.datetime.now(datetime.UTC) - created).total_seconds()) < 60


def test_a_build_with_no_shard_has_zero_totals():
    built = manifest.make_manifest(SMALL, small_corpus(()), {}, {}, [], {"wall_s": 0.5})
    assert built.counts.model_dump() == dict.fromkeys(("objects", "failed", "poses", "actions", "ok_actions", "transitions"), 0)
    assert built.timings.cpu_s_total == 0 and built.timings.cpu_s_by_stage == {} and built.shards == {}


def test_the_manifest_of_a_build_is_what_its_shards_and_tables_say(built):
    written = read_manifest(built)
    for object_id in OBJECTS:
        entry = written.shards[object_id]
        shard_record = (built / layout.completion_record(object_id)).read_text()
        assert entry.fingerprint in shard_record
        for relative, digest in entry.files.items():
            assert file_sha256(built / relative) == digest
    for key in ("poses", "actions", "ok_actions", "transitions"):
        assert getattr(written.counts, key) == sum(getattr(e.counts, key) for e in written.shards.values())
    for name, entry in written.tables.items():
        assert file_sha256(built / name) == entry.sha256, name
    assert written.tables[layout.OBJECTS_FILE].rows == len(OBJECTS)
    assert written.tables[layout.POSES_FILE].rows == written.counts.poses
    assert manifest.make_manifest(SMALL, small_corpus(), {}, {}, [], {"wall_s": 0.0}).code_version == written.code_version


def test_consolidated_tables_follow_the_order_given_and_read_each_shard_from_its_source(built, tmp_path):
    order = list(reversed(OBJECTS))
    out = tmp_path / "out"
    written = manifest.consolidate(out, order, dict.fromkeys(order, built))
    for table, name in (("objects", layout.OBJECTS_FILE), ("poses", layout.POSES_FILE)):
        stored = pq.read_table(out / name)
        assert stored.schema.equals(tables.TABLES[table]), name
        assert written[name] == {"sha256": file_sha256(out / name), "rows": stored.num_rows}
        ids = stored.column("object_id").to_pylist()
        assert set(ids) == set(order) and ids == sorted(ids, key=order.index), f"{name} in the order given"
        assert pq.read_metadata(out / name).row_group(0).column(0).compression == "ZSTD"
        in_build_order = pq.read_table(built / name)
        assert stored.sort_by("object_id").equals(in_build_order.sort_by("object_id")), "the same rows"
    assert written[layout.POSES_FILE]["rows"] == read_manifest(built).counts.poses
    assert not list(out.rglob(f"*{layout.TEMP_SUFFIX}"))

    # Each object's rows come from its source; the default source is the root itself.
    mixed = tmp_path / "mixed"
    manifest.consolidate(mixed, [OBJECTS[1]], {OBJECTS[1]: built})
    assert pq.read_table(mixed / layout.OBJECTS_FILE).column("object_id").to_pylist() == [OBJECTS[1]]
    again = manifest.consolidate(built, list(OBJECTS))
    assert again == {name: {"sha256": entry.sha256, "rows": entry.rows} for name, entry in read_manifest(built).tables.items()
                     if name in (layout.OBJECTS_FILE, layout.POSES_FILE)}, "the build's own tables, byte for byte"


def test_consolidating_no_object_writes_empty_tables_of_the_schema(tmp_path):
    written = manifest.consolidate(tmp_path, [])
    for table, name in (("objects", layout.OBJECTS_FILE), ("poses", layout.POSES_FILE)):
        stored = pq.read_table(tmp_path / name)
        assert stored.num_rows == 0 and stored.schema.equals(tables.TABLES[table])
        assert written[name] == {"sha256": file_sha256(tmp_path / name), "rows": 0}


def test_a_written_manifest_reads_back(built, tmp_path):
    original = read_manifest(built)
    manifest.write_manifest(tmp_path, original)
    assert read_manifest(tmp_path) == original


def test_a_manifest_is_parsed_from_the_bytes_given_and_refused_with_a_one_line_reason(built, tmp_path):
    """``read_manifest``: the bytes a caller read and hashed are parsed, not the file read again (a
    rebuild may have replaced it meanwhile); a file that is not JSON, of another schema version or
    not a manifest is refused with where and why."""
    raw = (built / "manifest.json").read_bytes()
    data = json.loads(raw)
    (tmp_path / "manifest.json").write_bytes(raw)
    assert read_manifest(tmp_path, json.dumps({**data, "seed": data["seed"] + 1}).encode()).seed == data["seed"] + 1
    assert read_manifest(tmp_path).seed == data["seed"]
    path = tmp_path / "manifest.json"

    def refused(content: str, reason: str) -> None:
        path.write_text(content)
        with pytest.raises(ManifestError) as refusal:
            read_manifest(tmp_path)
        assert str(refusal.value) == reason

    refused('{"schema_version": ', f"{path}: not valid JSON (Expecting value: line 1 column 20 (char 19))")
    refused(json.dumps({**data, "schema_version": "0.9"}),
            f"{tmp_path}: dataset schema version '0.9', this code reads '{SCHEMA_VERSION}'; rebuild the dataset with "
            "this code (make dataset) or read it with the code that wrote it")
    bad = copy.deepcopy(data)
    bad["counts"]["poses"] = "many"
    refused(json.dumps(bad), f"{path}: counts.poses: Input should be a valid integer, unable to parse string as an integer")


def test_the_code_version_names_the_package_the_commit_and_the_libraries(monkeypatch):
    version = manifest.code_version()
    assert version["package"] == CODE_VERSION
    assert re.fullmatch(r"3\.\d+\.\d+.*", version["python"])
    assert set(version["libraries"]) == set(manifest.LIBRARIES)
    assert version["libraries"]["numpy"] == np.__version__ == metadata.version("numpy")
    head = subprocess.run(["git", "rev-parse", "HEAD"], check=False, cwd=Path(manifest.__file__).parent, capture_output=True, text=True)
    if head.returncode == 0:
        assert version["git_commit"] == head.stdout.strip() and re.fullmatch(r"[0-9a-f]{40}", version["git_commit"])
    monkeypatch.setattr(manifest, "LIBRARIES", ("numpy", "no-such-library-anywhere"))
    assert manifest.code_version()["libraries"] == {"numpy": np.__version__, "no-such-library-anywhere": None}


def test_the_commit_is_none_outside_git_or_without_it(monkeypatch):
    calls = []

    def no_git(*args, **kwargs):
        calls.append(kwargs)
        raise FileNotFoundError("git")

    monkeypatch.setattr(manifest.subprocess, "run", no_git)
    assert manifest.code_version()["git_commit"] is None
    assert calls[0]["cwd"] == Path(manifest.__file__).resolve().parent and calls[0]["timeout"] > 0

    def not_a_repository(*args, **kwargs):
        return subprocess.CompletedProcess(args, 128, stdout="", stderr="fatal: not a git repository")

    monkeypatch.setattr(manifest.subprocess, "run", not_a_repository)
    assert manifest.code_version()["git_commit"] is None

    def hung(*args, **kwargs):
        raise subprocess.TimeoutExpired("git", kwargs["timeout"])

    monkeypatch.setattr(manifest.subprocess, "run", hung)
    assert manifest.code_version()["git_commit"] is None


def test_a_parameter_that_names_a_file_is_recorded_and_digested_by_the_files_content(tmp_path):
    """The boosted map is a parameter that names a file: the manifest records the content it read, and
    the parameters' digest (``/health``'s ``parameters_sha256``) follows the content, not the name."""
    import hashlib

    from pipeline.model.boosted_map import load_trees
    from schema.manifest import Manifest
    from tests.test_boosted_map import _map, _stump

    def built(config):
        load_trees.cache_clear()  # the build process reads the file as it is now
        made = manifest.make_manifest(config, small_corpus(()), {}, {}, [], {"wall_s": 0.0})
        return Manifest.model_validate(json.loads(made.to_json()))  # as a reader gets it

    trees = tmp_path / "robot.trees.json"
    trees.write_text(json.dumps(_map(_stump(0, 0.0, -1.0, 2.0))))
    named = SMALL.with_overrides({"topple.boosted_map": str(trees)})
    first = built(named)
    assert first.parameter_files == {"topple.boosted_map": hashlib.sha256(trees.read_bytes()).hexdigest()}

    trees.write_text(json.dumps(_map(_stump(0, 0.0, -1.0, 3.0))))  # a refit written to the same name
    second = built(named)
    assert second.parameters == first.parameters, "the parameters alone cannot tell the two models apart"
    assert second.parameter_files != first.parameter_files
    assert second.parameters_sha256() != first.parameters_sha256()

    elsewhere = tmp_path / "copy" / "robot.trees.json"
    elsewhere.parent.mkdir()
    elsewhere.write_bytes(trees.read_bytes())
    moved = built(SMALL.with_overrides({"topple.boosted_map": str(elsewhere)}))
    assert moved.parameters != second.parameters and moved.parameters_sha256() == second.parameters_sha256(), \
        "the same trees elsewhere are the same model"

    without = built(SMALL.with_overrides({"topple.boosted_map": "", "mdp.min_direction_z": SMALL.topple.down_map_z}))
    assert without.parameter_files == {}
    canonical = json.dumps(without.parameters.model_dump(mode="json"), sort_keys=True, separators=(",", ":")).encode()
    assert without.parameters_sha256() == hashlib.sha256(canonical).hexdigest(), "no file: the parameters' digest as before"
    # A manifest from before the field reads as one whose parameters name no file.
    older = json.loads(without.to_json())
    del older["parameter_files"]
    assert Manifest.model_validate(older).parameters_sha256() == without.parameters_sha256()


@pytest.mark.parametrize("files, message", [
    ({"topple.no_such_key": "ab" * 32}, "is no parameter that names a file"),
    ({"boosted_map": "ab" * 32}, "is no parameter that names a file"),
    ({"seed": "ab" * 32}, "is no parameter that names a file"),
    ({"topple.variant": "ab" * 32}, "is no parameter that names a file"),
    ({"topple.boosted_map": "not a digest"}, "is no SHA-256"),
])
def test_a_recorded_file_that_names_no_parameter_or_holds_no_digest_is_refused_in_one_line(built, tmp_path, files, message):
    import shutil

    copy_dir = tmp_path / "copy"
    shutil.copytree(built, copy_dir)
    data = json.loads((copy_dir / layout.MANIFEST).read_text())
    data["parameter_files"] = files
    (copy_dir / layout.MANIFEST).write_text(json.dumps(data))
    with pytest.raises(ManifestError, match=f"manifest.json: parameter_files: Value error, .*{message}") as raised:
        read_manifest(copy_dir)
    assert "\n" not in str(raised.value)
