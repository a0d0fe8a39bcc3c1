"""Issue 4 acceptance: a small dataset builds with the real compute, verifies, survives
corruption checks, SIGKILL and resume, and gives identical tables with 1 or 2 workers
and on dask; broken meshes are recorded as failures; analysts' readers agree with
the manifest.

Kept small (3 objects, 30 pushes per pose, 5 trials, light suction sampling) so the
whole file runs in a couple of minutes on 2 cores.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import duckdb
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest
import trimesh

from pipeline.build import dataset, fanout, rows, shards
from pipeline.build.atomic import file_sha256
from pipeline.build.corpus import read_list
from pipeline.build.dataset import compute_shard, staging_dir
from pipeline.build.fanout import SchedulerError
from pipeline.build.verify import verify_dataset
from pipeline.cli import main
from pipeline.model.config import Config
from pipeline.numerics import numpy_simd
from schema import TABLES, layout
from schema.manifest import read_manifest
from schema.reader import Dataset

OBJECTS = ["random_000", "random_002", "random_001"]
"""Small meshes from pybullet_data, listed by path as a user's list file would."""

PARAMS = [
    "--contacts", "30",
    "--trials", "5",
    "--set", "suction.n_candidates=20",
    "--set", "suction.n_samples=5",
    "--no-progress",
]
SORT_KEYS = {
    "objects": ["object_id"],
    "poses": ["object_id", "pose"],
    "actions": ["object_id", "pose", "action"],
    "transitions": ["object_id", "pose", "action", "next_pose"],
}


def write_corpus(directory: Path, names: list[str], extra_rows: str = "") -> Path:
    rows = "".join(f"{n},pybullet_data/random_urdfs,random_urdfs/{n[-3:]}/{n[-3:]}.obj,0.015,0.1\n" for n in names)
    path = directory / "corpus.csv"
    path.write_text("object_id,source,path,scale,mass\n" + rows + extra_rows)
    return path


def build(corpus: Path, out: Path, *extra: str) -> int:
    return main(["dataset", "--corpus", str(corpus), "--out", str(out), *PARAMS, *extra])


def read_tables(root: Path) -> dict[str, pa.Table]:
    """Every table as analysts read it, in a canonical order."""
    tables = {}
    for name in ("objects", "poses"):
        tables[name] = pq.read_table(root / f"{name}.parquet")
    for name in ("actions", "transitions"):
        table = ds.dataset(root / name, format="parquet", partitioning="hive").to_table()
        tables[name] = table.sort_by([(k, "ascending") for k in SORT_KEYS[name]])
    return tables


def read_arrays(root: Path) -> dict[str, np.ndarray]:
    arrays = {}
    for path in sorted((root / "arrays").glob("*.h5")):
        with h5py.File(path, "r") as f:
            f.visititems(lambda name, item: arrays.__setitem__(f"{path.stem}/{name}", item[()]) if isinstance(item, h5py.Dataset) else None)
    return arrays


def assert_same_dataset(a: Path, b: Path) -> None:
    tables_a, tables_b = read_tables(a), read_tables(b)
    for name in tables_a:
        assert tables_a[name].equals(tables_b[name]), f"{name} differs"
    arrays_a, arrays_b = read_arrays(a), read_arrays(b)
    assert arrays_a.keys() == arrays_b.keys()
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)
    manifest_a, manifest_b = read_manifest(a), read_manifest(b)
    assert manifest_a.counts == manifest_b.counts
    assert manifest_a.tables == manifest_b.tables, "consolidated tables are byte-identical"


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    return write_corpus(tmp_path_factory.mktemp("corpus"), OBJECTS)


@pytest.fixture(scope="module")
def reference(corpus, tmp_path_factory) -> Path:
    """The dataset every other run is compared with: 2 local workers."""
    out = tmp_path_factory.mktemp("reference") / "dataset"
    assert build(corpus, out, "--workers", "2") == 0
    return out


def test_dataset_builds_with_manifest_and_verifies(reference, capsys):
    manifest = read_manifest(reference)
    counts = manifest.counts
    assert counts.objects == 3 and counts.failed == 0 and manifest.failures == []
    assert counts.poses >= 3
    assert counts.poses * 30 <= counts.actions <= counts.poses * 31, "30 pushes + Max-Height per pose"
    assert manifest.parameters.contacts.n_contacts == 30
    assert manifest.parameters.topple.n_trials == 5
    assert manifest.seed == 0 and manifest.schema_version
    assert manifest.code_version.package
    blas = manifest.code_version.blas  # the kernel the build computed with (pipeline.numerics)
    assert set(blas) == {"library", "version", "kernel", "requested"}
    assert blas["library"] == "openblas" and blas["kernel"]
    assert manifest.code_version.simd == numpy_simd()  # numpy's own loops, recorded, not pinned
    assert [o.object_id for o in manifest.corpus.objects] == OBJECTS
    assert all(len(o.sha256) == 64 for o in manifest.corpus.objects)
    assert set(manifest.shards) == set(OBJECTS)
    assert {"topple", "suction", "write"} <= set(manifest.timings.cpu_s_by_stage)

    for name, table in read_tables(reference).items():
        assert table.schema.equals(_with_partition_key_last(TABLES[name], name), check_metadata=False), name
    assert read_tables(reference)["objects"].column("object_id").to_pylist() == OBJECTS, "corpus order"

    assert verify_dataset(reference) == []
    capsys.readouterr()
    assert main(["verify", str(reference)]) == 0
    assert capsys.readouterr().out.startswith("ok: ")


def _with_partition_key_last(schema: pa.Schema, name: str) -> pa.Schema:
    """Hive readers append the partition column after the file's columns."""
    if name not in ("actions", "transitions"):
        return schema
    return schema.remove(schema.get_field_index("object_id")).append(pa.field("object_id", pa.string()))


def test_rerun_reuses_every_shard(reference, corpus, tmp_path, capsys):
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    before = snapshot(copy)
    capsys.readouterr()
    assert build(corpus, copy, "--workers", "2") == 0
    assert "up to date: all 3 objects" in capsys.readouterr().err
    assert snapshot(copy) == before, "a run with nothing to do writes nothing"
    assert not staging_dir(copy).exists()
    assert_same_dataset(reference, copy)


def test_a_rerun_records_the_map_file_of_a_build_from_before_parameter_files(reference, corpus, tmp_path, capsys):
    """A dataset built before the manifest recorded the boosted map's content is not up to date: the rerun
    reuses every shard and writes a manifest that names the content, so /health's digest is the model's."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    data = json.loads((copy / "manifest.json").read_text())
    recorded = data.pop("parameter_files")
    assert recorded, "the default model's boosted map is a file"
    (copy / "manifest.json").write_text(json.dumps(data))
    capsys.readouterr()
    assert build(corpus, copy, "--workers", "2") == 0
    assert "up to date" not in capsys.readouterr().err
    rebuilt = read_manifest(copy)
    assert rebuilt.parameter_files == recorded and (rebuilt.run["computed"], rebuilt.run["reused"]) == (0, len(OBJECTS))


def test_a_rerun_rewrites_consolidated_tables_damaged_since_the_build(reference, corpus, tmp_path, capsys):
    # Every shard intact, but poses.parquet cut short and a served table overwritten in place: a rerun
    # used to say "up to date" and leave them (verify found them); it now writes them again from the shards.
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    poses = copy / "poses.parquet"
    poses.write_bytes(poses.read_bytes()[:1000])
    served_actions = copy / "served" / "actions.arrow"
    damaged = bytearray(served_actions.read_bytes())
    damaged[len(damaged) // 2: len(damaged) // 2 + 4] = b"XXXX"
    served_actions.write_bytes(bytes(damaged))
    assert main(["verify", str(copy)]) == 1
    capsys.readouterr()
    assert build(corpus, copy, "--workers", "2") == 0
    err = capsys.readouterr().err
    assert "every shard is complete but poses.parquet: sha256" in err and "(and 1 more)" in err
    assert (read_manifest(copy).run["computed"], read_manifest(copy).run["reused"]) == (0, len(OBJECTS))
    assert main(["verify", str(copy)]) == 0
    assert_same_dataset(reference, copy)
    assert file_sha256(served_actions) == file_sha256(reference / "served" / "actions.arrow")
    (copy / "objects.parquet").unlink()  # one table: the line names it alone
    assert build(corpus, copy, "--workers", "1") == 0
    assert f"{copy}: every shard is complete but objects.parquet: missing; writing the tables again from the shards\n" in (
        capsys.readouterr().err)
    assert_same_dataset(reference, copy)


def test_served_tables_the_manifest_does_not_describe_are_written_again(reference, corpus, tmp_path, capsys):
    """Served bytes as recorded, but not the tables this manifest's build wrote (here a row count that is
    not the file's): not up to date, whatever the checksums say; the rerun writes them again from the shards."""
    from schema import served

    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    relative = served.FILES["actions"]
    data = json.loads((copy / layout.MANIFEST).read_text())
    rows = data["tables"][relative]["rows"]
    data["tables"][relative]["rows"] = rows + 1
    (copy / layout.MANIFEST).write_text(json.dumps(data))
    assert verify_dataset(copy) == [f"{relative} holds {rows} rows, manifest.json says {rows + 1}"]
    capsys.readouterr()
    assert build(corpus, copy, "--workers", "1") == 0
    assert "up to date" not in capsys.readouterr().err
    assert read_manifest(copy).tables[relative].rows == rows
    assert (read_manifest(copy).run["computed"], read_manifest(copy).run["reused"]) == (0, len(OBJECTS))
    assert verify_dataset(copy) == []


