"""Reading a finished dataset: the one reader that the service and the studies share.

    dataset = Dataset.open("data/dataset")        # checks manifest.json (schema.manifest)
    poses = dataset.table("poses", columns=["object_id", "pose", "v_s"])
    transitions = dataset.partitioned("transitions")              # every object
    actions = dataset.object_rows("actions", "duck", columns=["pose", "action", "p_topple"])

Every failure is a ``DatasetUnreadable`` with a one-line message naming the file,
so a caller can report it or turn it into its own error.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schema import layout, tables
from schema.manifest import Manifest, ManifestError, read_manifest

CONSOLIDATED = {"objects": layout.OBJECTS_FILE, "poses": layout.POSES_FILE}


class DatasetUnreadable(ValueError):
    """A dataset file that is missing or cannot be read (one-line message)."""


@dataclass(frozen=True)
class Dataset:
    """A finished dataset directory and its validated manifest (``open``).

    Constructed directly with ``manifest=None``, it reads tables that were not
    written by the pipeline (hand-made tables in tests) without any check.
    """

    root: Path
    manifest: Manifest | None

    @classmethod
    def open(cls, root: str | Path) -> Dataset:
        try:
            return cls(Path(root), read_manifest(root))
        except ManifestError as err:
            raise DatasetUnreadable(str(err)) from None

    def table(self, name: str, columns: list[str] | None = None) -> pa.Table:
        """A consolidated table (``objects`` or ``poses``), in corpus order."""
        return _read_file(self.root / CONSOLIDATED[name], columns)

    def object_rows(self, name: str, object_id: str, columns: list[str] | None = None) -> pa.Table:
        """One object's rows of a partitioned table (``actions`` or ``transitions``), without ``object_id``."""
        if name not in tables.PARTITIONED:
            raise ValueError(f"{name!r} is not partitioned; partitioned tables: {tables.PARTITIONED}")
        return _read_file(self.root / layout.partition_file(name, layout.check_object_id(object_id)), columns)

    def partitioned(self, name: str, columns: list[str] | None = None) -> pa.Table:
        """Every object's rows of a partitioned table, with ``object_id`` from the partition directories."""
        if name not in tables.PARTITIONED:
            raise ValueError(f"{name!r} is not partitioned; partitioned tables: {tables.PARTITIONED}")
        import pyarrow.dataset as ds  # here: it imports pandas, which a server starting up does not need

        try:
            dataset = ds.dataset(self.root / name, format="parquet", partitioning="hive")
            return dataset.to_table(columns=columns)
        except (OSError, pa.ArrowException) as err:
            raise DatasetUnreadable(f"{self.root / name}: unreadable: {' '.join(str(err).split())[:200]}") from None


def _read_file(path: Path, columns: list[str] | None) -> pa.Table:
    try:
        return pq.read_table(path, columns=columns)
    except FileNotFoundError:
        raise DatasetUnreadable(f"{path}: missing") from None
    except (OSError, pa.ArrowException) as err:
        raise DatasetUnreadable(f"{path}: unreadable: {' '.join(str(err).split())[:200]}") from None
