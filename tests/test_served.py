# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
"""The served tables (schema/served.py): what the build writes is what the Parquet tables say,
the service maps them without copying, and anything stale, missing or inconsistent is either
served from Parquet instead or refused with a message naming the problem."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute
import pyarrow.parquet as pq
import pytest

from pipeline.build.verify import verify_dataset
from schema import served
from schema.reader import Dataset
from service.prefetch import Prefetch, map_and_hash
from service.store import LOAD_ATTEMPTS, DatasetError, Store
from tests.test_service import ROOT, dataset  # noqa: F401 (fixture)


def same_objects(a: Store, b: Store) -> None:
    assert list(a.objects) == list(b.objects)
    for object_id, one in a.objects.items():
        other = b.objects[object_id]
        for field in dataclasses.fields(one):
            x, y = getattr(one, field.name), getattr(other, field.name)
            if isinstance(x, dict):
                assert x.keys() == y.keys() and all(
                    np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f") for k in x), field.name
            elif isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), (object_id, field.name)
            else:
                assert x == y, field.name


def test_mapped_tables_are_views_and_equal_the_parquet_tables_converted(dataset, tmp_path, caplog):
    started = time.perf_counter()
    mapped = Store.load(dataset)
    assert 0 < mapped.load_seconds <= time.perf_counter() - started
    obj = next(iter(mapped.objects.values()))
    assert not obj.points.flags.writeable and not obj.q.flags.owndata, "a view into the mapped file, not a copy"
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / served.SERVED_DIR)
    with caplog.at_level(logging.WARNING, logger="service"):
        converted = Store.load(copy)
    assert "served/objects.arrow: missing" in caplog.text and "reading the Parquet tables instead" in caplog.text
    same_objects(mapped, converted)
    # Every object's served rows hold what the analysts' tables hold (so an offset into the
    # shared columns cannot be wrong the same way on both paths).
    reader = Dataset.open(dataset)
    poses = reader.table("poses")
    hulls = dict(zip(*reader.table("objects", ["object_id", "hull_vertices"]).to_pydict().values()))
    for object_id, obj in mapped.objects.items():
        np.testing.assert_array_equal(obj.hull_vertices, np.reshape(hulls[object_id], (-1, 3)))
        by = [("pose", "ascending"), ("action", "ascending")]
        actions = reader.object_rows("actions", object_id, ["pose", "action", "q", "point_x"]).sort_by(by)
        np.testing.assert_array_equal(obj.q, actions.column("q").to_numpy(zero_copy_only=False))
        np.testing.assert_array_equal(obj.points[:, 0], actions.column("point_x").to_numpy().astype(np.float32))
        transitions = reader.object_rows("transitions", object_id).sort_by([*by, ("next_pose", "ascending")])
        np.testing.assert_array_equal(obj.next_pose, transitions.column("next_pose").to_numpy())
        own = poses.filter(pa.compute.equal(poses.column("object_id"), object_id)).sort_by("pose")
        np.testing.assert_array_equal(obj.v_s, own.column("v_s").to_numpy())
        np.testing.assert_array_equal(obj.transforms.reshape(-1, 16), np.stack(own.column("transform").to_pylist()))


def test_served_files_of_another_build_are_not_used(dataset, tmp_path, caplog):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["tables"]["served/actions.arrow"]["rows"] += 1  # as if the manifest described another build
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with caplog.at_level(logging.WARNING, logger="service"):
        store = Store.load(copy)
    assert "served/actions.arrow holds" in caplog.text and store.counts["objects"] == 3
    assert any("served/actions.arrow" in problem for problem in verify_dataset(copy))


def test_a_tampered_served_file_fails_verify(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    with open(copy / "served" / "poses.arrow", "ab") as handle:
        handle.write(b"x")
    assert any(p.startswith("served/poses.arrow: sha256") for p in verify_dataset(copy))


def test_a_served_file_damaged_after_the_build_is_not_served(dataset, tmp_path, caplog):
    """A bit pattern changed inside a mapped table would be served as it stands (an Arrow file
    has no checksums of its own): the load hashes the mapped bytes and serves the Parquet
    tables instead, naming the file."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    good = Store.load(dataset)
    path = copy / "served" / "poses.arrow"
    data = path.read_bytes()
    # A pose probability whose 8 bytes occur once in the file: replacing them changes that number alone.
    first = next(b for b in (p.tobytes() for o in good.objects.values() for p in o.probability) if data.count(b) == 1)
    path.write_bytes(data.replace(first, np.float64(7.5).tobytes()))  # same size, same schema, one number wrong
    tampered = served.read_served(copy)["poses"]  # still a readable table...
    assert 7.5 in tampered.column("probability").to_pylist()
    with caplog.at_level(logging.WARNING, logger="service"):
        store = Store.load(copy)
    recorded = json.loads((copy / "manifest.json").read_text())["tables"]["served/poses.arrow"]["sha256"]
    assert re.search(rf"served/poses\.arrow: sha256 \w{{12}}\.\.\. differs from the manifest's {recorded[:12]}\.\.\. "
                     r"\(changed after the build; a rerun of the build rewrites it\); reading the Parquet", caplog.text)
    assert "reading the Parquet tables instead" in caplog.text
    same_objects(store, good)  # ...but what is served is the build's numbers
    assert 7.5 not in np.concatenate([o.probability for o in store.objects.values()])
    # The build's own check of its tables hashes them separately (``_damaged_tables``), so it reads them unhashed.
    from schema.manifest import read_manifest

    assert served.read_current(copy, read_manifest(copy), verify=False)["poses"].num_rows == tampered.num_rows
    with pytest.raises(served.ServedError, match="served/poses.arrow: sha256"):
        served.read_current(copy, read_manifest(copy))


