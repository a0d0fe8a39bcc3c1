# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""A robot's own pushes as a push log (``schema.pushlog``: ``dataset_meshes``, ``robot_row``,
``write_log``): the row is the ``/plan`` push in the object frame, and the log reader reads it back
as the dataset's push from the planned pose."""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

import schema.files
import schema.pushlog
import service.client
from pipeline.build.corpus import pybullet_data_dir
from pipeline.model.config import Config, PoseConfig
from pipeline.studies.logreader import read_log, recorded_world
from schema.api import PlanResponse
from schema.files import file_sha256
from schema.manifest import ManifestError
from schema.pushlog import PUSHLOG, LoggedMesh, dataset_meshes, rigid, robot_row, row_problems, write_log
from service import create_app
from tests.test_service import client, dataset, planar_transform, stored_transform, tables  # noqa: F401

ROBOT = {"finger_speed": 0.05, "finger_radius": 0.004, "source": "robot:test"}


@pytest.fixture(scope="module")
def executed(client, tables):
    """(object_id, pose, observed start, observed final, answer) for every pose of the tiny dataset seen
    at a random yaw and place where value iteration pushes; the final is the push's likeliest next pose,
    turned and moved again."""
    rng = np.random.default_rng(11)
    out = []
    for (object_id, pose), _ in sorted(tables["poses"].items()):
        observed = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.5, 0.5, 2)) @ stored_transform(tables, object_id, pose)
        answer = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist()}).json()
        if answer["push"] is None:
            continue
        likeliest = max(answer["next_poses"], key=lambda n: n["probability"])["next_pose"]
        final = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.5, 0.5, 2)) @ stored_transform(tables, object_id, likeliest)
        out.append((object_id, pose, observed, final, answer))
    assert len(out) >= 5, "the tiny dataset should have poses where value iteration pushes"
    return out


def test_a_row_is_the_plan_s_push_in_the_object_frame(executed, dataset, tables):
    meshes = dataset_meshes(dataset)
    contacts = tables["manifest"]["parameters"]["contacts"]
    for push_id, (object_id, pose, observed, final, answer) in enumerate(executed):
        row = robot_row(answer, observed, final, meshes[object_id], push_id=push_id, **ROBOT)
        start = np.array(row["start_transform"]).reshape(4, 4)
        point = np.array([row[f"point_{a}"] for a in "xyz"])
        direction = np.array([row[f"direction_{a}"] for a in "xyz"])
        np.testing.assert_array_equal(start, observed)
        np.testing.assert_array_equal(np.array(row["final_transform"]).reshape(4, 4), final)
        # The world push, as the robot executed it, is the logged push placed by the start pose.
        np.testing.assert_allclose(start[:3, :3] @ point + start[:3, 3], answer["push"]["point"], atol=1e-12)
        np.testing.assert_allclose(start[:3, :3] @ direction, answer["push"]["direction"], atol=1e-12)
        assert (row["start_pose"], row["action"], row["push_id"], row["repeat"]) == (pose, answer["action"], push_id, 0)
        assert (row["approach_offset"], row["push_depth"]) == (contacts["approach_offset"], contacts["push_depth"])
        assert (row["finger_speed"], row["finger_radius"], row["source"], row["seed"]) == (0.05, 0.004, "robot:test", None)
        assert (row["mesh_sha256"], row["scale"], row["mass"]) == (meshes[object_id].mesh_sha256, 0.015, 0.1)


