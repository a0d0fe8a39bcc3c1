"""Object ids as partition values: every id the layout accepts is read back as a string, by each
reader DATASET.md names, when it is the only partition read (a reader then infers its type from
that one value)."""

from __future__ import annotations

import duckdb
import polars as pl
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from pipeline.build.corpus import object_id_from_name
from schema.layout import HIVE_NULL, READER_WORDS, check_object_id, partition_file

# Near misses of the words the readers type, and ids that look like other literals.
ACCEPTED = ["random_001", "nanx", "infinite", "Inf_1", "_inf", "truee", "t", "f", "null", "None", "na", "today",
            "now", "e5", "x1", "_1", "inf.0", "epoch_2", "__hive_default_partition__"]


def _partition_type(root, object_id):
    path = root / partition_file("actions", object_id)
    path.parent.mkdir(parents=True)
    pq.write_table(pa.table({"pose": pa.array([0], pa.int32())}), path)
    arrow = ds.dataset(root / "actions", format="parquet", partitioning="hive").to_table()
    frame = pl.read_parquet(str(root / "actions" / "**" / "*.parquet"), hive_partitioning=True)
    sql = f"select typeof(object_id), object_id from read_parquet('{root}/actions/*/*.parquet', hive_partitioning=true)"
    duck = duckdb.connect().execute(sql).fetchone()
    return (str(arrow.schema.field("object_id").type), arrow["object_id"][0].as_py(),
            str(frame.schema["object_id"]), frame["object_id"][0], duck[0], duck[1])


@pytest.mark.parametrize("object_id", ACCEPTED)
def test_every_accepted_id_is_read_back_as_itself_by_pyarrow_polars_and_duckdb(tmp_path, object_id):
    assert check_object_id(object_id) == object_id
    assert _partition_type(tmp_path, object_id) == ("string", object_id, "String", object_id, "VARCHAR", object_id)


@pytest.mark.parametrize("word", sorted(READER_WORDS | {w.upper() for w in READER_WORDS} | {w.title() for w in READER_WORDS} | {HIVE_NULL}))
def test_ids_a_reader_would_type_are_refused_and_a_file_name_that_is_one_gets_a_prefix(word):
    with pytest.raises(ValueError, match=f"bad object id '{word}': Parquet readers would read it as a number, date, boolean or null"):
        check_object_id(word)
    derived = object_id_from_name(word)
    assert derived == f"obj_{word}" and check_object_id(derived) == derived

