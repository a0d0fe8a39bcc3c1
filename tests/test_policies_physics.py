"""The policy experiment executed in physics (pipeline.studies.policies_physics): the model's
predicted gain is the exact expectation over the stored transitions, and a small run on a
real (tiny) dataset plays each policy's pushes, re-plans, and logs them in the push-log schema."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as cli
from pipeline.studies import playlog, policies_physics
from pipeline.studies.policy_experiment import ACTION_SPAN, PolicyTables
from schema.pushlog import row_problems
from schema.reader import Dataset
from schema.vocabulary import NO_OP, POLICIES
from tests.test_service import SPARSE_CHOICE_FROM_THE_SIDE


def chain_tables() -> PolicyTables:
    """One object, poses 0, 1, 2 with V_s 0.1, 0.5, 0.9.  Every policy pushes action 7 in pose 0
    (to 1 with 0.6, stays with 0.4) and action 3 in pose 1 (to 2 with 0.5, back to 0 with 0.5);
    pose 2 is not pushed."""
    keys = np.array([0 * ACTION_SPAN + 7, 0 * ACTION_SPAN + 7, 1 * ACTION_SPAN + 3, 1 * ACTION_SPAN + 3], dtype=np.int64)
    probability = np.array([0.4, 0.6, 0.5, 0.5])
    actions = np.array([7, 3, NO_OP])
    return PolicyTables(
        object_ids=["a"], first_pose=np.array([0, 3]), probability=np.full(3, 1 / 3), v_s=np.array([0.1, 0.5, 0.9]),
        actions={p: actions for p in POLICIES}, keys=keys, next_row=np.array([0, 1, 2, 0]), cumulative=np.cumsum(probability),
    )


def test_predicted_values_are_the_exact_expectation_over_the_stored_transitions():
    tables = chain_tables()
    v = tables.v_s
    one = policies_physics.predicted_values(tables, "greedy", 1)
    np.testing.assert_allclose(one, [0.4 * v[0] + 0.6 * v[1], 0.5 * v[2] + 0.5 * v[0], v[2]])
    two = policies_physics.predicted_values(tables, "greedy", 2)
    np.testing.assert_allclose(two, [0.4 * one[0] + 0.6 * one[1], 0.5 * one[2] + 0.5 * one[0], v[2]])
    np.testing.assert_allclose(policies_physics.predicted_values(tables, "greedy", 0), v)


SPARSE_CHOICE_ARGS = tuple(arg for key, value in SPARSE_CHOICE_FROM_THE_SIDE.items() for arg in ("--set", f"{key}={value}"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    directory = tmp_path_factory.mktemp("policies")
    corpus = directory / "corpus.csv"
    corpus.write_text(
        "object_id,source,path,scale,mass\n"
        + "".join(f"random_{n},pybullet_data/random_urdfs,random_urdfs/{n}/{n}.obj,0.015,0.1\n" for n in ("000", "002"))
    )
    out = directory / "dataset"
    # The service tests' planner (40 contacts a pose are as sparse as their 30): one neighbour will do, from the side.
    assert cli(["dataset", "--corpus", str(corpus), "--out", str(out), "--contacts", "40", "--trials", "8",
                "--set", "suction.n_candidates=20", "--set", "suction.n_samples=5", *SPARSE_CHOICE_ARGS,
                "--workers", "1", "--no-progress"]) == 0
    return out


def test_a_small_run_plays_every_policy_and_logs_its_pushes(dataset, tmp_path):
    log = tmp_path / "log"
    report = policies_physics.experiment(dataset, 8, seed=1, workers=1, log=log)
    assert report["played_trials"] == 8 and not report["failed_objects"]
    table = playlog.read_log(log)
    assert all(problem is None for problem in row_problems(table))
    policy_of = (np.asarray(table["push_id"]) // policies_physics.PUSH_STEP_SPAN) % len(POLICIES)
    for index, policy in enumerate(POLICIES):
        r = report["policies"][policy]
        assert r["pushes"] == int((policy_of == index).sum())
        assert r["pushes"] <= 8 * policies_physics.MAX_PUSHES
        for key in ("predicted_topple_rate", "physical_topple_rate"):
            assert r[key] is None or 0.0 <= r[key] <= 1.0
        # The direction classes split the same pushes: counts add up, and so do the rates.
        assert sum(d["pushes"] for d in r["by_direction"]) == r["pushes"]
        for key in ("predicted_topple_rate", "physical_topple_rate"):
            if r["pushes"]:
                parts = sum(d["pushes"] * d[key] for d in r["by_direction"]) / r["pushes"]
                assert parts == pytest.approx(r[key])
        # So do first tries and repeats, and a repeat follows a push of its trial that left the pose.
        assert sum(d["pushes"] for d in r["by_attempt"]) == r["pushes"]
        for key in ("predicted_topple_rate", "physical_topple_rate"):
            if r["pushes"]:
                parts = sum(d["pushes"] * d[key] for d in r["by_attempt"]) / r["pushes"]
                assert parts == pytest.approx(r[key])
    # by_direction classes each push by its own direction in the pose frame, as the dataset stores it.
    from pipeline.studies.validation import direction_classes
    from schema.reader import Dataset

    stored = Dataset.open(dataset)
    u_z = {}
    for object_id in set(table["object_id"].to_pylist()):
        rows = stored.object_rows("actions", object_id, columns=["pose", "action", "direction_z"]).to_pydict()
        u_z.update({(object_id, p, a): z for p, a, z in zip(rows["pose"], rows["action"], rows["direction_z"])})
    keys = list(zip(table["object_id"].to_pylist(), table["start_pose"].to_pylist(), table["action"].to_pylist()))
    for index, policy in enumerate(POLICIES):
        z = np.array([u_z[k] for k, mine in zip(keys, policy_of == index) if mine])
        expected = {name: int(rows.sum()) for name, rows in direction_classes(z) if rows.any()}
        assert {d["direction"]: d["pushes"] for d in report["policies"][policy]["by_direction"]} == expected
    # Every logged push starts where the previous push of its trial and policy ended.
    rows = sorted(table.to_pylist(), key=lambda row: (row["object_id"], row["push_id"]))
    for before, after in itertools.pairwise(rows):
        if before["object_id"] == after["object_id"] and after["push_id"] == before["push_id"] + 1:
            start, end = np.reshape(after["start_transform"], (4, 4)), np.reshape(before["final_transform"], (4, 4))
            np.testing.assert_allclose(start[:3, :3], end[:3, :3], atol=0.02)
    # Same seed, same starts and noise: the same report.
    again = policies_physics.experiment(dataset, 8, seed=1, workers=1)
    assert again["policies"] == report["policies"]


def test_chosen_pushes_are_split_by_the_reports_direction_classes():
    predicted = np.array([0.8, 0.6, 0.5, 0.2, 0.3, 0.4])
    toppled = np.array([1.0, 0.0, 1.0, 0.0, 1.0, 1.0])
    u_z = np.array([-0.9, -0.7, -0.31, -0.3, 0.29, 0.5])  # the bands are closed below: -0.7 oblique, -0.3 side
    rows = {d["direction"]: d for d in policies_physics.topple_rates_by_direction(predicted, toppled, u_z)}
    assert list(rows) == ["from above", "oblique", "side", "from below"]
    assert (rows["from above"]["pushes"], rows["from above"]["predicted_topple_rate"], rows["from above"]["physical_topple_rate"]) == (1, 0.8, 1.0)
    assert rows["oblique"]["pushes"] == 2 and rows["oblique"]["predicted_topple_rate"] == pytest.approx(0.55)
    assert rows["oblique"]["physical_topple_rate"] == 0.5
    assert rows["side"]["pushes"] == 2 and rows["side"]["predicted_topple_rate"] == pytest.approx(0.25)
    assert rows["from below"]["pushes"] == 1
    assert policies_physics.topple_rates_by_direction(np.zeros(0), np.zeros(0), np.zeros(0)) == []


def test_a_missing_dataset_is_a_one_line_error(tmp_path, capsys):
    assert policies_physics.main([str(tmp_path / "nope"), "--trials", "1", "--no-progress"]) == 2
    assert "nope" in capsys.readouterr().err


def test_repeats_of_a_failed_push_are_read_apart_from_first_tries():
    # A trial's pushes: fail, fail (the same push again), topple, then from the new pose fail once.
    assert policies_physics.after_a_failure([False, False, True, False]) == [False, True, True, False]
    assert policies_physics.after_a_failure([True, True]) == [False, False]
    assert policies_physics.after_a_failure([]) == []
    predicted = np.array([0.6, 0.6, 0.6, 0.3])
    toppled = np.array([0.0, 0.0, 1.0, 0.0])
    again = np.array(policies_physics.after_a_failure([False, False, True, False]))
    rows = {d["attempt"]: d for d in policies_physics.topple_rates_by_attempt(predicted, toppled, again)}
    assert (rows["first try"]["pushes"], rows["first try"]["physical_topple_rate"]) == (2, 0.0)
    assert rows["first try"]["predicted_topple_rate"] == pytest.approx(0.45)
    assert (rows["after a failure"]["pushes"], rows["after a failure"]["physical_topple_rate"]) == (2, 0.5)
    assert list(rows) == ["first try", "after a failure"]
    assert [d["attempt"] for d in policies_physics.topple_rates_by_attempt(predicted[:1], toppled[:1], again[:1])] == ["first try"]


def test_a_dataset_built_in_another_venv_finds_pybullets_meshes_in_this_one(dataset, tmp_path):
    # The manifest records the absolute mesh path the build read; a copy of the dataset whose venv lived
    # elsewhere must still be playable here, and only with the very bytes the manifest recorded.
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    here = {}
    for entry in manifest["corpus"]["objects"]:
        here[entry["object_id"]] = Path(entry["path"]).resolve()
        inside = entry["path"].rsplit("/pybullet_data/", 1)[1]
        entry["path"] = f"/another/machine/.venv/lib/python3.11/site-packages/pybullet_data/{inside}"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    ids = sorted(here)
    plans = policies_physics.object_plans(Dataset.open(copy), ids)
    assert {i: Path(plans[i].spec.path).resolve() for i in ids} == here

    manifest["corpus"]["objects"][0]["sha256"] = "0" * 64  # another file under the same name is not the mesh
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(policies_physics.ExperimentError, match="/another/machine/.* is missing or differs"):
        policies_physics.object_plans(Dataset.open(copy), ids)