def test_the_log_reads_back_as_the_dataset_s_pushes_from_the_planned_poses(executed, dataset, tables, tmp_path):
    meshes = dataset_meshes(dataset)
    rows = [robot_row(answer, observed, final, meshes[object_id], push_id=i, **ROBOT)
            for i, (object_id, _, observed, final, answer) in enumerate(executed)]
    # Two sessions that number their pushes alike, side by side: two logs, every push kept.
    half = len(rows) // 2
    first = write_log(rows[:half], tmp_path / "robot" / "session-1", dataset=dataset)
    second = write_log([dict(row, push_id=row["push_id"] - half) for row in rows[half:]], tmp_path / "robot" / "session-2",
                       dataset=dataset)
    assert (first, second) == (tmp_path / "robot" / "session-1" / "pushes.parquet", tmp_path / "robot" / "session-2" / "pushes.parquet")
    assert sorted(p.name for p in (tmp_path / "robot").rglob("*")) == ["pushes.parquet", "pushes.parquet", "session-1", "session-2"]
    log = read_log([tmp_path / "robot"], Config())
    assert log.rejected == {} and len(log.pushes) == len(executed)
    by_id = {(push.log, push.push_id): push for push in log.pushes}
    for i, (object_id, pose, _, final, answer) in enumerate(executed):
        push, action = by_id[(int(i >= half), i - half * (i >= half))], tables["actions"][(object_id, pose, answer["action"])]
        assert push.object_id == object_id and push.pose == pose
        # The reader's pose-frame push is the dataset's candidate (stored in float32).
        np.testing.assert_allclose(push.point, [action[f"point_{a}"] for a in "xyz"], atol=1e-6)
        np.testing.assert_allclose(push.direction, [action[f"direction_{a}"] for a in "xyz"], atol=1e-6)
        likeliest = max(answer["next_poses"], key=lambda n: n["probability"])["next_pose"]
        assert push.outcomes.tolist() == [likeliest]
    # The file names the dataset's pose numbering, which its start_pose column uses.
    recorded = recorded_world(pq.read_schema(first).metadata)
    assert recorded is not None and PoseConfig(**json.loads(recorded)) == PoseConfig(**tables["manifest"]["parameters"]["poses"])
    assert recorded_world(pq.read_schema(write_log(rows[:1], tmp_path / "plain")).metadata) is None


def test_the_client_s_model_of_the_answer_gives_the_same_row(executed, dataset):
    object_id, _, observed, final, answer = executed[0]
    mesh = dataset_meshes(dataset)[object_id]
    typed = PlanResponse.model_validate(answer)
    assert robot_row(typed, observed, final, mesh, push_id=3, repeat=2, **ROBOT) == robot_row(
        answer, observed, final, mesh, push_id=3, repeat=2, **ROBOT)


def test_a_plan_without_a_push_another_object_or_a_bad_matrix_is_refused(client, executed, dataset, tables):
    meshes = dataset_meshes(dataset)
    object_id, _, observed, final, answer = executed[0]
    grasping = [(o, p) for (o, p), row in tables["poses"].items() if row["value_iteration_action"] == -1]
    assert grasping, "the tiny dataset should have a pose where value iteration does not push"
    other, pose = grasping[0]
    seen = stored_transform(tables, other, pose)
    no_push = client.post("/plan", json={"object_id": other, "pose": seen.tolist()}).json()
    with pytest.raises(ValueError, match=f"chose no push \\(decision {no_push['decision']!r}\\)"):
        robot_row(no_push, seen, seen, meshes[other], push_id=0, **ROBOT)
    stranger = next(mesh for name, mesh in meshes.items() if name != object_id)
    with pytest.raises(ValueError, match=f"plan is for object '{object_id}'"):
        robot_row(answer, observed, final, stranger, push_id=0, **ROBOT)
    with pytest.raises(ValueError, match=r"start_transform must be a 4x4 matrix, not shape \(3, 3\)"):
        robot_row(answer, observed[:3, :3], final, meshes[object_id], push_id=0, **ROBOT)
    with pytest.raises(ValueError, match="final_transform must be a 4x4"):
        robot_row(answer, observed, final.ravel(), meshes[object_id], push_id=0, **ROBOT)