def test_a_lost_manifest_is_written_again_from_the_shards(reference, corpus, tmp_path, capsys):
    """Every shard complete but no readable manifest (deleted, or cut short): not up to date; the rerun
    reuses every shard and writes the tables and the manifest again."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    # The manifest also says how the run was made: one worker as asked, else every core (loky's default).
    for damage, workers in (((copy / layout.MANIFEST).unlink, 1),
                            (lambda: (copy / layout.MANIFEST).write_text('{"schema_ver'), fanout.default_workers())):
        damage()
        capsys.readouterr()
        assert build(corpus, copy, *(["--workers", "1"] if workers == 1 else [])) == 0
        assert f"resuming: {len(OBJECTS)} of {len(OBJECTS)} objects already complete in {copy}\n" in capsys.readouterr().err
        run = read_manifest(copy).run
        assert {key: run[key] for key in ("workers", "backend", "scheduler", "computed", "reused")} == {
            "workers": workers, "backend": "loky", "scheduler": None, "computed": 0, "reused": len(OBJECTS)}
        assert 0 < read_manifest(copy).timings.wall_s < 600, "this run's wall time, from its start"
        assert verify_dataset(copy) == [] and not staging_dir(copy).exists()
        assert_same_dataset(reference, copy)


def snapshot(root: Path) -> dict[str, tuple[str, int]]:
    """Every file under ``root`` (but the lock) -> (SHA-256, mtime)."""
    return {
        p.relative_to(root).as_posix(): (file_sha256(p), p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def assert_intact(root: Path, before: dict) -> None:
    """The finished dataset is exactly as it was: verifiable and servable."""
    assert snapshot(root) == before
    assert verify_dataset(root) == []
    Dataset.open(root).table("poses")


def test_failed_runs_leave_the_finished_dataset_intact(reference, corpus, tmp_path, capsys, monkeypatch):
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    before = snapshot(copy)
    monkeypatch.setattr(fanout, "CONNECT_TIMEOUT_S", 0.5)
    unreachable = ["--scheduler", "tcp://127.0.0.1:1"]

    # Nothing to compute: the scheduler is never contacted, nothing is written.
    assert build(corpus, copy, *unreachable) == 0
    assert_intact(copy, before)

    # One more object, but no scheduler: the run fails and the old dataset stays.
    grown = write_corpus(tmp_path, [*OBJECTS, "random_003"])
    capsys.readouterr()
    assert build(grown, copy, *unreachable) == 1
    assert "cannot connect to the dask scheduler at tcp://127.0.0.1:1" in capsys.readouterr().err
    assert_intact(copy, before)
    assert not staging_dir(copy).exists(), "no empty hidden staging directory is left beside --out"

    # Bad parameters, and a strict run that meets a broken mesh, change nothing either.
    assert build(corpus, copy, "--set", "topple.mu_table_mean=many") == 2
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nf 1 2 3\n")
    broken = write_corpus(tmp_path, OBJECTS, "flat,,flat.obj,1,0.1\n")
    assert build(broken, copy, "--strict", "--workers", "1") == 1
    assert_intact(copy, before)
    assert not staging_dir(copy).exists(), "the failed object's staging is gone; nothing else was staged"

    # A fresh --out on an unreachable scheduler: neither it nor a staging directory is left.
    fresh = tmp_path / "fresh" / "sched"
    assert build(grown, fresh, *unreachable) == 1
    assert not (tmp_path / "fresh").exists()


def test_analysts_read_the_tables_and_counts_match_the_manifest(reference):
    counts = read_manifest(reference).counts.model_dump()
    actions = ds.dataset(reference / "actions", format="parquet", partitioning="hive")
    transitions = ds.dataset(reference / "transitions", format="parquet", partitioning="hive")
    assert actions.count_rows() == counts["actions"]
    assert transitions.count_rows() == counts["transitions"]
    assert pq.read_metadata(reference / "poses.parquet").num_rows == counts["poses"]
    assert pq.read_metadata(reference / "objects.parquet").num_rows == counts["objects"]

    con = duckdb.connect()
    root = reference.as_posix()
    glob = "read_parquet('{}/{}/*/*.parquet', hive_partitioning = true)"
    assert con.execute(f"select count(*) from {glob.format(root, 'actions')}").fetchone()[0] == counts["actions"]
    assert con.execute(f"select count(*) from {glob.format(root, 'transitions')}").fetchone()[0] == counts["transitions"]
    ok = con.execute(f"select count(*) from {glob.format(root, 'actions')} where status = 'ok'").fetchone()[0]
    assert ok == counts["ok_actions"]

    # The README's join: transitions with the V_s of the pose they lead to.
    joined = con.execute(
        f"""
        select t.object_id, t.pose, t.action, sum(t.probability) as total, sum(t.probability * p.v_s) as greedy
        from {glob.format(root, 'transitions')} t
        join '{root}/poses.parquet' p on p.object_id = t.object_id and p.pose = t.next_pose
        group by all
        """
    ).fetchall()
    assert len(joined) == ok
    assert all(abs(total - 1) < 1e-9 for *_, total, _ in joined)
    by_object = con.execute(
        f"select object_id, avg(p_topple) from {glob.format(root, 'actions')} group by all order by 1"
    ).fetchall()
    assert [row[0] for row in by_object] == sorted(OBJECTS)
    assert all(0 <= row[1] <= 1 for row in by_object)

    greedy = con.execute(f"select object_id, pose, action, greedy from {glob.format(root, 'actions')} where status = 'ok'").fetchall()
    stored = {(o, p, a): g for o, p, a, g in greedy}
    for object_id, pose, action, _, expected in joined:
        assert stored[(object_id, pose, action)] == pytest.approx(expected, abs=1e-9)

    # Every q from the tables alone: V_T where the push leads, the failed pose's value where it stays.
    q = con.execute(
        f"""
        select t.object_id, t.pose, t.action, a.q,
               sum(t.probability * case when t.next_pose = t.pose then s.v_failed else p.v_t end) as recomputed
        from {glob.format(root, 'transitions')} t
        join {glob.format(root, 'actions')} a using (object_id, pose, action)
        join '{root}/poses.parquet' p on p.object_id = t.object_id and p.pose = t.next_pose
        join '{root}/poses.parquet' s on s.object_id = t.object_id and s.pose = t.pose
        group by all
        """
    ).fetchall()
    assert len(q) == ok and all(stored == pytest.approx(recomputed, abs=1e-9) for *_, stored, recomputed in q)


def test_verify_fails_after_a_shard_is_corrupted(reference, tmp_path, capsys):
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    target = copy / layout.partition_file("actions", OBJECTS[1])
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0xFF
    target.write_bytes(bytes(data))
    (copy / layout.arrays_file(OBJECTS[2])).unlink()
    (copy / "transitions" / "object_id=stranger").mkdir()

    capsys.readouterr()
    assert main(["verify", str(copy)]) == 1
    out = capsys.readouterr().out
    assert f"actions/object_id={OBJECTS[1]}/part-0.parquet: sha256" in out
    assert f"arrays/{OBJECTS[2]}.h5: missing" in out
    assert "transitions/object_id=stranger: not a shard in the manifest" in out
    assert OBJECTS[0] not in out


def test_verify_names_each_kind_of_damage(reference, tmp_path):
    assert verify_dataset(tmp_path / "nowhere") == [f"{tmp_path / 'nowhere'}: no such directory"]
    (tmp_path / "a_file").write_text("")
    assert verify_dataset(tmp_path / "a_file") == [f"{tmp_path / 'a_file'}: not a directory"]

    def damaged(name: str, edit) -> list[str]:
        copy = tmp_path / name
        shutil.copytree(reference, copy)
        edit(copy)
        return verify_dataset(copy)

    def one_more(count):
        def edit(root):
            manifest = json.loads((root / layout.MANIFEST).read_text())
            manifest["counts"][count] += 1
            (root / layout.MANIFEST).write_text(json.dumps(manifest))
        return edit

    transitions = json.loads((reference / layout.MANIFEST).read_text())["counts"]["transitions"]
    assert damaged("counts", one_more("transitions")) == [
        f"manifest: transitions total {transitions + 1} but the shards add up to {transitions}"]
    assert damaged("objects", one_more("objects")) == ["manifest: 4 objects but 3 shards"]
    unreadable = damaged("unreadable", lambda root: (root / layout.MANIFEST).write_text("{"))
    assert len(unreadable) == 1 and "manifest" in unreadable[0]

    def flip_a_byte(root):
        data = bytearray((root / layout.POSES_FILE).read_bytes())
        data[len(data) // 2] ^= 0xFF
        (root / layout.POSES_FILE).write_bytes(bytes(data))

    flipped = damaged("poses", flip_a_byte)
    assert len(flipped) == 1 and flipped[0].startswith(f"{layout.POSES_FILE}: sha256 ")

    def recount(root):
        record_path = root / layout.completion_record(OBJECTS[0])
        record = json.loads(record_path.read_text())
        record["counts"]["transitions"] += 1
        record_path.write_text(json.dumps(record))

    assert damaged("record", recount) == [f"{layout.completion_record(OBJECTS[0])}: differs from the manifest's entry for {OBJECTS[0]}"]


def test_one_worker_gives_the_same_dataset_as_two(reference, corpus, tmp_path):
    assert build(corpus, tmp_path / "one", "--workers", "1") == 0
    assert_same_dataset(reference, tmp_path / "one")


def test_dask_backend_gives_the_same_dataset_as_loky(reference, corpus, tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        assert build(corpus, tmp_path / "dask", "--scheduler", cluster.scheduler_address) == 0
        address = cluster.scheduler_address
    run = read_manifest(tmp_path / "dask").run
    assert (run["backend"], run["scheduler"], run["workers"]) == ("dask", address, None), "the cluster decides the workers"
    assert_same_dataset(reference, tmp_path / "dask")


def test_dask_workers_on_another_blas_kernel_are_named_in_a_warning(capsys, monkeypatch):
    # A dask worker loads numpy before any task imports pipeline, so its kernel is whatever the
    # environment it started in says (LocalCluster's env= comes too late); the parent says so
    # before it submits anything.
    from distributed import LocalCluster

    from pipeline.build.fanout import backend
    from pipeline.numerics import blas_kernel

    own = blas_kernel()["kernel"]
    other = "Sandybridge" if own != "Sandybridge" else "Nehalem"
    with monkeypatch.context() as started_in:
        started_in.setenv("OPENBLAS_CORETYPE", other)  # the workers' environment at their start
        cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None)
    with cluster, backend(scheduler=cluster.scheduler_address):
        pass
    err = capsys.readouterr().err
    assert f"warning: 1 of 1 dask workers compute with BLAS kernel {other}, this process with {own}" in err
    assert f"start them with OPENBLAS_CORETYPE={own}" in err
    with (LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
          backend(scheduler=cluster.scheduler_address)):
        pass
    assert "warning" not in capsys.readouterr().err, "workers in this process compute as it does"


def test_the_progress_bar_counts_objects_poses_and_failures(capsys):
    bar = fanout.Progress(total=5, already_done=2)
    bar.object_done(3)
    bar.object_done(0, failed=True)
    bar.object_done(4)
    assert (bar.poses, bar.new_poses, bar.failures) == (7, 7, 1)
    assert (bar.bar.n, bar.bar.total) == (5, 5), "the objects already done count from the start"
    poses, failed, rate = re.fullmatch(r"poses=(\d+), failed=(\d+), (\d+\.\d\d) poses/s", bar.bar.postfix).groups()
    assert (poses, failed) == ("7", "1")
    # 7 poses over the time since the bar started, rounded to two decimals: at least 7 over the time until now.
    assert float(rate) >= 7 / (time.perf_counter() - bar.started) - 0.005
    bar.close()
    err = capsys.readouterr().err
    assert "objects: 100%" in err and "5/5" in err and "poses=7, failed=1" in err
    assert re.search(r"obj/s|s/obj", err), "objects, not tqdm's 'it'"
    quiet = fanout.Progress(total=2, enabled=False)
    quiet.object_done(3)
    quiet.close()
    assert quiet.poses == 3 and capsys.readouterr().err == "", "--no-progress: nothing on stderr"
    # The fan-out draws no bar of its own unless asked (the dataset's bar is this one).
    assert sorted(fanout.map_unordered(abs, [(-1,), (2,)], workers=1)) == [1, 2]
    assert capsys.readouterr().err == ""


def test_a_scheduler_is_reached_through_one_default_client_closed_after_the_run(monkeypatch, capsys):
    # The dask tests above run a real cluster; this one sees what backend() does with the client and
    # how it refuses, with a stand-in client and joblib configuration (the dask backend finds the
    # client as distributed's default one, hence set_as_default).
    import contextlib

    import distributed
    import joblib

    events = []

    class Client:
        def __init__(self, address, timeout, set_as_default):
            events.append(("connect", address, timeout, set_as_default))

        def run(self, function):
            events.append(("run", function))
            return {"tcp://w1": {"kernel": "Other"}}

        def close(self):
            events.append("close")

    @contextlib.contextmanager
    def parallel_config(backend):
        events.append(("backend", backend))
        yield

    monkeypatch.setattr(distributed, "Client", Client)
    monkeypatch.setattr(joblib, "parallel_config", parallel_config)
    with pytest.raises(RuntimeError, match="^inside$"), fanout.backend(workers=3, scheduler="tcp://host:8786") as n_jobs:
        assert n_jobs == -1, "the cluster decides"
        raise RuntimeError("inside")
    assert events == [("connect", "tcp://host:8786", f"{fanout.CONNECT_TIMEOUT_S}s", True), ("run", fanout.blas_kernel), ("backend", "dask"), "close"]
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("warning: 1 of 1 dask workers compute with BLAS kernel Other, this process with ")

    for error in (OSError("refused"), TimeoutError("no answer"), ValueError("not an address")):
        def refuse(*args, error=error, **kwargs):
            raise error

        monkeypatch.setattr(distributed, "Client", refuse)
        with pytest.raises(SchedulerError) as refused, fanout.backend(scheduler="tcp://host:8786"):
            pass
        assert str(refused.value) == f"cannot connect to the dask scheduler at tcp://host:8786: {error}"
    monkeypatch.setitem(sys.modules, "distributed", None)  # not installed: the import raises ImportError
    with pytest.raises(SchedulerError) as refused, fanout.backend(scheduler="tcp://host:8786"):
        pass
    assert str(refused.value) == "--scheduler needs dask.distributed (pip install 'dask[distributed]')"

    with fanout.backend(workers=3) as n_jobs:
        assert n_jobs == 3
    with fanout.backend() as n_jobs:
        assert n_jobs == fanout.default_workers() == max(1, joblib.cpu_count())
    monkeypatch.setattr(joblib, "cpu_count", lambda: 1)
    assert fanout.default_workers() == 1, "one core: one worker"


def test_the_kernel_warning_counts_the_workers_on_other_kernels_and_names_each_kernel_once():
    # The dask test above has one worker; here several, two of them on one other kernel and one
    # that could not say (None, as blas_kernel gives when threadpoolctl cannot read the library).
    workers = {
        "tcp://w1": {"kernel": "Haswell", "library": "openblas"},
        "tcp://w2": {"kernel": "Sandybridge"},
        "tcp://w3": {"kernel": "Sandybridge"},
        "tcp://w4": {"kernel": "Nehalem"},
        "tcp://w5": {"kernel": None},
    }
    assert fanout.kernel_mismatch("Haswell", workers) == (
        "4 of 5 dask workers compute with BLAS kernel Nehalem, None, Sandybridge, this process with Haswell, "
        "so their shards may differ in the last bits from a local build's; start them with OPENBLAS_CORETYPE=Haswell "
        '(docs/DATASET.md, "Reproducible across machines")'
    )
    assert fanout.kernel_mismatch("Haswell", {"tcp://w1": {"kernel": "Haswell"}, "tcp://w2": {"kernel": "Haswell"}}) is None
    assert fanout.kernel_mismatch(None, {"tcp://w1": {"kernel": None}}) is None, "no kernel known on either side: no warning"
    assert fanout.kernel_mismatch("Haswell", {}) is None, "no workers, nothing to warn about"
    assert fanout.kernel_mismatch("Haswell", {"tcp://w1": {}}).startswith("1 of 1 dask workers compute with BLAS kernel None,")


KILLABLE = (
    "import sys, time, pipeline.model.evaluation as objects\n"
    "compute, seen = objects.process_object, []\n"
    "stop = sys.argv.pop(1)\n"
    "def process_object(spec, config):\n"
    "    seen.append(spec.object_id)\n"
    "    if stop == 'compute' and len(seen) > 1: time.sleep(30)\n"
    "    return compute(spec, config)\n"
    "objects.process_object = process_object\n"
    "from pipeline.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)
"""Runs the CLI in one in-process worker; objects after the first pause before computing
(same results; an object takes ~50 ms, too short a window to kill in on a busy machine)."""


def run_killed(stop: str, corpus: Path, out: Path, *extra: str) -> str:
    """Run a build that is SIGKILLed once a shard is staged (``stop="compute"``).  Returns its stderr."""
    staged = staging_dir(out) / layout.SHARDS_DIR
    command = ["dataset", "--corpus", str(corpus), "--out", str(out), *PARAMS, "--workers", "1", *extra]
    process = subprocess.Popen(
        [sys.executable, "-c", KILLABLE, stop, *command],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )
    deadline = time.monotonic() + 120
    if stop == "compute":
        while not list(staged.glob("*/complete.json")) and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=120)
    assert process.returncode == -signal.SIGKILL, process.stderr.read().decode()[-500:]
    stderr = process.stderr.read().decode()
    process.stderr.close()
    return stderr


def test_sigkill_part_way_then_resume_gives_the_same_dataset(reference, corpus, tmp_path):
    out = tmp_path / "killed"
    command = [sys.executable, "-m", "pipeline", "dataset", "--corpus", str(corpus), "--out", str(out), *PARAMS]
    records = staging_dir(out) / layout.SHARDS_DIR
    stderr = run_killed("compute", corpus, out)

    finished = {p.parent.name: p.stat().st_mtime_ns for p in records.glob("*/complete.json")}
    assert 1 <= len(finished) < len(OBJECTS), f"not killed part-way: {sorted(finished)} {stderr[-500:]}"
    assert not (out / "manifest.json").exists()
    assert verify_dataset(out) != []

    resumed = subprocess.run([*command, "--workers", "2"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    # They wait in the staging directory, beside --out (which holds nothing yet): the message names it.
    assert f"resuming: {len(finished)} of {len(OBJECTS)} objects already complete in {staging_dir(out)}\n" in resumed.stderr
    manifest = read_manifest(out)
    assert manifest.run["reused"] == len(finished)
    assert manifest.run["computed"] == len(OBJECTS) - len(finished)
    for object_id, mtime in finished.items():
        record = out / layout.completion_record(object_id)
        assert record.stat().st_mtime_ns == mtime, f"{object_id} was recomputed"
    assert not list(out.rglob("*.tmp")) and not staging_dir(out).exists()
    assert verify_dataset(out) == []
    assert_same_dataset(reference, out)


def test_sigkill_while_extending_a_finished_dataset_keeps_it_until_the_commit(reference, tmp_path, monkeypatch, capsys):
    """Killed while computing new objects: the old dataset is untouched.  Stopped inside
    the commit (here by an exception at its third rename: the files on disk are what a
    kill leaves): the next run finishes that commit before anything else."""
    small = write_corpus(tmp_path, OBJECTS[:1])
    out = tmp_path / "dataset"
    assert build(small, out, "--workers", "1") == 0
    before = snapshot(out)

    grown = write_corpus(tmp_path, OBJECTS)
    run_killed("compute", grown, out)
    assert_intact(out, before)
    assert len(list((staging_dir(out) / layout.SHARDS_DIR).glob("*/complete.json"))) == 1

    move, moved = dataset._move, []

    def crash_after_first_partition(source, target):
        if moved and "actions" in moved[-1].parts:
            raise SystemExit("killed")
        moved.append(target)
        move(source, target)

    monkeypatch.setattr(dataset, "_move", crash_after_first_partition)
    capsys.readouterr()
    with pytest.raises(SystemExit):
        build(grown, out, "--workers", "1")
    monkeypatch.setattr(dataset, "_move", move)
    assert f"resuming: 2 of 3 objects already complete (1 in {out}, 1 in {staging_dir(out)})\n" in capsys.readouterr().err
    assert (staging_dir(out) / "commit.json").exists(), "stopped after the commit point"
    assert verify_dataset(out) != [], "half-way through the renames"

    capsys.readouterr()
    assert build(grown, out, "--workers", "1") == 0
    err = capsys.readouterr().err
    assert "finished the commit of an interrupted run" in err
    assert "up to date: all 3 objects" in err, "the rolled-forward commit is the whole build"
    assert not staging_dir(out).exists()
    assert verify_dataset(out) == []
    assert_same_dataset(reference, out)


def test_a_commit_moves_shard_files_then_removes_dropped_objects_then_records_and_the_manifest_last(
    reference, corpus, tmp_path, monkeypatch
):
    """The commit's order (module docstring): the new shards' files, then the shards the new manifest no
    longer lists removed, then the completion records, the consolidated tables, and the manifest last; so
    a kill at any step leaves no record before its files and no manifest before what it lists."""
    from schema import served

    out = tmp_path / "dataset"
    shutil.copytree(reference, out)
    move, remove, events = dataset._move, dataset._remove_object_files, []

    def logged_move(source, target):
        if source.exists():
            events.append(("move", target.relative_to(out).as_posix()))
        move(source, target)

    def logged_remove(root, object_id):
        if root == out:
            events.append(("remove", object_id))
        remove(root, object_id)

    monkeypatch.setattr(dataset, "_move", logged_move)
    monkeypatch.setattr(dataset, "_remove_object_files", logged_remove)
    assert build(corpus, out, "--limit", "1", "--force", "--workers", "1") == 0
    kept = OBJECTS[0]
    record = layout.completion_record(kept)
    consolidated = [layout.OBJECTS_FILE, layout.POSES_FILE, *served.FILES.values()]
    files = [e for e in events if e[0] == "move" and e[1] not in (record, *consolidated, layout.MANIFEST)]
    assert files and all(kept in relative for _, relative in files), events
    assert set(read_manifest(out).shards[kept].files) == {relative for _, relative in files}
    removed = sorted(object_id for kind, object_id in events if kind == "remove")
    assert removed == sorted(OBJECTS[1:])
    tail = events[len(files) + len(removed):]
    assert events[:len(files)] == files and tail[0] == ("move", record), events
    assert sorted(tail[1:-1]) == sorted(("move", name) for name in consolidated) and tail[-1] == ("move", layout.MANIFEST)
    assert verify_dataset(out) == []


def test_interrupted_shard_write_leaves_an_incomplete_shard(tmp_path, monkeypatch, corpus):
    spec = read_list(corpus, default_mass=0.25).specs[0]
    config = Config().with_overrides({"contacts.n_contacts": 10, "topple.n_trials": 2, "suction.n_candidates": 5})
    shard = compute_shard(spec, config)
    assert isinstance(shard, rows.ShardData), shard
    inputs = shards.shard_inputs(spec, config)
    key = shards.fingerprint(inputs)

    record = shards.write_shard(tmp_path, shard, inputs)
    assert shards.is_complete(tmp_path, spec.object_id, key) == record
    assert shards.is_complete(tmp_path, spec.object_id, "other parameters") is None

    def disk_full(path, shard):
        Path(path).write_bytes(b"partial")
        raise OSError("No space left on device")

    monkeypatch.setattr(shards, "_write_hdf5", disk_full)
    with pytest.raises(OSError, match="No space"):
        shards.write_shard(tmp_path, shard, inputs)
    assert shards.read_record(tmp_path, spec.object_id) is None, "the old record goes first"
    assert shards.is_complete(tmp_path, spec.object_id, key) is None
    assert not list(tmp_path.rglob("*.tmp")), "the temporary file is removed"
    assert (tmp_path / layout.arrays_file(spec.object_id)).read_bytes() != b"partial"


def test_broken_mesh_is_a_failure_and_strict_makes_it_fatal(tmp_path, capsys):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n")
    (meshes / "garbage.obj").write_text("this is not a mesh\n")
    (meshes / "photo.png").write_bytes(b"\x89PNG\r\n")
    (meshes / "junk.ply").write_text("junk\n")
    corpus = write_corpus(
        tmp_path, OBJECTS[:1], "flat,,meshes/flat.obj,1,0.1\ngarbage,,meshes/garbage.obj,1,0.1\ngone,,meshes/gone.obj,1,0.1\n"
        "photo,,meshes/photo.png,1,0.1\njunk,,meshes/junk.ply,1,0.1\n"
    )
    out = tmp_path / "dataset"
    assert build(corpus, out, "--workers", "2") == 0
    manifest = read_manifest(out)
    assert manifest.counts.objects == 1 and manifest.counts.failed == 5
    failures = {f.object_id: f for f in manifest.failures}
    assert set(failures) == {"flat", "garbage", "gone", "photo", "junk"}
    assert failures["gone"].kind == "corpus" and "not found" in failures["gone"].reason
    for object_id in ("flat", "garbage", "photo", "junk"):
        assert failures[object_id].kind == "mesh", failures[object_id]
        assert failures[object_id].reason.startswith(f"{object_id}: ")
    assert failures["photo"].reason == (
        "photo: cannot read photo.png: '.png' is not a mesh format toppledb reads; convert it to OBJ, STL or PLY"
    )
    assert "not a valid PLY file" in failures["junk"].reason and "Not a ply file" not in failures["junk"].reason
    summary = capsys.readouterr().out
    assert "failed    flat:" in summary
    assert verify_dataset(out) == []
    assert pq.read_metadata(out / "objects.parquet").num_rows == 1

    strict = write_corpus(tmp_path, [], "flat,,meshes/flat.obj,1,0.1\n")
    assert build(strict, tmp_path / "new" / "strict", "--strict", "--workers", "1") == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --strict: flat: ") and err.count("\n") == 1
    assert not (tmp_path / "new" / "strict").exists(), "a fresh --out the failed run made is not left behind empty"
    # Nor its parent, made by the run too: the staging directory beside --out held nothing to resume from.
    assert not (tmp_path / "new").exists()

    # A corpus problem (a missing file) stops a strict run before anything is computed, in the corpus's words.
    gone = write_corpus(tmp_path, OBJECTS[:1], "gone,,meshes/gone.obj,1,0.1\n")
    assert build(gone, tmp_path / "new" / "gone", "--strict", "--workers", "1") == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --strict: gone: ") and err.endswith(f"{failures['gone'].reason}\n") and err.count("\n") == 1
    assert not (tmp_path / "new").exists()


def test_a_strict_run_keeps_the_shards_it_finished_for_the_next_run(tmp_path, capsys):
    """--strict stops at a failed object, but the objects it finished before stay staged (a rerun
    reuses them); only a staging directory with nothing to resume is removed."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n")
    # Largest mesh first (``_compute``): with one worker random_000 is finished before flat fails.
    corpus = write_corpus(tmp_path, OBJECTS[:1], "flat,,meshes/flat.obj,1,0.1\n")
    out = tmp_path / "strict"
    assert build(corpus, out, "--strict", "--workers", "1") == 1
    staged = staging_dir(out) / layout.SHARDS_DIR
    assert [p.parent.name for p in staged.glob("*/complete.json")] == [OBJECTS[0]]
    capsys.readouterr()
    assert build(corpus, out, "--workers", "1") == 0
    assert f"resuming: 1 of 2 objects already complete in {staging_dir(out)}" in capsys.readouterr().err
    run = read_manifest(out).run  # flat is tried again (and fails); random_000 is not recomputed
    assert (run["computed"], run["reused"]) == (1, 1) and not staging_dir(out).exists()