def test_served_files_the_manifest_does_not_record_or_of_another_schema_are_not_served(dataset, tmp_path, caplog):
    """A manifest from before the served files records none of them, and a served file may be another
    code's layout with the bytes its manifest records: either way the load serves the Parquet tables."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    good = Store.load(dataset)
    manifest = json.loads((copy / "manifest.json").read_text())
    entry = manifest["tables"].pop("served/hulls.arrow")
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with caplog.at_level(logging.WARNING, logger="service"):
        same_objects(Store.load(copy), good)
    assert "manifest.json records no served/hulls.arrow (built by an older toppledb); reading the Parquet tables instead" in caplog.text
    # float32 vertices: a readable table of the same rows, recorded by its manifest, but not this code's schema.
    path = copy / "served" / "hulls.arrow"
    hulls = pa.ipc.open_file(pa.py_buffer(path.read_bytes())).read_all()
    other = hulls.cast(pa.schema([("vertex", pa.list_(pa.float32(), 3))]))
    with pa.ipc.new_file(tmp_path / "hulls.arrow", other.schema) as writer:
        writer.write_table(other)
    os.replace(tmp_path / "hulls.arrow", path)
    manifest["tables"]["served/hulls.arrow"] = {**entry, "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}
    (copy / "manifest.json").write_text(json.dumps(manifest))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="service"):
        same_objects(Store.load(copy), good)
    assert f"{path}: not the served hulls table of this code (schema differs); reading the Parquet tables instead" in caplog.text


def test_a_served_file_that_cannot_be_opened_is_reported_with_its_reason_cut_to_200_characters(dataset, tmp_path, caplog):
    """A symlink loop in place of a served file: open's reason names the path, which is long here, so
    the log line gives its first 200 characters (a reason may be kilobytes) and serves the Parquet tables."""
    copy = tmp_path / ("long-" * 30) / "dataset"
    shutil.copytree(dataset, copy)
    path = copy / "served" / "objects.arrow"
    path.unlink()
    path.symlink_to(path)
    reason = f"[Errno 40] Too many levels of symbolic links: '{path}'"
    assert len(reason) > 200
    with caplog.at_level(logging.WARNING, logger="service"):
        same_objects(Store.load(copy), Store.load(dataset))
    assert f"{path}: unreadable: {reason[:200]}; reading the Parquet tables instead" in caplog.text


@pytest.fixture(scope="module")
def parquet(dataset):
    table = Dataset.open(dataset)
    ids = table.table("objects").column("object_id").to_pylist()
    return (table.table("objects"), table.table("poses"),
            [table.object_rows("actions", i, served.ACTION_COLUMNS) for i in ids],
            [table.object_rows("transitions", i, served.TRANSITION_COLUMNS) for i in ids])


def test_tables_that_do_not_fit_together_are_refused_by_name(parquet):
    objects, poses, actions, transitions = parquet
    served.served_tables(objects, poses, actions, transitions)  # the real ones fit

    def refused(match, **changed):
        args = {"objects": objects, "poses": poses, "actions": list(actions), "transitions": list(transitions), **changed}
        with pytest.raises(served.ServedError, match=match):
            served.served_tables(**args)

    refused("actions partition does not hold", actions=[actions[0].slice(1), *actions[1:]])
    status = actions[0].column("status").to_pylist()
    refused("unknown action status", actions=[actions[0].set_column(
        actions[0].schema.get_field_index("status"), "status", pa.array(["teleported", *status[1:]])), *actions[1:]])
    far = transitions[0].set_column(transitions[0].schema.get_field_index("next_pose"), "next_pose",
                                    pa.array([99] * transitions[0].num_rows, pa.int32()))
    refused("transitions refer to poses or actions that do not exist", transitions=[far, *transitions[1:]])
    refused("poses.parquet holds poses", poses=poses.slice(1))
    refused("3 objects but 2 action", actions=actions[:2])


def test_a_dataset_whose_tables_do_not_fit_is_not_served(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / served.SERVED_DIR)
    ids = pq.read_table(copy / "objects.parquet").column("object_id").to_pylist()
    part = copy / "actions" / f"object_id={ids[0]}" / "part-0.parquet"
    pq.write_table(pq.read_table(part).slice(1), part)
    manifest = json.loads((copy / "manifest.json").read_text())
    recorded = manifest["shards"][ids[0]]["files"][f"actions/object_id={ids[0]}/part-0.parquet"]
    with pytest.raises(DatasetError, match=rf"actions/object_id={ids[0]}/part-0.parquet: sha256 \w{{12}}\.\.\. differs from the manifest's "
                                           rf"{recorded[:12]}\.\.\.; check it with `toppledb verify"):
        Store.load(copy)  # not the bytes the build wrote
    # A file the manifest does not record is not the build's either, whatever it holds.
    del manifest["shards"][ids[0]]["files"][f"actions/object_id={ids[0]}/part-0.parquet"]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match=rf"actions/object_id={ids[0]}/part-0.parquet: not recorded; check it with `toppledb verify"):
        Store.load(copy)
    # As if a build had written them so (recorded their checksum): the tables still have to fit together.
    manifest["shards"][ids[0]]["files"][f"actions/object_id={ids[0]}/part-0.parquet"] = hashlib.sha256(part.read_bytes()).hexdigest()
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="actions partition does not hold"):
        Store.load(copy)


def test_the_parquet_tables_a_damaged_served_file_falls_back_to_are_checked_too(dataset, tmp_path, caplog):
    """Served from Parquet because a served file is damaged, the Parquet files must be the build's
    bytes too: a damaged poses.parquet is refused, not served (it would give its numbers as they stand)."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    (copy / "served" / "poses.arrow").write_bytes(b"")  # empty: unreadable
    poses = pq.read_table(copy / "poses.parquet")
    v_s = poses.column("v_s").to_pylist()
    pq.write_table(poses.set_column(poses.schema.get_field_index("v_s"), poses.schema.field("v_s"),
                                    pa.array([0.123, *v_s[1:]], pa.float64())), copy / "poses.parquet")
    with caplog.at_level(logging.WARNING, logger="service"), \
            pytest.raises(DatasetError, match=r"poses.parquet: sha256 \w{12}\.\.\. differs from the manifest's.*toppledb verify"):
        Store.load(copy)
    assert "served/poses.arrow: unreadable: cannot mmap an empty file; reading the Parquet tables instead" in caplog.text
    (copy / "poses.parquet").unlink()
    with pytest.raises(DatasetError, match="poses.parquet: missing or unreadable"):
        Store.load(copy)


