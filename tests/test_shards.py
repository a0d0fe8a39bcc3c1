"""One shard on disk (pipeline/build/shards.py), in process: what ``write_shard`` writes reads
back as the ``ShardData`` it was given, its record names every file with its SHA-256, a write
that does not read back is refused, and each check (``read_record``, ``checksum_problems``,
``is_complete``, ``content_problems``) names what is wrong with a damaged shard.  A shard's
identity (``shard_inputs``) leaves out exactly the parameters it does not depend on.

The objects are the small evaluations of tests/test_rows.py: a shard is written in milliseconds,
so each test damages its own.
"""

from __future__ import annotations

import dataclasses
import json
import time

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from shapes import box_object

from pipeline.build import shards
from pipeline.build.atomic import file_sha256
from pipeline.build.rows import ShardError, build_shard
from pipeline.model.evaluation import evaluate_object
from pipeline.model.topple import ENGINE_REVISION
from schema import hdf5, layout, tables
from schema.version import SCHEMA_VERSION
from tests.test_rows import SMALL, TRIALS, spec_of

SHARD_FILES = {
    layout.partition_file("actions", "box"), layout.partition_file("transitions", "box"),
    layout.shard_rows_file("objects", "box"), layout.shard_rows_file("poses", "box"), layout.arrays_file("box"),
}


@pytest.fixture(scope="module")
def box():
    """(shard, inputs) of the small box."""
    spec = spec_of("box")
    return build_shard(spec, evaluate_object(box_object(), SMALL), TRIALS), shards.shard_inputs(spec, SMALL)


@pytest.fixture
def written(box, tmp_path):
    """(root, record, shard) of the box's shard written under a fresh directory."""
    shard, inputs = box
    started = time.process_time()
    record = shards.write_shard(tmp_path, shard, inputs)
    assert 0 <= record["timings"]["write"] <= time.process_time() - started, "CPU seconds of this write"
    return tmp_path, record, shard


def test_a_written_shard_reads_back_as_it_was_built(written, box):
    root, record, shard = written
    _, inputs = box
    assert set(record["files"]) == SHARD_FILES
    for relative, digest in record["files"].items():
        assert digest == file_sha256(root / relative), relative
    assert record["object_id"] == "box" and record["schema_version"] == SCHEMA_VERSION
    assert record["fingerprint"] == shards.fingerprint(inputs) and record["inputs"] == inputs
    assert record["counts"] == shard.counts
    assert set(record["timings"]) == set(shard.timings) | {"write"} and record["timings"]["write"] >= 0
    assert json.loads((root / layout.completion_record("box")).read_text()) == record
    assert shards.read_record(root, "box") == record

    for table in ("actions", "transitions"):
        assert pq.read_table(root / layout.partition_file(table, "box")).equals(shard.rows[table]), table
    for table in ("objects", "poses"):
        assert pq.read_table(root / layout.shard_rows_file(table, "box")).equals(shard.rows[table]), table
        assert pq.read_metadata(root / layout.shard_rows_file(table, "box")).row_group(0).column(0).compression == "ZSTD"

    with h5py.File(root / layout.arrays_file("box"), "r") as f:
        assert {k: hdf5._plain(v) for k, v in f.attrs.items()} == shard.attributes
        for spec in hdf5.OBJECT_ARRAYS:
            assert f[spec.name].dtype == spec.dtype
            np.testing.assert_array_equal(f[spec.name][()], shard.object_arrays[spec.name])
        assert sorted(f["poses"]) == [hdf5.pose_group(i).split("/")[1] for i in range(len(shard.pose_arrays))]
        for pose, arrays in enumerate(shard.pose_arrays):
            for spec in hdf5.POSE_ARRAYS:
                stored = f[f"{hdf5.pose_group(pose)}/{spec.name}"]
                assert stored.dtype == spec.dtype and stored.compression is None, "small arrays are stored contiguous"
                np.testing.assert_array_equal(stored[()], arrays[spec.name])
    assert shards.content_problems(root, record) == []
    assert shards.is_complete(root, "box", record["fingerprint"]) == record


def test_large_arrays_are_compressed_and_read_back_the_same(tmp_path):
    trials = 1000  # outcomes of 11 pushes x 1000 trials, int16: 22 kB, above the threshold
    config = SMALL.with_overrides({"topple.n_trials": trials})
    spec = spec_of("box")
    shard = build_shard(spec, evaluate_object(box_object(), config), trials)
    shards.write_shard(tmp_path, shard, shards.shard_inputs(spec, config))
    with h5py.File(tmp_path / layout.arrays_file("box"), "r") as f:
        outcomes = f[f"{hdf5.pose_group(0)}/outcomes"]
        assert outcomes.nbytes > shards.COMPRESS_ABOVE_BYTES
        assert (outcomes.compression, outcomes.compression_opts, outcomes.shuffle) == ("gzip", 4, True)
        np.testing.assert_array_equal(outcomes[()], shard.pose_arrays[0]["outcomes"])
        assert f["center_mass"].compression is None