def test_write_log_writes_all_or_nothing_and_never_writes_into_a_log(executed, dataset, tmp_path):
    meshes = dataset_meshes(dataset)
    rows = [robot_row(answer, observed, final, meshes[object_id], push_id=i, **ROBOT)
            for i, (object_id, _, observed, final, answer) in enumerate(executed[:3])]
    skewed = dict(rows[1], final_transform=(np.diag([1.0, 2.0, 1.0, 1.0])).ravel().tolist())
    target = tmp_path / "session"
    refused = {
        r"1 problem in 3 rows, nothing written: row 1: final_transform is not a rigid": [rows[0], skewed, rows[2]],
        "no rows": [],
        r"rows lack the columns \['mu_finger'\]": [{k: v for k, v in rows[0].items() if k != "mu_finger"}],
        r"2 problems in 1 rows, nothing written: row 0: push_id must be an integer, not 3.7; row 0: source is empty": [dict(rows[0], source=None, push_id=3.7)],
        "row 1: repeat must be an integer, not '1'": [rows[0], dict(rows[1], repeat="1")],
    }
    for message, bad in refused.items():
        with pytest.raises(ValueError, match=message):
            write_log(bad, target)
    with pytest.raises(ValueError, match="push_id must be an integer, not 2.5"):
        robot_row(executed[0][4], executed[0][2], executed[0][3], meshes[executed[0][0]], push_id=2.5, **ROBOT)
    with pytest.raises(ValueError, match="log readers skip names that start with '_' or '.'"):
        write_log(rows, tmp_path / "_session")
    assert list(tmp_path.iterdir()) == [], "a refused write leaves nothing"
    path = write_log(rows, target)
    written = path.read_bytes()
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask, "a log is as readable as any file its writer makes"
    with pytest.raises(FileExistsError, match="is not empty: write each session to a new directory"):
        write_log(rows[:1], target)
    with pytest.raises(FileExistsError, match="is not empty"):
        write_log(rows[:1], tmp_path)  # the sessions' parent: a file there would join them into one log
    (tmp_path / "a-file").write_text("")
    with pytest.raises(NotADirectoryError, match="is a file"):
        write_log(rows[:1], tmp_path / "a-file")
    assert path.read_bytes() == written and sorted(p.name for p in tmp_path.rglob("*")) == ["a-file", "pushes.parquet", "session"]