def test_a_dataset_whose_tables_hold_other_counts_than_its_manifest_is_not_served(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["counts"]["poses"] += 1
    (copy / "manifest.json").write_text(json.dumps(manifest))
    poses = manifest["counts"]["poses"]
    with pytest.raises(DatasetError, match=rf"the tables hold .*'poses': {poses - 1},.* but manifest.json says .*'poses': {poses},.*"
                                           rf"check it with `toppledb verify {re.escape(str(copy))}`"):
        Store.load(copy)


def test_a_dataset_without_current_served_tables_gets_them_without_recomputing(dataset, tmp_path):
    from pipeline.build.corpus import Corpus, ObjectSpec
    from pipeline.build.dataset import build_dataset
    from pipeline.model.config import Config
    from schema.manifest import read_manifest

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / served.SERVED_DIR)  # as a build by older code left it
    manifest = read_manifest(copy)
    corpus = Corpus(manifest.corpus.name, [ObjectSpec(**o.model_dump()) for o in manifest.corpus.objects])
    config = Config.from_dict(manifest.parameters.model_dump())
    summary = build_dataset(corpus, config, copy, workers=1, progress=False, log=lambda _: None)
    assert summary.computed == 0 and summary.reused == 3
    assert verify_dataset(copy) == []
    same_objects(Store.load(copy), Store.load(dataset))