def test_rewriting_a_shard_replaces_it_and_a_failed_write_leaves_no_record(written, box, monkeypatch):
    root, record, shard = written
    _, inputs = box
    assert shards.write_shard(root, shard, inputs)["files"] == record["files"], "same shard, same bytes"

    def short_writer(table: pa.Table):
        return lambda path: pq.write_table(table.slice(0, 1), path)

    monkeypatch.setattr(shards, "_parquet_writer", short_writer)
    with pytest.raises(OSError, match=rf"read back 1 rows, wrote {shard.rows['actions'].num_rows}$"):
        shards.write_shard(root, shard, inputs)
    assert shards.read_record(root, "box") is None, "the old record goes first"
    assert shards.is_complete(root, "box", record["fingerprint"]) is None
    assert pq.read_metadata(root / layout.partition_file("actions", "box")).num_rows == shard.rows["actions"].num_rows, \
        "the file that did not read back is not moved in"
    assert not list(root.rglob(f"*{layout.TEMP_SUFFIX}"))


def test_arrays_that_do_not_fit_their_layout_are_refused_before_the_record(box, tmp_path):
    shard, inputs = box
    fewer_actions = shard.rows["poses"].set_column(
        tables.POSES.get_field_index("n_actions"), tables.POSES.field("n_actions"),
        pa.array([n - 1 for n in shard.rows["poses"].column("n_actions").to_pylist()], pa.int32()))
    for bad in (dataclasses.replace(shard, rows={**shard.rows, "poses": fewer_actions}),
                dataclasses.replace(shard, attributes={**shard.attributes, "n_trials": TRIALS + 1})):
        with pytest.raises(ShardError, match=r"^box: HDF5 does not match its layout: /poses/000/outcomes: shape"):
            shards.write_shard(tmp_path, bad, inputs)
        assert shards.read_record(tmp_path, "box") is None
    with pytest.raises(ValueError, match="bad object id 'a/b'"):
        shards.write_shard(tmp_path, dataclasses.replace(shard, object_id="a/b"), inputs)


def test_records_that_are_absent_unreadable_or_without_fingerprint_read_as_none(written):
    root, record, _ = written
    path = root / layout.completion_record("box")
    for text in ("{", "[]", "{}", '{"fingerprint": 3}', '"text"'):
        path.write_text(text)
        assert shards.read_record(root, "box") is None, text
        assert shards.is_complete(root, "box", record["fingerprint"]) is None
    path.write_text(json.dumps({"fingerprint": "abc"}))
    assert shards.read_record(root, "box") == {"fingerprint": "abc"}
    assert shards.read_record(root, "nobody") is None


def test_checksum_problems_name_missing_and_changed_files(written):
    root, record, _ = written
    assert shards.checksum_problems(root, record) == []
    assert shards.checksum_problems(root, {}) == [], "a record without files has none to check"
    actions = layout.partition_file("actions", "box")
    (root / layout.arrays_file("box")).unlink()
    (root / actions).write_bytes(b"other bytes")
    assert shards.checksum_problems(root, record) == [
        f"{actions}: sha256 {file_sha256(root / actions)[:12]}... differs from the record's {record['files'][actions][:12]}...",
        f"{layout.arrays_file('box')}: missing",
    ]
    assert shards.is_complete(root, "box", record["fingerprint"]) is None


def test_a_shard_of_another_schema_version_is_not_complete(written):
    root, record, _ = written
    path = root / layout.completion_record("box")
    assert shards.is_complete(root, "box", record["fingerprint"]) == record
    assert shards.is_complete(root, "box", "another fingerprint") is None
    path.write_text(json.dumps({**record, "schema_version": "0.0"}))
    assert shards.is_complete(root, "box", record["fingerprint"]) is None