def test_other_parameters_are_refused_and_force_rebuilds(reference, corpus, tmp_path, capsys):
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    # Not a failed build but a path the user must change (--force or another --out): exit 2.
    assert build(corpus, copy, "--trials", "6") == 2
    err = capsys.readouterr().err
    assert "3 shard(s) built from other inputs (config.topple.n_trials: 5 -> 6). To replace it, add --force" in err
    assert f"choose another --out, e.g. --out {copy}-2" in err and err.count("\n") == 1
    assert build(corpus, copy, "--limit", "2") == 2
    assert f"1 shard(s) of objects not in this corpus (e.g. {OBJECTS[2]})" in capsys.readouterr().err
    assert verify_dataset(copy) == [], "a refused run changes nothing"

    assert build(corpus, copy, "--limit", "1", "--force", "--workers", "1") == 0
    manifest = read_manifest(copy)
    assert manifest.counts.objects == 1 and manifest.run["computed"] == 1
    assert sorted(p.name for p in (copy / "actions").iterdir()) == [f"object_id={OBJECTS[0]}"]
    assert verify_dataset(copy) == []
    assert json.loads((copy / "manifest.json").read_text())["corpus"]["objects"][0]["object_id"] == OBJECTS[0]


def test_the_after_failure_power_is_part_of_a_shard_only_when_value_iteration_plans_with_it(reference, corpus):
    # mdp.after_failure_power (schema.retry's map) is what value iteration plans with when it
    # believes failures (the default, MODEL.md (12.13)), so a new value is a new shard; a build that
    # does not believe them never reads it, and then a new value asks for no rebuild.
    config = Config.from_dict(read_manifest(reference).parameters.model_dump())
    assert config.mdp.believe_failures
    spec = next(iter(read_list(corpus, 0.25).specs))
    other_power = config.with_overrides({"mdp.after_failure_power": 3.0})
    assert shards.fingerprint(shards.shard_inputs(spec, other_power)) != shards.fingerprint(shards.shard_inputs(spec, config))
    thesis = config.with_overrides({"mdp.believe_failures": False})
    assert shards.shard_inputs(spec, thesis) == shards.shard_inputs(spec, thesis.with_overrides({"mdp.after_failure_power": 3.0}))
    assert shards.shard_inputs(spec, thesis) != shards.shard_inputs(spec, config)
    # A build that does not plan with them keeps the identity it had before either existed, so a
    # dataset built then can still be added to; k = 1 believes nothing either.
    assert set(shards.shard_inputs(spec, thesis)["config"]["mdp"]).isdisjoint({"after_failure_power", "believe_failures"})
    no_map = config.with_overrides({"mdp.after_failure_power": 1.0})
    assert shards.shard_inputs(spec, no_map) == shards.shard_inputs(spec, thesis.with_overrides({"mdp.after_failure_power": 1.0}))
    other = config.with_overrides({"mdp.gamma": 0.9})
    assert shards.fingerprint(shards.shard_inputs(spec, other)) != shards.fingerprint(shards.shard_inputs(spec, config))