def test_a_load_that_meets_a_rebuild_s_commit_is_made_again_once_the_manifest_changed(dataset, tmp_path, monkeypatch):
    """A rebuild renames its files into place one by one, the manifest last: a load in between is
    refused by the checksums, and made again when the manifest changed meanwhile; a refusal with the
    manifest unchanged is the answer."""
    import service.store as store_module

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    real, calls = store_module.Store._load_once, []

    def mid_commit(root, prefetch=None):
        calls.append(root)
        if len(calls) == 1:  # the rebuild's last rename lands while this load reads
            manifest = copy / "manifest.json"
            (copy / "manifest.new").write_bytes(manifest.read_bytes())
            (copy / "manifest.new").replace(manifest)
            raise DatasetError("served/actions.arrow: sha256 differs (new files, old manifest)")
        return real(root, prefetch)

    monkeypatch.setattr(store_module.Store, "_load_once", mid_commit)
    assert Store.load(copy).counts["objects"] == 3 and len(calls) == 2
    calls.clear()
    monkeypatch.setattr(store_module.Store, "_load_once", lambda root, prefetch=None: (calls.append(root), real(copy / "nowhere"))[1])
    with pytest.raises(DatasetError, match="no such dataset directory"):
        Store.load(copy)
    assert len(calls) == 1, "nothing changed: refused at once"
    # A manifest that changes during every load (rebuilds in a loop) is given up on after LOAD_ATTEMPTS loads.
    calls.clear()

    def always_mid_commit(root, prefetch=None):
        calls.append(root)
        (copy / "manifest.new").write_bytes((copy / "manifest.json").read_bytes())
        (copy / "manifest.new").replace(copy / "manifest.json")
        raise DatasetError(f"served/actions.arrow: sha256 differs (load {len(calls)})")

    monkeypatch.setattr(store_module.Store, "_load_once", always_mid_commit)
    with pytest.raises(DatasetError, match=f"load {LOAD_ATTEMPTS}\\)"):
        Store.load(copy)
    assert len(calls) == LOAD_ATTEMPTS