def test_content_problems_name_each_damaged_file(written):
    root, record, shard = written
    actions = layout.partition_file("actions", "box")
    poses = layout.shard_rows_file("poses", "box")
    arrays = layout.arrays_file("box")

    for key, relative in (("actions", actions), ("transitions", layout.partition_file("transitions", "box")), ("poses", poses)):
        n = record["counts"][key]
        miscounted = {**record, "counts": {**record["counts"], key: n + 1}}
        assert shards.content_problems(root, miscounted) == [f"{relative}: {n} rows, the manifest says {n + 1}"]

    pq.write_table(shard.rows["actions"].drop_columns(["q"]), root / actions)
    assert shards.content_problems(root, record) == [
        f"{actions}: schema differs from schema.tables (columns {shard.rows['actions'].drop_columns(['q']).column_names})"]
    def unreadable() -> str:
        """The reader's own words, on one line, cut to 120 characters."""
        with pytest.raises((OSError, pa.ArrowException)) as reading:
            pq.read_schema(root / actions)
        return f"{actions}: not a readable Parquet file ({' '.join(str(reading.value).split())[:120]})"

    (root / actions).write_bytes(b"not parquet\n  at all")
    assert shards.content_problems(root, record) == [unreadable()]
    (root / actions).unlink()
    assert shards.content_problems(root, record) == [unreadable()]
    prefix = f"{actions}: not a readable Parquet file ("
    assert len(unreadable()) == len(prefix) + 120 + 1, "a long reason (this one names the file) is cut to 120 characters"
    pq.write_table(shard.rows["actions"], root / actions)
    assert shards.content_problems(root, record) == []

    n_actions = shard.rows["poses"].column("n_actions").to_pylist()
    more = shard.rows["poses"].set_column(tables.POSES.get_field_index("n_actions"), tables.POSES.field("n_actions"),
                                          pa.array([n + 1 for n in n_actions], pa.int32()))
    pq.write_table(more, root / poses)
    problems = shards.content_problems(root, record)
    assert problems and all(p.startswith(f"{arrays}: /poses/") and "outcomes: shape" in p for p in problems)
    assert len(problems) == len(n_actions), "the actions per pose come from the poses table"
    pq.write_table(shard.rows["poses"], root / poses)

    with h5py.File(root / arrays, "r+") as f:
        f.attrs["object_id"] = "other"
    assert shards.content_problems(root, record) == [f"{arrays}: attribute object_id = 'other', expected 'box'"]
    with h5py.File(root / arrays, "r+") as f:
        f.attrs["object_id"] = "box"
        f.attrs["schema_version"] = "0.0"
    assert shards.content_problems(root, record) == [
        f"{arrays}: attribute schema_version = '0.0', expected {SCHEMA_VERSION!r}"]
    with h5py.File(root / arrays, "r+") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["n_poses"] = 7
    assert shards.content_problems(root, record) == [f"{arrays}: attribute n_poses = 7, expected {record['counts']['poses']}"]
    (root / arrays).write_bytes(b"not hdf5")
    (problem,) = shards.content_problems(root, record)
    assert problem.startswith(f"{arrays}: not a readable HDF5 file (")


def test_parquet_problems_checks_rows_only_when_given(written):
    root, _, shard = written
    path = root / layout.shard_rows_file("poses", "box")
    n = shard.counts["poses"]
    assert shards.parquet_problems(path, "p", tables.POSES, n) == []
    assert shards.parquet_problems(path, "p", tables.POSES, None) == []
    assert shards.parquet_problems(path, "p", tables.POSES, n + 2) == [f"p: {n} rows, the manifest says {n + 2}"]
    assert shards.parquet_problems(path, "p", tables.OBJECTS, n) == [f"p: schema differs from schema.tables (columns {tables.POSES.names})"]
    no_metadata = tables.POSES.remove_metadata()
    assert shards.parquet_problems(path, "p", no_metadata, n) == [], "descriptions are not part of the comparison"


def test_remove_temp_files_removes_only_temporary_files(tmp_path):
    for relative in (".a.parquet.tmp", "actions/object_id=x/.part-0.parquet.tmp", "arrays/.x.h5.tmp"):
        (tmp_path / relative).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / relative).write_text("partial")
    kept = ["keep.tmp", ".hidden", "arrays/x.h5"]
    for relative in kept:
        (tmp_path / relative).write_text("data")
    assert shards.remove_temp_files(tmp_path) == 3
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()) == sorted(kept)
    assert shards.remove_temp_files(tmp_path) == 0


def test_a_shards_identity_is_its_object_and_the_parameters_it_uses():
    spec = spec_of("box")
    inputs = shards.shard_inputs(spec, SMALL)
    assert inputs["schema_version"] == SCHEMA_VERSION and inputs["engine_revision"] == ENGINE_REVISION
    revised = {**inputs, "engine_revision": ENGINE_REVISION + 1}
    assert shards.fingerprint(revised) != shards.fingerprint(inputs), "another engine's shard is not resumed"
    assert inputs["object"] == {k: v for k, v in dataclasses.asdict(spec).items() if k != "path"}
    moved = dataclasses.replace(spec, path="/elsewhere/box.obj")
    assert shards.shard_inputs(moved, SMALL) == inputs, "the same mesh elsewhere is the same shard"
    for field, value in (("sha256", "cd" * 32), ("scale", 0.25), ("mass", 0.5), ("object_id", "box2"), ("source", "x")):
        other = shards.shard_inputs(dataclasses.replace(spec, **{field: value}), SMALL)
        assert shards.fingerprint(other) != shards.fingerprint(inputs), field
    reordered = {k: inputs[k] for k in reversed(list(inputs))}
    assert shards.fingerprint(reordered) == shards.fingerprint(inputs), "key order is no part of it"
    assert len(shards.fingerprint(inputs)) == 64
    every = SMALL.to_dict()
    # Only the service reads the budget's; the repeat choice is off.
    every["mdp"] = {k: v for k, v in every["mdp"].items() if k not in shards.BUDGET_ONLY["mdp"] + shards.REPEAT_CHOICE["mdp"]}
    assert {k: v for k, v in inputs["config"].items() if k != "topple"} == {k: v for k, v in every.items() if k != "topple"}


