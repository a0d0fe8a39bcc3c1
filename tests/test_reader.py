# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
"""The dataset reader (schema/reader.py) that the service's Parquet path, the Python API and the
studies share: the tables it reads, the columns asked for, and every failure as a one-line
``DatasetUnreadable`` naming its file."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from schema import layout, tables
from schema.manifest import ManifestError, read_manifest
from schema.reader import Dataset, DatasetUnreadable
from tests.test_service import dataset  # noqa: F401 (fixture)

NOT_PARTITIONED = "'poses' is not partitioned; partitioned tables: ('actions', 'transitions')"


def hand_made(root: Path) -> Dataset:
    """Two objects' actions, written as the pipeline lays them out, read without a manifest."""
    for object_id, q in (("duck", [0.1, 0.2]), ("mug", [0.7])):
        path = root / layout.partition_file("actions", object_id)
        path.parent.mkdir(parents=True)
        pq.write_table(pa.table({"pose": list(range(len(q))), "action": [0] * len(q), "q": q}), path)
    pq.write_table(pa.table({"object_id": ["duck", "mug"], "n_poses": [2, 1]}), root / layout.OBJECTS_FILE)
    return Dataset(root, None)


def test_a_finished_dataset_opens_with_its_manifest(dataset):
    opened = Dataset.open(dataset)
    assert opened.root == Path(dataset)
    assert opened.manifest is not None and opened.manifest == read_manifest(dataset)


def test_a_directory_without_a_valid_manifest_is_unreadable_with_the_manifests_message(tmp_path):
    with pytest.raises(ManifestError) as said:
        read_manifest(tmp_path)
    with pytest.raises(DatasetUnreadable) as raised:
        Dataset.open(tmp_path)
    assert str(raised.value) == str(said.value) and str(said.value)
    assert raised.value.__cause__ is None and raised.value.__suppress_context__


def test_tables_are_read_with_the_columns_asked_for(tmp_path):
    data = hand_made(tmp_path)
    assert data.table("objects").to_pydict() == {"object_id": ["duck", "mug"], "n_poses": [2, 1]}
    assert data.table("objects", ["n_poses"]).column_names == ["n_poses"]
    duck = data.object_rows("actions", "duck")
    assert duck.column_names == ["pose", "action", "q"], "an object's rows without object_id"
    assert data.object_rows("actions", "duck", ["q", "pose"]).to_pydict() == {"q": [0.1, 0.2], "pose": [0, 1]}
    # Every object's rows, object_id from the partition directories, appended after the file's columns.
    every = data.partitioned("actions").sort_by([("object_id", "ascending"), ("pose", "ascending")])
    assert every.column_names == ["pose", "action", "q", "object_id"]
    assert every.to_pydict() == {"pose": [0, 1, 0], "action": [0, 0, 0], "q": [0.1, 0.2, 0.7],
                                 "object_id": ["duck", "duck", "mug"]}
    assert data.partitioned("actions", ["object_id", "q"]).column_names == ["object_id", "q"]


def test_only_the_partitioned_tables_are_read_by_object(tmp_path):
    assert tables.PARTITIONED == ("actions", "transitions")
    data = hand_made(tmp_path)
    for read in (lambda: data.object_rows("poses", "duck"), lambda: data.partitioned("poses")):
        with pytest.raises(ValueError) as raised:
            read()
        assert str(raised.value) == NOT_PARTITIONED
        assert not isinstance(raised.value, DatasetUnreadable), "a caller's mistake, not the dataset's"


def test_a_missing_file_or_table_is_unreadable_in_one_line_naming_it(tmp_path):
    data = hand_made(tmp_path)
    with pytest.raises(DatasetUnreadable) as raised:
        data.table("poses")
    assert str(raised.value) == f"{tmp_path / layout.POSES_FILE}: missing"
    with pytest.raises(DatasetUnreadable) as raised:
        data.object_rows("transitions", "duck")
    assert str(raised.value) == f"{tmp_path / layout.partition_file('transitions', 'duck')}: missing"
    with pytest.raises(DatasetUnreadable) as raised:
        data.partitioned("transitions")
    assert str(raised.value).startswith(f"{tmp_path / 'transitions'}: unreadable: ")
    assert raised.value.__cause__ is None and raised.value.__suppress_context__


def test_arrows_message_is_one_line_cut_at_200_characters(tmp_path):
    # A missing column: pyarrow names it and prints the file's schema, one field a line.
    data = hand_made(tmp_path)
    path = tmp_path / layout.partition_file("actions", "duck")
    with pytest.raises(pa.ArrowInvalid) as arrow:
        pq.read_table(path, columns=["nope"])
    assert "\n" in str(arrow.value) and str(arrow.value).startswith("No match for FieldRef.Name(nope) in pose: int64\n")
    with pytest.raises(DatasetUnreadable) as raised:
        data.object_rows("actions", "duck", ["nope"])
    prefix = f"{path}: unreadable: "
    message = str(raised.value)
    assert message.startswith(prefix + "No match for FieldRef.Name(nope) in pose: int64 action: int64 q: double")
    assert "\n" not in message and "  " not in message
    # The same through the whole table, whose columns carry object_id too.
    with pytest.raises(DatasetUnreadable) as raised:
        data.partitioned("actions", ["nope"])
    message = str(raised.value)
    assert message.startswith(f"{tmp_path / 'actions'}: unreadable: No match for FieldRef.Name(nope) in pose: int64 action: int64")
    assert "\n" not in message
    # A reason longer than 200 characters is cut at 200.
    long = tmp_path / ("long-" * 50)
    long.mkdir()
    (long / layout.POSES_FILE).write_bytes(b"not parquet")
    reason = (f"Could not open Parquet input source '{long / layout.POSES_FILE}': Parquet magic bytes not found in footer. "
              "Either the file is corrupted or this is not a parquet file.")
    assert len(reason) > 200
    with pytest.raises(DatasetUnreadable) as raised:
        Dataset(long, None).table("poses")
    assert str(raised.value) == f"{long / layout.POSES_FILE}: unreadable: {reason[:200]}"
    assert raised.value.__cause__ is None and raised.value.__suppress_context__
    # The whole table's reason is cut the same way.
    with pytest.raises(FileNotFoundError) as arrow:
        ds.dataset(long / "transitions", format="parquet", partitioning="hive")
    reason = " ".join(str(arrow.value).split())
    assert len(reason) > 200
    with pytest.raises(DatasetUnreadable) as raised:
        Dataset(long, None).partitioned("transitions")
    assert str(raised.value) == f"{long / 'transitions'}: unreadable: {reason[:200]}"