def test_the_load_parses_the_manifest_bytes_it_hashed(dataset, tmp_path, monkeypatch):
    """The store names its build by the SHA-256 of manifest.json's bytes: a rebuild that replaces the
    file between the load's read and its parse must not pair the old hash with the new manifest."""
    import service.store as store_module

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    raw = (copy / "manifest.json").read_bytes()
    real = store_module.read_manifest

    def replaced_meanwhile(root, raw_read=None):
        rebuilt = json.loads(raw)
        rebuilt["created"] = "2099-01-01T00:00:00+00:00"
        (copy / "manifest.json").write_text(json.dumps(rebuilt))
        return real(root, raw_read)

    monkeypatch.setattr(store_module, "read_manifest", replaced_meanwhile)
    store = Store.load(copy)
    assert store.manifest_sha256 == hashlib.sha256(raw).hexdigest()
    assert store.manifest.created == json.loads(raw)["created"] != "2099-01-01T00:00:00+00:00"


def test_the_service_takes_prefetched_mappings_only_for_the_build_it_loads(dataset, tmp_path, caplog):
    """``python -m service`` maps and hashes the served files while it imports (``service.prefetch``):
    the load uses those digests for the same directory and manifest, and maps its own otherwise."""
    import hashlib as _hashlib
    import os

    from service.prefetch import Prefetch

    manifest_sha256 = _hashlib.sha256((dataset / "manifest.json").read_bytes()).hexdigest()
    prefetch = Prefetch(dataset)
    files = prefetch.mapped(dataset, manifest_sha256)
    assert sorted(files) == sorted(served.FILES.values())
    for relative, (mapping, digest) in files.items():
        assert digest == _hashlib.sha256((dataset / relative).read_bytes()).hexdigest() and len(mapping) > 0
    assert prefetch.mapped(dataset, manifest_sha256) == {}, "handed over once: it keeps no old build mapped"
    assert Prefetch(dataset).mapped(tmp_path, manifest_sha256) == {}
    assert Prefetch(dataset).mapped(dataset, "0" * 64) == {}
    same_objects(Store.load(dataset, Prefetch(dataset)), Store.load(dataset))
    # The load trusts the prefetched digest of the bytes it serves: a wrong one is a damaged file.
    wrong = Prefetch(dataset)
    wrong._thread.join()
    wrong._files["served/hulls.arrow"] = (wrong._files["served/hulls.arrow"][0], "0" * 64)
    with caplog.at_level(logging.WARNING, logger="service"):
        Store.load(dataset, wrong)
    assert "served/hulls.arrow: sha256 000000000000... differs" in caplog.text
    # Another directory's prefetch, or one that found nothing, leaves the load to map its own.
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="service"):
        same_objects(Store.load(copy, Prefetch(dataset)), Store.load(dataset))
        same_objects(Store.load(copy, Prefetch(tmp_path / "nowhere")), Store.load(dataset))
    assert "Parquet" not in caplog.text
    # A symlink loop or a named pipe in place of a served file is the load's to report, not a hang or a crash.
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    with pytest.raises(DatasetError, match="no such dataset directory"):
        Store.load(loop, Prefetch(loop))
    (copy / "served" / "poses.arrow").unlink()
    os.mkfifo(copy / "served" / "poses.arrow")
    with caplog.at_level(logging.WARNING, logger="service"):
        same_objects(Store.load(copy, Prefetch(copy)), Store.load(dataset))  # from Parquet
    assert f"{copy / 'served' / 'poses.arrow'}: not a regular file; reading the Parquet tables instead" in caplog.text
    assert "unreadable" not in caplog.text