def test_corrections_and_maps_that_are_off_are_no_part_of_a_shards_identity():
    def unused(**overrides) -> dict:
        return shards.unused_by_shards(SMALL.with_overrides(overrides))

    spread, onward = shards.UNUSED_WHEN_OFF["landing_spread"], shards.UNUSED_WHEN_OFF["landing_onward"]
    boosted = shards.UNUSED_WHEN_OFF["boosted_map"]
    # The default plans with failures (its map is used), carries landings onward and applies the boosted
    # map, but spreads none.
    assert SMALL.mdp.plans_with_failures and SMALL.topple.applied_landing_onward and not SMALL.topple.applied_landing_spread
    assert SMALL.topple.applied_boosted_map
    budget = {"mdp": shards.BUDGET_ONLY["mdp"] + shards.REPEAT_CHOICE["mdp"]}  # the repeat choice is off too
    assert unused() == {"topple": spread, **budget}
    assert unused(**{"mdp.choose_for_repeats": True}) == {"topple": spread, **shards.BUDGET_ONLY}
    assert unused(**{"topple.landing_spread": 0.3}) == budget
    side = {"mdp.min_direction_z": -0.3}  # no boosted map: value iteration chooses no push the down map maps
    assert unused(**{"topple.landing_spread": 0.3, "topple.boosted_map": "", **side}) == {"topple": boosted, **budget}
    argmax = {"mdp": budget["mdp"] + shards.NEIGHBOURHOOD_CHOICE["mdp"]}
    assert unused(**{"topple.landing_spread": 0.3, "mdp.choice_radius": 0.0, **side}) == argmax, "the argmax reads no neighbourhood"
    assert unused(**{"topple.variant": "robust"}) == {"topple": spread + onward + boosted, **budget}
    serving = {"mdp": shards.SERVING_ONLY["mdp"] + budget["mdp"]}
    assert unused(**{"mdp.believe_failures": False}) == {**serving, "topple": spread}
    assert unused(**{"mdp.believe_failures": False, "topple.landing_spread": 0.3}) == serving

    base = shards.shard_inputs(spec_of("box"), SMALL)
    assert not set(spread) & set(base["config"]["topple"]) and set(onward) <= set(base["config"]["topple"])
    same = SMALL.with_overrides({"topple.landing_spread_poses": SMALL.topple.landing_spread_poses + 1})
    assert shards.shard_inputs(spec_of("box"), same) == base, "a parameter of a correction that is off changes nothing"
    narrower = SMALL.with_overrides({"mdp.budget_min_direction_z": 0.0})
    assert shards.shard_inputs(spec_of("box"), narrower) == base, "only the served budget reads its cut"
    other = SMALL.with_overrides({"topple.landing_onward_below": SMALL.topple.landing_onward_below / 2})
    assert shards.shard_inputs(spec_of("box"), other) != base
    repeating = SMALL.with_overrides({"mdp.choose_for_repeats": True})
    assert not set(shards.REPEAT_CHOICE["mdp"]) & set(base["config"]["mdp"]), "off, the repeat choice is no part of it"
    assert shards.shard_inputs(spec_of("box"), repeating) != base, "on, it moves the stored push"


def test_input_differences_recurse_into_sections():
    old = {"config": {"topple": {"n_trials": 5, "mu": 0.4}, "seed": 0}, "object": {"sha256": "a"}}
    new = {"config": {"topple": {"n_trials": 6, "mu": 0.4}, "seed": 0}, "object": {"sha256": "b"}}
    assert shards.input_differences(old, new) == ["config.topple.n_trials: 5 -> 6", "object.sha256: 'a' -> 'b'"]
    assert shards.input_differences(old, old) == []
    assert shards.input_differences({}, {"a": "x" * 38}) == [f"a: None -> {'x' * 38!r}"]
    assert shards.input_differences({}, {"a": "x" * 39}) == [f"a: None -> {repr('x' * 39)[:37]}..."]