def test_add_computes_only_the_new_object_and_commits_atomically(reference, tmp_path, capsys):
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    before = snapshot(copy)
    mesh = Path(read_list(write_corpus(tmp_path, ["random_003"]), 0.25).specs[0].path)

    assert main(["add", str(copy), str(mesh), "--id", "random_000"]) == 2, "an id already in the dataset"
    assert capsys.readouterr().err == f"error: {copy} already has an object 'random_000'; choose another --id\n"
    assert main(["add", str(copy), str(mesh), "--id", "Random_000"]) == 2, "the same files on macOS or Windows"
    assert "already has an object 'random_000'; choose another --id (ids that differ only in case" in capsys.readouterr().err
    # A mesh toppledb cannot use is bad input (2), as in ``figures``, in toppledb's words, not trimesh's.
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nf 1 2 3\n")
    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n")
    (tmp_path / "junk.ply").write_text("junk\n")
    rejected = {
        "flat.obj": "error: flat: zero volume",
        "photo.png": "error: photo: cannot read photo.png: '.png' is not a mesh format toppledb reads; "
                     "convert it to OBJ, STL or PLY",
        "junk.ply": "error: junk: cannot read junk.ply: not a valid PLY file (text without vertices and faces); "
                    "export it again as OBJ, STL or PLY",
        # The hint names the flags add has, not a corpus sidecar or list column.
        str(mesh): "too large for a tabletop: largest side",
    }
    for file, message in rejected.items():
        assert main(["add", str(copy), str(tmp_path / file), "--no-progress"]) == 2, file
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1, err
        assert "--strict" not in err and "corpus.toml" not in err and "scale column" not in err, err
    # With --density no mass can be computed from it either: the mesh's own reason, said once.
    assert main(["add", str(copy), str(tmp_path / "junk.ply"), "--density", "700", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert rejected["junk.ply"] in err and err.count("\n") == 1, err
    assert_intact(copy, before)
    # A mesh that loads but that the model rejects (a sphere has no pose worth pushing) fails inside the
    # build: still exit 2, and no empty staging directory is left beside the dataset.
    trimesh.creation.icosphere(radius=0.03).export(tmp_path / "ball.obj")
    assert main(["add", str(copy), str(tmp_path / "ball.obj"), "--no-progress"]) == 2
    assert "nearly a sphere" in capsys.readouterr().err
    assert_intact(copy, before)
    assert not staging_dir(copy).exists()

    assert main(["add", str(copy), str(mesh), "--scale", "0.015", "--mass", "0.1", "--id", "extra", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert captured.out.startswith("added     extra: ") and "(1 computed, 3 reused)" in captured.out
    assert captured.err == "", "no progress bar (--no-progress), and no 'resuming:' line for the objects it reuses"
    assert verify_dataset(copy) == []
    manifest = read_manifest(copy)
    assert list(manifest.shards) == [*OBJECTS, "extra"] and manifest.counts.objects == 4
    capsys.readouterr()
    assert build(write_corpus(tmp_path, OBJECTS), copy) == 2, "the corpus it was built from no longer describes it"
    err = capsys.readouterr().err
    assert "1 shard(s) of objects not in this corpus (e.g. extra). To replace it, add --force" in err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert {k: v for k, v in snapshot(copy).items() if k.startswith(("actions", "transitions", "arrays", "_shards"))} == {
        k: v for k, v in before.items() if k.startswith(("actions", "transitions", "arrays", "_shards"))
    } | {k: v for k, v in snapshot(copy).items() if "extra" in k}, "the other shards are untouched"

    # The added shard is what a build with the dataset's parameters computes for it.
    spec = read_list(write_corpus(tmp_path, ["random_003"]), 0.25).specs[0]
    spec = dataclasses.replace(spec, object_id="extra")
    expected = compute_shard(spec, Config.from_dict(manifest.parameters.model_dump()))
    stored = pq.read_table(copy / layout.partition_file("actions", "extra"))
    assert stored.equals(expected.rows["actions"])


def test_add_says_why_a_dataset_cannot_be_extended_and_changes_nothing(reference, tmp_path, capsys):
    """``add`` refuses what it cannot extend consistently, each in one line: no dataset, parameters this
    code does not know, shards of other inputs (the first three differences, or the schema when the
    record keeps none); a mesh is named by the id it is added under; a begun commit is finished first."""
    from pipeline.model.topple import ENGINE_REVISION
    from schema.version import SCHEMA_VERSION

    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    mesh = Path(read_list(write_corpus(tmp_path, ["random_003"]), 0.25).specs[0].path)
    add = ["--scale", "0.015", "--mass", "0.1", "--no-progress"]

    nowhere = tmp_path / "nowhere"
    assert main(["add", str(nowhere), str(mesh), *add]) == 2
    assert capsys.readouterr().err == f"error: cannot add to {nowhere}: {nowhere}: no such dataset directory\n"

    manifest_bytes = (copy / layout.MANIFEST).read_bytes()
    data = json.loads(manifest_bytes)
    data["parameters"]["topple"]["nope"] = 1  # the manifest's model keeps it; this code's Config does not
    (copy / layout.MANIFEST).write_text(json.dumps(data))
    assert main(["add", str(copy), str(mesh), *add]) == 1
    assert capsys.readouterr().err == (
        f"error: {copy}: its parameters do not fit this code (unknown config key(s): topple.nope); rebuild it\n"
    )
    (copy / layout.MANIFEST).write_bytes(manifest_bytes)

    record_path = copy / layout.completion_record(OBJECTS[0])  # the first shard is the one compared
    record_bytes = record_path.read_bytes()
    record = json.loads(record_bytes)
    inputs = record["inputs"]
    assert (inputs["config"]["contacts"]["n_contacts"], inputs["config"]["topple"]["n_trials"]) == (30, 5)
    inputs["config"]["contacts"]["n_contacts"] = 40
    inputs["config"]["topple"]["n_trials"] = 7
    inputs["engine_revision"] = -1
    inputs["schema_version"] = "0.0"  # a fourth difference, not shown
    record["fingerprint"] = shards.fingerprint(inputs)
    record_path.write_text(json.dumps(record))
    rebuild = "`add` needs the code that built it: rebuild the dataset with this code (toppledb dataset --force) first\n"
    assert main(["add", str(copy), str(mesh), *add]) == 1
    assert capsys.readouterr().err == (
        f"error: {copy} was built with parameters this code no longer gives it (config.contacts.n_contacts: 40 -> 30; "
        f"config.topple.n_trials: 7 -> 5; engine_revision: -1 -> {ENGINE_REVISION}); " + rebuild
    )
    assert SCHEMA_VERSION != "0.0"
    record = json.loads(record_bytes)
    record["fingerprint"] = "0" * 64  # the same inputs, fingerprinted otherwise (another schema's hashing)
    record_path.write_text(json.dumps(record))
    assert main(["add", str(copy), str(mesh), *add]) == 1
    assert capsys.readouterr().err == f"error: {copy} was built with parameters this code no longer gives it (schema); " + rebuild
    record_path.write_bytes(record_bytes)
    assert verify_dataset(copy) == [] and not staging_dir(copy).exists(), "a refused add writes nothing"

    # A mesh that cannot be used is named by the id the user gave it, not by its file's name.
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nf 1 2 3\n")
    assert main(["add", str(copy), str(tmp_path / "flat.obj"), "--id", "slab", "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith("error: slab: zero volume")

    # A commit a killed run began (here one with nothing left to move) is finished before the object is added.
    staging_dir(copy).mkdir()
    (staging_dir(copy) / "commit.json").write_text(json.dumps({"moves": [], "keep": OBJECTS}))
    assert main(["add", str(copy), str(mesh), *add, "--id", "extra"]) == 0
    assert capsys.readouterr().err.startswith(f"finished the commit of an interrupted run in {copy}\n")
    assert list(read_manifest(copy).shards) == [*OBJECTS, "extra"] and not staging_dir(copy).exists()


def test_add_keeps_the_builds_failures_and_a_crash_is_a_failed_build(tmp_path, capsys, monkeypatch):
    """The objects that failed before stay failures, as they were, and are not tried again; the new
    object crashing (not a mesh the model rejects) is a failed build, exit 1, and changes nothing."""
    from pipeline.model import evaluation

    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n")
    corpus = write_corpus(tmp_path, OBJECTS[:1], "flat,,meshes/flat.obj,1,0.1\ngone,,meshes/gone.obj,1,0.1\n")
    out = tmp_path / "dataset"
    assert build(corpus, out, "--workers", "1") == 0
    failures = [f.model_dump() for f in read_manifest(out).failures]
    assert [(f["object_id"], f["kind"]) for f in failures] == [("flat", "mesh"), ("gone", "corpus")]
    mesh = read_list(write_corpus(tmp_path, ["random_002"]), 0.25).specs[0].path
    add = ["add", str(out), mesh, "--scale", "0.015", "--mass", "0.1", "--id", "extra", "--no-progress"]

    def crash(spec, config):
        raise RuntimeError("boom")

    monkeypatch.setattr(evaluation, "process_object", crash)
    capsys.readouterr()
    assert main(add) == 1
    assert capsys.readouterr().err == "error: extra: RuntimeError: boom\n"
    monkeypatch.undo()
    assert list(read_manifest(out).shards) == [OBJECTS[0]] and not staging_dir(out).exists()

    assert main(add) == 0
    manifest = read_manifest(out)
    assert list(manifest.shards) == [OBJECTS[0], "extra"] and manifest.run["computed"] == 1
    assert [f.model_dump() for f in manifest.failures] == failures
    assert verify_dataset(out) == []


def test_a_damaged_completion_record_is_redone_not_blamed_on_other_inputs(reference, corpus, tmp_path, capsys):
    """A record that reads as JSON but holds no fingerprint is a shard without a record: the same
    command redoes it (the others reused) instead of asking for --force over 'other inputs'."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    (copy / layout.completion_record(OBJECTS[1])).write_text("{}")
    assert build(corpus, copy, "--workers", "1") == 0, capsys.readouterr().err
    manifest = read_manifest(copy)
    assert (manifest.run["computed"], manifest.run["reused"]) == (1, len(OBJECTS) - 1)
    assert verify_dataset(copy) == []
    assert_same_dataset(reference, copy)
    assert build(corpus, copy, "--workers", "1") == 0
    out = capsys.readouterr().out  # up to date: the cpu line says whose time it is
    assert "objects   3 (0 computed, 3 reused)" in out and "(when the shards were computed; none was this run)" in out
    wall = [line for line in out.splitlines() if line.startswith("wall ")][-1]
    assert 0 <= float(wall.split()[1]) < 60, "this run's own wall time, from its start"


def test_a_killed_force_run_resumes_when_run_again_and_a_new_one_starts_over(reference, corpus, tmp_path, capsys):
    """--force recomputes every shard; killed part-way, the same command run again by the same code
    keeps what it had staged.  Staged shards of other code (another forced.json) are recomputed."""
    from pipeline.build.dataset import FORCED_RUN

    out = tmp_path / "dataset"
    shutil.copytree(reference, out)
    run_killed("compute", corpus, out, "--force")
    staged = sorted(p.parent.name for p in (staging_dir(out) / layout.SHARDS_DIR).glob("*/complete.json"))
    assert 1 <= len(staged) < len(OBJECTS) and (staging_dir(out) / FORCED_RUN).is_file()
    assert build(corpus, out, "--force", "--workers", "1") == 0
    assert f"resuming: {len(staged)} of {len(OBJECTS)} objects already complete in {staging_dir(out)}\n" in capsys.readouterr().err
    assert (read_manifest(out).run["computed"], read_manifest(out).run["reused"]) == (len(OBJECTS) - len(staged), len(staged))
    assert_same_dataset(reference, out)

    run_killed("compute", corpus, out, "--force")
    (staging_dir(out) / FORCED_RUN).write_text('{"code_version": "another"}')
    assert build(corpus, out, "--force", "--workers", "1") == 0
    assert read_manifest(out).run["computed"] == len(OBJECTS), "another code's staged shards are not reused"
    assert_same_dataset(reference, out)


def test_only_a_force_run_of_the_same_code_resumes_a_stopped_force_run(reference, corpus, tmp_path, monkeypatch, capsys):
    """In process (one worker, where mutmut sees it): a --force run stopped after its first object resumes
    from its staged shard when run again; one whose staging names other code, or a stopped run without
    --force, is recomputed whole by --force."""
    from pipeline.build.dataset import FORCED_RUN
    from pipeline.model import evaluation

    real, seen = evaluation.process_object, []

    def stopped_after_one(spec, config):
        seen.append(spec.object_id)
        if len(seen) > 1:
            raise KeyboardInterrupt  # as Ctrl-C part-way: the finished shard stays staged
        return real(spec, config)

    def stop_after_one(*extra) -> list[str]:
        seen.clear()
        monkeypatch.setattr(evaluation, "process_object", stopped_after_one)
        assert build(corpus, out, "--workers", "1", *extra) == 130
        monkeypatch.setattr(evaluation, "process_object", real)
        return sorted(p.parent.name for p in (staging_dir(out) / layout.SHARDS_DIR).glob("*/complete.json"))

    out = tmp_path / "dataset"
    shutil.copytree(reference, out)
    assert len(stop_after_one("--force")) == 1 and (staging_dir(out) / FORCED_RUN).is_file()
    capsys.readouterr()
    assert build(corpus, out, "--force", "--workers", "1") == 0
    assert f"resuming: 1 of {len(OBJECTS)} objects already complete in {staging_dir(out)}\n" in capsys.readouterr().err
    assert (read_manifest(out).run["computed"], read_manifest(out).run["reused"]) == (len(OBJECTS) - 1, 1)
    assert_same_dataset(reference, out)

    assert len(stop_after_one("--force")) == 1
    (staging_dir(out) / FORCED_RUN).write_text('{"code_version": "another"}')
    assert build(corpus, out, "--force", "--workers", "1") == 0
    assert (read_manifest(out).run["computed"], read_manifest(out).run["reused"]) == (len(OBJECTS), 0)

    for object_id in OBJECTS[1:]:  # a plain run then has two objects to compute, and stops after one
        (out / layout.completion_record(object_id)).write_text("{}")
    assert len(stop_after_one()) == 1 and not (staging_dir(out) / FORCED_RUN).exists()
    assert build(corpus, out, "--force", "--workers", "1") == 0
    assert (read_manifest(out).run["computed"], read_manifest(out).run["reused"]) == (len(OBJECTS), 0)
    assert_same_dataset(reference, out)


def test_a_given_process_computes_each_object_and_its_errors_are_failures_with_their_traceback(corpus, tmp_path):
    """``build_dataset``'s ``process`` is what computes an object (here the real one, but for one object
    it raises): an unexpected error is that object's failure, kind ``error``, with the last lines of its
    traceback; the others are built."""
    from pipeline.build.dataset import build_dataset
    from pipeline.model.evaluation import process_object

    calls, raised = [], []

    def process(spec, config):
        calls.append(spec.object_id)
        if spec.object_id == OBJECTS[1]:
            raised.append(ValueError("no  such\n  luck"))
            raise raised[-1]
        return process_object(spec, config)

    config = Config().with_overrides({"contacts.n_contacts": 10, "topple.n_trials": 2, "suction.n_candidates": 5})
    out = tmp_path / "dataset"
    summary = build_dataset(read_list(corpus, 0.25), config, out, workers=1, progress=False, process=process, log=lambda _: None)
    assert sorted(calls) == sorted(OBJECTS) and summary.committed and summary.computed == len(OBJECTS)
    manifest = read_manifest(out)
    assert list(manifest.shards) == [OBJECTS[0], OBJECTS[2]]
    assert manifest.timings.wall_s == round(summary.wall_s, 3), "the run's wall time, in ms"
    [failure] = manifest.failures
    assert (failure.object_id, failure.kind, failure.reason) == (OBJECTS[1], "error", "ValueError: no such luck")
    assert "in process" in failure.detail and failure.detail.rstrip().endswith("ValueError: no  such\n  luck")
    # The traceback's last lines as Python prints them (one worker computes in this process: the same error).
    printed = "".join(traceback.format_exception(raised[0]))
    assert printed.endswith(failure.detail) and failure.detail.startswith(("Traceback", "  File "))
    assert verify_dataset(out) == [] and not staging_dir(out).exists()


def test_a_staging_path_that_is_not_a_directory_is_the_users_to_change(reference, corpus, tmp_path, capsys):
    """A file where the staging directory goes (``.<name>.staging`` beside --out): exit 2 in one line, before
    any computing, and the dataset and the file stay as they were."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    (copy / layout.completion_record(OBJECTS[1])).write_text("{}")  # one object to compute again
    before = snapshot(copy)
    staging_dir(copy).write_text("not a directory")
    assert build(corpus, copy, "--workers", "1") == 2
    assert capsys.readouterr().err == (f"resuming: 2 of 3 objects already complete in {copy}\n"
                                       f"error: cannot create staging directory {staging_dir(copy)}: File exists\n")
    assert snapshot(copy) == before and staging_dir(copy).read_text() == "not a directory"


def test_input_differences_name_every_changed_added_and_removed_key():
    long = [0.125] * 30
    exactly_40 = "x" * 38  # its repr, quotes included, is 40 characters: shown whole
    old = {"topple": {"n_trials": 100, "variant": "robust"}, "seed": 0, "gone": 1, "map": {"a": 1}, "note": "a"}
    new = {"topple": {"n_trials": 50, "variant": "robust"}, "seed": 0, "added": long, "map": 3, "note": exactly_40}
    assert shards.input_differences(old, new) == [
        f"added: None -> {repr(long)[:37]}...",  # longer values are cut to 40 characters
        "gone: 1 -> None",
        "map: {'a': 1} -> 3",
        f"note: 'a' -> {exactly_40!r}",
        "topple.n_trials: 100 -> 50",
    ]
    assert shards.input_differences(new, new) == []


def test_add_checks_the_mesh_against_the_datasets_own_mesh_limits(tmp_path, capsys):
    """A dataset built with other mesh limits is extended under them, not under the defaults: built to take
    objects up to 0.7 m, it takes a 0.62 m one (the default limit is 0.5 m) and refuses a 0.74 m one, naming
    its own limit, before any work."""
    out = tmp_path / "dataset"
    assert build(write_corpus(tmp_path, ["random_000"]), out, "--set", "mesh.max_extent=0.7") == 0  # 0.12 m
    mesh = Path(read_list(write_corpus(tmp_path, ["random_003"]), 0.25).specs[0].path)  # 6.18 m as the file has it
    add = [str(out), str(mesh), "--mass", "0.1", "--no-progress"]
    before = snapshot(out)
    assert main(["add", *add, "--scale", "0.12", "--id", "large"]) == 2
    err = capsys.readouterr().err
    assert "large: too large for a tabletop: largest side 0.7413 m > 0.7 m" in err and err.count("\n") == 1, err
    assert_intact(out, before)
    assert main(["add", *add, "--scale", "0.1", "--id", "wide"]) == 0
    assert list(read_manifest(out).shards) == ["random_000", "wide"] and verify_dataset(out) == []


def test_the_summary_names_what_loading_repaired_beyond_merged_vertices(tmp_path, capsys):
    """A box missing a face is closed before it is computed, and the run's summary says so on one line;
    merging an STL-style triangle soup's duplicate vertices is routine and kept to objects.parquet."""
    box = trimesh.creation.box([0.05, 0.06, 0.07])
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    trimesh.Trimesh(box.vertices, box.faces[1:], process=False).export(meshes / "holed.obj")
    trimesh.Trimesh(box.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False).export(meshes / "soup.stl")
    out = tmp_path / "dataset"
    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), *PARAMS]) == 0
    repaired = [line for line in capsys.readouterr().out.splitlines() if line.startswith("repaired")]
    assert repaired == ["repaired  holed: filled holes"]
    objects = pq.read_table(out / "objects.parquet").to_pylist()
    assert {o["object_id"]: o["repairs"] for o in objects} == {"holed": ["filled holes"],
                                                                "soup": ["merged 28 duplicate vertices"]}


def test_the_progress_bar_counts_every_object_and_starts_at_those_already_settled(corpus, tmp_path, monkeypatch):
    """The bar's total is every object of the corpus; it starts at the objects reused and those the corpus
    already failed, and each object computed moves it by one with its poses (0 and a failure when it failed)."""
    from pipeline.build.dataset import build_dataset
    from pipeline.model.evaluation import process_object

    bars = []

    class Bar:
        def __init__(self, total, already_done=0, enabled=True):
            self.opened, self.done, self.closed = (total, already_done, enabled), [], False
            bars.append(self)

        def object_done(self, n_poses, failed=False):
            self.done.append((n_poses, failed))

        def close(self):
            self.closed = True

    def process(spec, config):
        if spec.object_id == OBJECTS[1]:
            raise ValueError("no luck")
        return process_object(spec, config)

    config = Config().with_overrides({"contacts.n_contacts": 10, "topple.n_trials": 2, "suction.n_candidates": 5})
    out = tmp_path / "dataset"
    first = write_corpus(tmp_path, OBJECTS[:1])
    build_dataset(read_list(first, 0.25), config, out, workers=1, progress=False, log=lambda _: None)
    monkeypatch.setattr(fanout, "Progress", Bar)
    (tmp_path / "more").mkdir()
    more = write_corpus(tmp_path / "more", OBJECTS, "gone,,meshes/gone.obj,1,0.1\n")  # a missing file
    summary = build_dataset(read_list(more, 0.25), config, out, workers=1, process=process, log=lambda _: None)
    assert (summary.reused, summary.computed, summary.manifest.counts.failed) == (1, 2, 2)
    [bar] = bars
    assert bar.opened == (4, 2, True), "4 objects, 1 reused and 1 failed by the corpus before computing"
    poses = pq.read_table(out / "poses.parquet").column("object_id").to_pylist().count(OBJECTS[2])
    assert poses > 0 and sorted(bar.done) == [(0, True), (poses, False)] and bar.closed


def test_an_unfinished_shard_of_an_object_outside_the_corpus_is_deleted_not_refused(reference, corpus, tmp_path, capsys):
    """A shard with no completion record is an interrupted write: of an object outside the corpus, nothing to
    keep or to refuse the run for; it is deleted and the dataset is as the build left it."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    before = snapshot(copy)
    (copy / layout.arrays_file("gone")).write_bytes(b"partial")
    (copy / layout.shard_dir("gone")).mkdir()
    (copy / layout.shard_dir("gone") / "objects.parquet").write_bytes(b"partial")
    assert build(corpus, copy, "--workers", "1") == 0
    assert "up to date: all 3 objects" in capsys.readouterr().err
    assert snapshot(copy) == before and verify_dataset(copy) == []


def test_shards_whose_record_predates_recorded_inputs_are_refused_as_not_recorded(reference, corpus, tmp_path, capsys):
    """A complete shard of another fingerprint whose record does not say its inputs (written before records
    kept them): the refusal says so instead of listing differences, and the dataset is unchanged."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    path = copy / layout.completion_record(OBJECTS[0])
    record = json.loads(path.read_text())
    del record["inputs"]
    path.write_text(json.dumps({**record, "fingerprint": "from an older version"}))
    before = snapshot(copy)
    assert build(corpus, copy, "--workers", "1") == 2
    err = capsys.readouterr().err
    assert f"{copy} holds 1 shard(s) built from other inputs (not recorded). To replace it, add --force" in err
    assert err.count("\n") == 1 and snapshot(copy) == before


def test_a_refusal_over_other_inputs_names_the_first_three_differences(reference, corpus, tmp_path, capsys):
    """Four parameters changed: the one-line refusal names three of them, "; " apart, and changes nothing."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    changed = ["--trials", "6", "--contacts", "31", "--set", "suction.n_candidates=21", "--set", "suction.n_samples=6"]
    assert main(["dataset", "--corpus", str(corpus), "--out", str(copy), *PARAMS, *changed]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and verify_dataset(copy) == []
    named = err.split("3 shard(s) built from other inputs (", 1)[1].split("). To replace it", 1)[0].split("; ")
    every = {"config.topple.n_trials: 5 -> 6", "config.contacts.n_contacts: 30 -> 31",
             "config.suction.n_candidates: 20 -> 21", "config.suction.n_samples: 5 -> 6"}
    assert len(named) == 3 and set(named) < every, named


def test_an_unfinished_staged_shard_is_computed_again(reference, corpus, tmp_path, capsys):
    """A killed run left part of a shard in the staging directory (no completion record): the next run
    deletes it, computes that object again and commits the same dataset."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    (copy / layout.completion_record(OBJECTS[1])).unlink()
    staged = staging_dir(copy) / layout.arrays_file(OBJECTS[1])
    staged.parent.mkdir(parents=True)
    staged.write_bytes((reference / layout.arrays_file(OBJECTS[1])).read_bytes()[:100])
    assert build(corpus, copy, "--workers", "1") == 0, capsys.readouterr().err
    assert f"resuming: 2 of 3 objects already complete in {copy}\n" in capsys.readouterr().err
    assert (read_manifest(copy).run["computed"], read_manifest(copy).run["reused"]) == (1, 2)
    assert not staging_dir(copy).exists() and verify_dataset(copy) == []
    assert_same_dataset(reference, copy)


def test_a_staged_leftover_of_an_object_outside_the_corpus_is_deleted_by_an_up_to_date_run(reference, corpus, tmp_path):
    """Part of a shard staged by a killed run of another corpus: a run with nothing to do still deletes it,
    and the staging directory it leaves holding no file (no empty hidden directory beside --out)."""
    copy = tmp_path / "dataset"
    shutil.copytree(reference, copy)
    leftover = staging_dir(copy) / layout.arrays_file("gone")
    leftover.parent.mkdir(parents=True)
    leftover.write_bytes(b"partial")
    assert build(corpus, copy, "--workers", "1") == 0
    assert not staging_dir(copy).exists() and verify_dataset(copy) == []


def test_a_failed_run_removes_only_the_staging_directory_it_made(tmp_path, capsys):
    """A --force --strict run stopped by its only object: the staging directory it made holds just its
    forced-run note, nothing to resume, and goes; one that was there before with a file in it is an earlier
    run's to judge and stays."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n")
    corpus = write_corpus(tmp_path, [], "flat,,meshes/flat.obj,1,0.1\n")
    fresh = tmp_path / "fresh"
    assert build(corpus, fresh, "--force", "--strict", "--workers", "1") == 1
    assert not staging_dir(fresh).exists() and not fresh.exists()
    kept = tmp_path / "kept"
    staging_dir(kept).mkdir()
    (staging_dir(kept) / "notes.txt").write_text("an earlier run's")
    assert build(corpus, kept, "--strict", "--workers", "1") == 1
    assert (staging_dir(kept) / "notes.txt").read_text() == "an earlier run's"
    capsys.readouterr()


def test_a_force_runs_note_changes_with_any_source_file_and_the_kernel_but_not_who_requested_it(monkeypatch):
    """``_forced_run`` tells this code from any other: an edit to a file of ``pipeline`` or ``schema`` or another
    BLAS kernel changes it; which kernel was requested (not the one computed with) does not."""
    from pipeline.build import manifest

    note = dataset._forced_run()
    read_bytes = Path.read_bytes
    for edited in ("pipeline/build/rows.py", "schema/layout.py"):
        monkeypatch.setattr(Path, "read_bytes", lambda p, e=edited: read_bytes(p) + (b"#" if p.as_posix().endswith(e) else b""))
        assert dataset._forced_run() != note, edited
    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    code_version = manifest.code_version

    def with_blas(**blas):
        version = code_version()
        return {**version, "blas": {**version["blas"], **blas}}

    monkeypatch.setattr(manifest, "code_version", lambda: with_blas(requested="another"))
    assert dataset._forced_run() == note
    monkeypatch.setattr(manifest, "code_version", lambda: with_blas(kernel="another"))
    assert dataset._forced_run() != note


def test_failure_groups_put_the_most_common_reason_first():
    """Grouped by the reason without its id and details, the largest group first (not alphabetical)."""
    groups = dataset.failure_groups([("a", "a: too large (3 m)"), ("b", "b: too large (4 m)"), ("c", "c: cannot read c.obj")])
    assert list(groups.items()) == [("too large", ["a", "b"]), ("cannot read <file>", ["c"])]