def smaps_rss_kb(path: Path) -> list[int]:
    """Resident kB of each of this process's mappings of ``path`` (/proc/self/smaps)."""
    rss, current = [], False
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            first = line.split(maxsplit=1)[0]
            if "-" in first and not first.endswith(":"):  # a mapping's header: address range, ..., path
                current = line.rstrip("\n").endswith(str(path))
            elif current and first == "Rss:":
                rss.append(int(line.split()[1]))
    return rss


def test_map_and_hash_refuses_what_it_cannot_map_and_leaves_the_hashed_pages_out_of_the_resident_set(tmp_path):
    """The prefetch's digest is of the mapped bytes; hashed, the pages are advised away, so a worker's
    resident set holds only what its requests touch (the pages stay in the shared file cache)."""
    path = tmp_path / "blob.arrow"
    data = np.random.default_rng(0).bytes(4 << 20)
    path.write_bytes(data)
    mapping, digest = map_and_hash(path)
    assert digest == hashlib.sha256(data).hexdigest()
    if os.path.exists("/proc/self/smaps"):  # Linux
        assert smaps_rss_kb(path) == [0], "hashed pages left in the resident set"
    assert mapping[:] == data, "read again from the file cache"
    mapping.close()
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "empty.arrow").write_bytes(b"")
    for name in ("pipe", "nowhere.arrow", "."):
        with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path / name))}: not a regular file"):
            map_and_hash(tmp_path / name)  # a named pipe would wait for a writer
    with pytest.raises(ValueError, match="cannot mmap an empty file"):
        map_and_hash(tmp_path / "empty.arrow")


def test_a_prefetch_waiting_for_its_manifest_hands_over_nothing_and_does_not_keep_the_process_alive(tmp_path):
    """The prefetch reads manifest.json on a daemon thread: should that read wait (a stalled network disk;
    a named pipe here), a service that stops before it loads (a port in use, a bad option) still exits."""
    os.mkfifo(tmp_path / "manifest.json")
    prefetch = Prefetch(tmp_path)
    with open(tmp_path / "manifest.json", "wb"):
        pass  # the prefetch's read ends, empty: not JSON
    assert prefetch.mapped(tmp_path, "") == {}, "the load passes '' when it could not read the manifest"
    code = "import sys; from service.prefetch import Prefetch; Prefetch(sys.argv[1]); print('exiting')"
    result = subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=False, capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert result.returncode == 0 and result.stdout == "exiting\n", result.stderr


def test_directories_this_user_may_not_enter_are_reported_not_raised(dataset, tmp_path, monkeypatch, caplog):
    """As root the tests cannot be refused a directory, so Path refuses as Python 3.11 does for another user."""
    from schema.manifest import ManifestError, read_manifest

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    real_exists, real_is_dir = Path.exists, Path.is_dir

    def refused_below(directory):
        def check(real):
            def call(self, *args, **kwargs):
                if directory in self.parents or self == directory:
                    raise PermissionError(13, "Permission denied", str(self))
                return real(self, *args, **kwargs)
            return call
        return check

    # served/ is not ours to enter: the service says which file and falls back to the Parquet tables.
    monkeypatch.setattr(Path, "exists", refused_below(copy / "served")(real_exists))
    with caplog.at_level(logging.WARNING):
        store = Store.load(copy)
    assert store.counts["objects"] == 3
    assert "served/objects.arrow: unreadable: Permission denied; reading the Parquet tables instead" in caplog.text
    # The dataset lies below a directory not ours to enter: a one-line refusal, not a traceback.
    monkeypatch.setattr(Path, "exists", real_exists)
    monkeypatch.setattr(Path, "is_dir", refused_below(tmp_path)(real_is_dir))
    with pytest.raises(ManifestError, match=r"dataset: cannot be read \(Permission denied\)"):
        read_manifest(copy)
    with pytest.raises(DatasetError, match="cannot be read"):
        Store.load(copy)