def test_a_failed_write_leaves_no_file_and_a_claimed_name_is_kept(executed, dataset, tmp_path, monkeypatch):
    meshes = dataset_meshes(dataset)
    rows = [robot_row(answer, observed, final, meshes[object_id], push_id=i, **ROBOT)
            for i, (object_id, _, observed, final, answer) in enumerate(executed[:2])]

    def half_written(table, where):
        Path(where).write_bytes(b"PAR1")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(schema.pushlog.pq, "write_table", half_written)
    with pytest.raises(OSError, match="No space left on device"):
        write_log(rows, tmp_path / "full")
    assert list((tmp_path / "full").iterdir()) == [], "neither the log nor its temporary is left"
    monkeypatch.undo()
    # A file system without hard links (FAT, SMB, FUSE): the name is claimed, then the whole file moved onto it.
    def no_links(source, target):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(schema.files.os, "link", no_links)
    path = write_log(rows, tmp_path / "fat")
    assert len(read_log([path.parent], Config()).pushes) == 2 and [p.name for p in path.parent.iterdir()] == ["pushes.parquet"]

    def raced(source, target):  # another writer's file appears at the name just before it is claimed
        Path(target).write_bytes(b"theirs")
        raise OSError(errno.ENOTSUP, "Operation not supported")

    monkeypatch.setattr(schema.files.os, "link", raced)
    with pytest.raises(FileExistsError):
        write_log(rows, tmp_path / "shared")
    assert [(p.name, p.read_bytes()) for p in (tmp_path / "shared").iterdir()] == [("pushes.parquet", b"theirs")]

    def interrupted(source, target):
        raise KeyboardInterrupt

    monkeypatch.setattr(schema.files.os, "link", no_links)
    monkeypatch.setattr(schema.files.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_log(rows, tmp_path / "stopped")
    assert list((tmp_path / "stopped").iterdir()) == [], "neither the claim nor the temporary is left"


def test_dataset_meshes_name_each_object_as_the_build_read_it(dataset, tmp_path):
    meshes = dataset_meshes(dataset)
    assert sorted(meshes) == ["random_000", "random_001", "random_002"]
    for object_id, mesh in meshes.items():
        # pybullet's meshes are named relative to its data, so the log reads on another machine.
        assert (mesh.mesh_source, mesh.mesh_path) == ("pybullet_data", f"random_urdfs/{object_id[-3:]}/{object_id[-3:]}.obj")
        assert mesh.mesh_sha256 == file_sha256(pybullet_data_dir() / mesh.mesh_path)
        assert (mesh.scale, mesh.mass) == (0.015, 0.1)
    # A mesh of one's own is logged by its absolute path.
    copy = tmp_path / "copy"
    copy.mkdir()
    manifest = json.loads((dataset / "manifest.json").read_text())
    manifest["corpus"]["objects"][0].update(source="file", path="/meshes/part.obj")
    manifest["corpus"]["objects"][1].update(source="pybullet_data/random_urdfs", path="/elsewhere/part.obj")
    windows = "C:\\envs\\site-packages\\pybullet_data\\random_urdfs\\002\\002.obj"
    manifest["corpus"]["objects"][2].update(path=windows)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    own = dataset_meshes(copy)
    assert own["random_000"] == LoggedMesh("random_000", "file", "/meshes/part.obj", 0.015, 0.1,
                                            manifest["corpus"]["objects"][0]["sha256"])
    assert (own["random_001"].mesh_source, own["random_001"].mesh_path) == ("file", "/elsewhere/part.obj")
    # A build on Windows: pybullet's mesh is still named relative to pybullet_data.
    assert (own["random_002"].mesh_source, own["random_002"].mesh_path) == ("pybullet_data", "random_urdfs/002/002.obj")
    shutil.rmtree(copy)
    with pytest.raises(ManifestError, match="no such dataset directory"):
        dataset_meshes(copy)


def test_the_documented_robot_loop_runs_as_written(executed, dataset, tmp_path, monkeypatch):
    """docs/VALIDATION.md's example, with a stub robot whose first push leaves the object where it was
    and whose second moves it to the first push's likeliest next pose."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "VALIDATION.md").read_text()
    after = text.index("**Logging a robot's pushes.**")
    block = text[text.index("```python\n", after) + len("```python\n"):text.index("```", text.index("```python\n", after) + 3)]
    object_id, pose, observed, final, answer = executed[0]
    state = {"pose": observed, "executed": []}

    def observe(name):
        assert name == object_id
        return state["pose"]

    def execute(start, end):
        state["executed"].append((start, end))
        if len(state["executed"]) == 2:
            state["pose"] = final

    real = service.client.Client
    monkeypatch.setattr(service.client, "Client", lambda base_url, **kw: real(http=TestClient(create_app(dataset)), **kw))
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "dataset").symlink_to(dataset)
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "docs/VALIDATION.md", "exec"), {"object_id": object_id, "observe": observe, "execute": execute})  # noqa: S102  (the docs run as written)

    np.testing.assert_allclose(state["executed"][0], [answer["push"]["start"], answer["push"]["end"]], atol=1e-12)
    log = read_log([tmp_path / "data" / "logs" / "robot"], Config())
    assert log.rejected == {} and len(log.pushes) == len(state["executed"]) >= 2
    first, second = sorted(log.pushes, key=lambda push: push.push_id)[:2]
    likeliest = max(answer["next_poses"], key=lambda n: n["probability"])["next_pose"]
    assert (first.pose, first.outcomes.tolist()) == (pose, [pose]), "the first push failed"
    assert (second.pose, second.outcomes.tolist()) == (pose, [likeliest])
    assert not np.allclose(second.point, first.point) or not np.allclose(second.direction, first.direction), \
        "a push that left the object where it was is not served again"


def test_a_pose_observed_in_single_precision_is_mapped_in_double(executed, dataset):
    """A camera pipeline may give float32 poses: the row is the one of the same pose in float64, the push
    mapped into the object frame in double precision."""
    object_id, _, observed, final, answer = executed[0]
    mesh = dataset_meshes(dataset)[object_id]
    single = observed.astype(np.float32)
    assert robot_row(answer, single, final, mesh, push_id=0, **ROBOT) == robot_row(
        answer, single.astype(float), final, mesh, push_id=0, **ROBOT)
    with pytest.raises(ValueError, match="repeat must be an integer, not 1.5"):
        robot_row(answer, observed, final, mesh, push_id=0, repeat=1.5, **ROBOT)


def test_a_mesh_of_one_s_own_under_a_folder_named_pybullet_data_keeps_its_path(dataset, tmp_path):
    manifest = json.loads((dataset / "manifest.json").read_text())
    manifest["corpus"]["objects"][0].update(source="file", path="/home/me/pybullet_data/parts/part.obj")
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    own = dataset_meshes(tmp_path)["random_000"]
    assert (own.mesh_source, own.mesh_path) == ("file", "/home/me/pybullet_data/parts/part.obj")


def test_write_log_writes_the_push_log_s_schema_and_refuses_what_does_not_fit_it(executed, dataset, tmp_path):
    meshes = dataset_meshes(dataset)
    rows = [robot_row(answer, observed, final, meshes[object_id], push_id=i, **ROBOT)
            for i, (object_id, _, observed, final, answer) in enumerate(executed[:2])]
    path = write_log(rows, tmp_path / "session")
    written = pq.read_schema(path)
    assert written.equals(PUSHLOG) and written.metadata == PUSHLOG.metadata, "the columns' types and the log's version"
    assert [written.field(name).metadata for name in PUSHLOG.names] == [field.metadata for field in PUSHLOG]
    refused = {
        "^no rows to write$": [],
        r"^rows do not fit the push log's schema: Length of item not correct: expected 16 but got array of size 15$":
            [rows[0], dict(rows[1], final_transform=rows[1]["final_transform"][:15])],
        "^7 problems in 7 rows, nothing written: row 0: mass must be positive and finite; row 1: .*; row 4: mass must be "
        "positive and finite$": [dict(rows[0], push_id=i, mass=0.0) for i in range(7)],
    }
    for message, bad in refused.items():
        with pytest.raises(ValueError, match=message):
            write_log(bad, tmp_path / "refused")
    with pytest.raises(ValueError) as long:
        write_log([dict(rows[0], mass="heavy " * 100)], tmp_path / "refused")
    assert str(long.value) == "rows do not fit the push log's schema: " + f"Could not convert {'heavy ' * 100!r}"[:200]
    with pytest.raises(ValueError, match="log readers skip names that start with '_' or '.'"):
        write_log(rows, tmp_path / ".session")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session"], "a refused write leaves nothing"


# --- row_problems: every row checked, each bad one with its reason ---------------------------


def plain_row(**changes) -> dict:
    """A usable log row (an object standing at the origin, pushed along +x), with ``changes``."""
    row = {
        "object_id": "box", "mesh_sha256": "0" * 64, "mesh_source": "file", "mesh_path": "/meshes/box.stl",
        "scale": 1.0, "mass": 0.25, "push_id": 0, "repeat": 0, "start_pose": None,
        "start_transform": np.eye(4).ravel().tolist(), "point_x": -0.02, "point_y": 0.0, "point_z": 0.05,
        "direction_x": 1.0, "direction_y": 0.0, "direction_z": 0.0, "action": None, "finger_speed": 0.05,
        "approach_offset": 0.015, "push_depth": 0.04, "finger_radius": 0.004,
        "final_transform": np.eye(4).ravel().tolist(), "mu_table": None, "mu_finger": None, "source": "test", "seed": None,
    }
    return {**row, **changes}


def problems_of(*rows: dict) -> list[str | None]:
    return row_problems(pa.Table.from_pylist(list(rows), schema=PUSHLOG))


def test_each_number_of_a_row_is_held_to_its_own_bound():
    assert problems_of(plain_row()) == [None]
    for name in ("mass", "scale", "finger_speed"):
        assert problems_of(*(plain_row(**{name: v}) for v in (0.0, -1.0, math.nan, math.inf))) == [
            f"{name} must be positive and finite"] * 4, name
    for name in ("approach_offset", "push_depth", "finger_radius"):
        assert problems_of(*(plain_row(**{name: v}) for v in (0.0, -1e-6, math.nan, -math.inf))) == [
            None] + [f"{name} must be non-negative and finite"] * 3, name


def test_a_point_or_direction_with_nan_or_infinite_entries_is_named():
    assert problems_of(plain_row(), plain_row(point_y=math.nan), plain_row(direction_z=math.inf), plain_row(),
                       plain_row(direction_x=1e-12)) == [
        None, "point has NaN or infinite entries", "direction has NaN or infinite entries", None, "direction is zero"]


def test_a_missing_or_partly_missing_transform_is_named_and_the_other_column_still_checked():
    stretched = np.diag([2.0, 2.0, 2.0, 1.0]).ravel().tolist()
    holed = np.eye(4).ravel().tolist()
    holed[5] = None  # a null inside the matrix, as a Parquet file may hold
    assert problems_of(plain_row(start_transform=None), plain_row(final_transform=stretched), plain_row()) == [
        "start_transform missing", "final_transform is not a rigid transform (rotation with det +1, last row 0 0 0 1)", None]
    assert problems_of(plain_row(), plain_row(start_transform=holed)) == [None, "start_transform has NaN or infinite entries"]
    # A row without a matrix leaves the column's other rows checked.
    not_rigid = "final_transform is not a rigid transform (rotation with det +1, last row 0 0 0 1)"
    assert problems_of(plain_row(final_transform=None), plain_row(final_transform=stretched), plain_row(final_transform=holed),
                       plain_row()) == ["final_transform missing", not_rigid, "final_transform has NaN or infinite entries", None]


def test_a_rigid_transform_is_a_rotation_with_det_one_and_the_last_row_0_0_0_1_each_within_the_tolerance():
    shear = np.eye(4)
    shear[0, 1] = 0.5  # det 1, not a rotation
    lifted = np.eye(4)
    lifted[3, 2] = 0.5  # a rotation, but the last row is not 0 0 0 1
    turned = np.eye(4)
    turned[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    assert rigid(np.stack([turned, shear, lifted, np.eye(4)])).tolist() == [True, False, False, True]
    # The tolerance is the largest deviation accepted (exact in binary: 1.0625**2 - 1 = 0.12890625).
    tolerance = 1.0625**2 - 1
    scaled = np.diag([1.0625, 1.0625, 1.0, 1.0])  # R^T R - I and det R - 1 both exactly the tolerance
    raised = np.eye(4)
    raised[3, 0] = tolerance
    assert rigid(np.stack([scaled, raised]), tolerance).tolist() == [True, True]
    assert rigid(np.stack([scaled, raised]), np.nextafter(tolerance, 0.0)).tolist() == [False, False]
    leaning = np.eye(4)
    leaning[0, 1] = 1e-3  # R^T R - I is 1e-3 off the diagonal, det R is 1: the default tolerance exactly
    assert rigid(leaning[None]).tolist() == [True]


def test_a_mesh_below_pybullet_data_is_named_from_its_last_such_part_on_any_machine():
    from schema.pushlog import below_pybullet_data

    assert below_pybullet_data("/venv/lib/site-packages/pybullet_data/random_urdfs/002/002.obj") == "random_urdfs/002/002.obj"
    assert below_pybullet_data("C:\\envs\\site-packages\\pybullet_data\\duck.obj") == "duck.obj"
    assert below_pybullet_data("/home/me/pybullet_data/copy/pybullet_data/bunny.obj") == "bunny.obj"
    assert below_pybullet_data("/home/me/meshes/part.obj") is None
