"""One object's result as the rows and arrays of its shard (pipeline/build/rows.py), in process.

``build_shard`` runs in the dataset job's workers, where no test of a whole build can look at
it; here it is called directly on small real evaluations (a box, symmetric, with a pose that has
no grasp; a random object, whose poses have no merged copies) and on a hand-edited pose whose
transitions are known, so every table's contract is checked row by row: counts, the status and
policy vocabulary, nulls where the model has NaN, transitions that sum to one, and the shapes
``schema.hdf5`` gives the arrays.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from shapes import box_object, random_object

from pipeline.build.corpus import ObjectSpec
from pipeline.build.rows import ShardError, build_shard
from pipeline.model.config import Config
from pipeline.model.evaluation import evaluate_object
from pipeline.model.outcomes import PolicyChoice
from schema import hdf5, tables
from schema.version import SCHEMA_VERSION
from schema.vocabulary import (
    NO_OP,
    OUTCOME_NO_EDGE,
    OUTCOME_NOT_EVALUATED,
    POLICIES,
    STATUS_FINGER_COLLISION,
    STATUS_NAMES,
    STATUS_OK,
    STATUS_TOO_LOW,
)

SMALL = Config().with_overrides({
    "contacts.n_contacts": 10, "topple.n_trials": 3, "suction.n_candidates": 5, "suction.n_samples": 3,
})
"""A few pushes and trials: an object evaluates in a few hundredths of a second."""
TRIALS = SMALL.topple.trials


def spec_of(object_id: str) -> ObjectSpec:
    return ObjectSpec(object_id=object_id, path=f"/meshes/{object_id}.obj", scale=0.5, mass=0.25,
                      source="test/shapes", sha256="ab" * 32)


@pytest.fixture(scope="module")
def box():
    """(spec, result) of a box: symmetric (merged poses), and one pose without a grasp."""
    result = evaluate_object(box_object(), SMALL)
    assert result.equivalent_transforms is not None and any(s.quality == 0 for s in result.suction)
    return spec_of("box"), result


@pytest.fixture(scope="module")
def lumpy():
    """(spec, result) of a random object: no pose merged (``equivalent_transforms`` None)."""
    result = evaluate_object(random_object(1), SMALL)
    assert result.equivalent_transforms is None
    return spec_of("random_001"), result


def column(table: pa.Table, name: str) -> list:
    return table.column(name).to_pylist()


def floats(table: pa.Table, name: str) -> np.ndarray:
    """A float column with nulls as NaN (to compare with the model's arrays)."""
    return np.array([np.nan if v is None else v for v in column(table, name)], dtype=np.float64)


def assert_no_nan(table: pa.Table) -> None:
    """Missing values are nulls: no float column of ``table`` holds a NaN."""
    for field in table.schema:
        if pa.types.is_floating(field.type):
            assert pc.sum(pc.is_nan(table.column(field.name))).as_py() in (0, None), field.name


def rows_of(table: pa.Table, pose: int) -> pa.Table:
    return table.filter(pc.equal(table.column("pose"), pose))


@pytest.mark.parametrize("which", ["box", "lumpy"])
def test_counts_and_rows_follow_the_result(which, request):
    spec, result = request.getfixturevalue(which)
    started = time.process_time()
    shard = build_shard(spec, result, TRIALS)
    elapsed = time.process_time() - started
    statuses = [np.asarray(a.status) for a in result.actions]
    n_ok = [int((s == STATUS_OK).sum()) for s in statuses]
    assert shard.object_id == spec.object_id
    assert shard.counts == {
        "poses": len(result.poses),
        "actions": sum(len(s) for s in statuses),
        "ok_actions": sum(n_ok),
        "transitions": shard.rows["transitions"].num_rows,
    }
    assert {name: t.num_rows for name, t in shard.rows.items()} == {
        "objects": 1, "poses": len(result.poses), "actions": shard.counts["actions"], "transitions": shard.counts["transitions"]}
    assert shard.rows["objects"].schema.equals(tables.OBJECTS) and shard.rows["poses"].schema.equals(tables.POSES)
    assert shard.rows["actions"].schema.equals(tables.file_schema(tables.ACTIONS))
    assert shard.rows["transitions"].schema.equals(tables.file_schema(tables.TRANSITIONS))
    poses = shard.rows["poses"]
    assert column(poses, "n_actions") == [len(s) for s in statuses]
    assert column(poses, "n_ok_actions") == n_ok
    for table in shard.rows.values():
        assert_no_nan(table)
    assert shard.attributes == {"schema_version": SCHEMA_VERSION, "object_id": spec.object_id,
                                "n_poses": len(result.poses), "n_trials": TRIALS}
    assert set(result.timings) | {"tables"} == set(shard.timings) and 0 <= shard.timings["tables"] <= elapsed
    assert all(shard.timings[k] == result.timings[k] for k in result.timings)


@pytest.mark.parametrize("which", ["box", "lumpy"])
def test_actions_rows_are_the_pushes_with_nulls_where_the_model_has_nan(which, request):
    spec, result = request.getfixturevalue(which)
    actions = build_shard(spec, result, TRIALS).rows["actions"]
    for i, (pushes, topple, values) in enumerate(zip(result.actions, result.topple, result.values)):
        rows = rows_of(actions, i)
        n = len(pushes.status)
        assert column(rows, "action") == list(range(n)), "every push, in action order"
        assert column(rows, "status") == [STATUS_NAMES[s] for s in pushes.status]
        for prefix, vectors in (("point", pushes.points), ("normal", pushes.normals), ("direction", pushes.directions)):
            stored = np.column_stack([column(rows, f"{prefix}_{a}") for a in "xyz"])
            np.testing.assert_array_equal(stored, vectors, err_msg=prefix)
        assert column(rows, "is_max_height") == [k == pushes.max_height for k in range(n)]
        for name, expected in (("p_topple", topple.p_topple), ("mean_force", topple.mean_force),
                               ("q", values.q), ("greedy", values.greedy)):
            np.testing.assert_array_equal(floats(rows, name), expected, err_msg=name)  # NaN where null
            assert rows.column(name).null_count == int(np.isnan(expected).sum()), name
        ok = np.asarray(pushes.status) == STATUS_OK
        assert rows.column("p_topple").null_count == n - ok.sum(), "only ok pushes have a topple probability"


@pytest.mark.parametrize("which", ["box", "lumpy"])
def test_transitions_of_each_ok_push_sum_to_one(which, request):
    spec, result = request.getfixturevalue(which)
    transitions = build_shard(spec, result, TRIALS).rows["transitions"]
    assert pc.min(transitions.column("probability")).as_py() > 0, "nonzero entries only"
    for i, (pushes, topple) in enumerate(zip(result.actions, result.topple)):
        rows = rows_of(transitions, i)
        ok = np.flatnonzero(np.asarray(pushes.status) == STATUS_OK)
        keys = list(zip(column(rows, "action"), column(rows, "next_pose")))
        assert keys == sorted(keys), "ordered by action, then next pose"
        assert sorted(set(column(rows, "action"))) == ok.tolist(), "every ok push, and only those"
        total = np.zeros(len(pushes.status))
        for (action, target), p in zip(keys, column(rows, "probability")):
            assert p == topple.next_pose[action, target]
            total[action] += p
        np.testing.assert_allclose(total[ok], 1.0, atol=1e-12)
        assert set(column(rows, "next_pose")) <= set(range(len(result.poses)))


def test_pose_rows_carry_the_pose_its_grasp_and_the_policies(box, lumpy):
    for spec, result in (box, lumpy):
        poses = build_shard(spec, result, TRIALS).rows["poses"].to_pylist()
        for row, pose, suction, values in zip(poses, result.poses, result.suction, result.values):
            assert row["object_id"] == spec.object_id and row["pose"] == pose.index
            assert row["probability"] == pose.probability
            assert np.array_equal(np.reshape(row["transform"], (4, 4)), pose.transform), "row-major"
            assert [row[f"down_{a}"] for a in "xyz"] == list(pose.down)
            equivalents = np.reshape(row["equivalent_transforms"], (-1, 4, 4))
            assert np.array_equal(equivalents[0], pose.transform), "its own transform first"
            if result.equivalent_transforms is None:
                assert len(equivalents) == 1
            else:
                assert np.array_equal(equivalents, result.equivalent_transforms[pose.index])
            assert (row["height"], row["com_height"]) == (pose.height, pose.com_height)
            assert row["n_base_edges"] == len(pose.base_edges)
            assert (row["v_s"], row["v_t"]) == (suction.quality, values.value)
            grasp = [row[f"grasp_{v}_{a}"] for v in ("point", "axis") for a in "xyz"]
            if np.isfinite(suction.point).all():
                assert grasp == [*suction.point, *suction.axis]
            else:
                assert grasp == [None] * 6, "no grasp: nulls, not NaN"
            for policy in POLICIES:
                choice = values.policies[policy]
                assert (row[f"{policy}_action"], row[f"{policy}_value"]) == (choice.action, choice.value)
    box_poses = build_shard(*box, TRIALS).rows["poses"]
    assert len(column(box_poses, "equivalent_transforms")[0]) > 1, "the box's merged copies are listed"
    assert box_poses.column("grasp_point_x").null_count > 0, "and one of its poses has no grasp"


def test_object_row_and_arrays_have_the_layout_of_schema_hdf5(box, lumpy):
    for spec, result in (box, lumpy):
        shard = build_shard(spec, result, TRIALS)
        (row,) = shard.rows["objects"].to_pylist()
        assert (row["object_id"], row["source"], row["sha256"], row["scale"]) == (
            spec.object_id, spec.source, spec.sha256, spec.scale)
        assert row["mass"] == result.mass and [row[f"com_{a}"] for a in "xyz"] == list(result.center_mass)
        assert row["n_poses"] == len(result.poses)
        assert (row["n_hull_vertices"], row["n_faces"]) == (len(result.hull_vertices), len(result.hull_faces))
        assert np.array_equal(row["hull_vertices"], result.hull_vertices)
        assert row["repairs"] == [str(r) for r in result.repairs] == []
        repaired = dataclasses.replace(result, repairs=["merged 4 duplicate vertices", "closed 1 hole"])
        (row,) = build_shard(spec, repaired, TRIALS).rows["objects"].to_pylist()
        assert row["repairs"] == ["merged 4 duplicate vertices", "closed 1 hole"]

        sizes: dict[str, int] = {"T": TRIALS}
        assert set(shard.object_arrays) == {s.name for s in hdf5.OBJECT_ARRAYS}
        for spec_ in hdf5.OBJECT_ARRAYS:
            array = np.asarray(shard.object_arrays[spec_.name])
            assert hdf5.check_array(spec_.name, spec_, array.shape, spec_.dtype, sizes) == []
        assert np.array_equal(shard.object_arrays["center_mass"], result.center_mass)
        assert len(shard.pose_arrays) == len(result.poses)
        for arrays, pose, pushes, topple in zip(shard.pose_arrays, result.poses, result.actions, result.topple):
            assert set(arrays) == {s.name for s in hdf5.POSE_ARRAYS}
            pose_sizes = {"T": TRIALS, "A": len(pushes.status), "E": len(pose.base_edges)}
            for spec_ in hdf5.POSE_ARRAYS:
                array = np.asarray(arrays[spec_.name])
                assert hdf5.check_array(spec_.name, spec_, array.shape, spec_.dtype, pose_sizes) == [], spec_.name
            assert np.array_equal(arrays["transform"], pose.transform) and np.array_equal(arrays["down"], pose.down)
            assert np.array_equal(arrays["base_edges"], pose.base_edges)
            for name in ("edge_final_pose", "edge_blocked", "apex_angle"):
                assert np.array_equal(arrays[name], getattr(pose, name)), name
            assert np.array_equal(arrays["outcomes"], topple.outcomes)


def handmade(box, pose=0):
    """The box's result with pose ``pose``'s pushes replaced by four whose outcome is known:

    0 ok, stays or falls onto pose 2 (1/4, 3/4);  1 too low (NaN row);
    2 ok, always falls onto pose 1, the Max-Height push;  3 finger collision, with a row of numbers
    that must not be stored (only ok pushes have transitions).
    """
    spec, result = box
    n = len(result.poses)
    next_pose = np.zeros((4, n))
    next_pose[0, [pose, 2]] = 0.25, 0.75
    next_pose[1] = np.nan
    next_pose[2, 1] = 1.0
    next_pose[3, 1] = 1.0
    nan = np.nan
    pushes = dataclasses.replace(
        result.actions[pose],
        points=np.arange(12.0).reshape(4, 3) / 100, normals=np.tile([1.0, 0, 0], (4, 1)), directions=np.tile([-1.0, 0, 0], (4, 1)),
        status=np.array([STATUS_OK, STATUS_TOO_LOW, STATUS_OK, STATUS_FINGER_COLLISION], dtype=np.int8), max_height=2,
    )
    outcomes = np.full((4, TRIALS), OUTCOME_NOT_EVALUATED, dtype=np.int16)
    outcomes[[0, 2]] = OUTCOME_NO_EDGE
    table = dataclasses.replace(result.topple[pose], next_pose=next_pose, p_topple=np.array([0.75, nan, 1.0, nan]),
                                mean_force=np.array([nan, nan, 2.5, nan]), outcomes=outcomes)
    values = dataclasses.replace(result.values[pose], q=np.array([0.5, nan, 0.25, nan]), greedy=np.array([0.4, nan, 0.2, nan]),
                                 policies={p: PolicyChoice(NO_OP if p == "greedy" else 2, 0.3) for p in POLICIES})

    def swap(items, item):
        return [item if k == pose else x for k, x in enumerate(items)]

    return spec, dataclasses.replace(result, actions=swap(result.actions, pushes), topple=swap(result.topple, table),
                                     values=swap(result.values, values))


def test_a_pose_with_known_outcomes_gives_exactly_its_rows(box):
    spec, result = handmade(box)
    shard = build_shard(spec, result, TRIALS)
    transitions = rows_of(shard.rows["transitions"], 0)
    assert list(zip(column(transitions, "action"), column(transitions, "next_pose"), column(transitions, "probability"))) == [
        (0, 0, 0.25), (0, 2, 0.75), (2, 1, 1.0)]
    actions = rows_of(shard.rows["actions"], 0)
    assert column(actions, "status") == ["ok", "too_low", "ok", "finger_collision"]
    assert column(actions, "is_max_height") == [False, False, True, False]
    assert column(actions, "p_topple") == [0.75, None, 1.0, None]
    assert column(actions, "mean_force") == [None, None, 2.5, None], "an ok push that never topples has no force"
    assert column(actions, "q") == [0.5, None, 0.25, None] and column(actions, "greedy") == [0.4, None, 0.2, None]
    assert column(actions, "point_y") == [0.01, 0.04, 0.07, 0.10]
    pose = shard.rows["poses"].to_pylist()[0]
    assert (pose["n_actions"], pose["n_ok_actions"]) == (4, 2)
    assert (pose["greedy_action"], pose["max_height_action"], pose["value_iteration_action"]) == (NO_OP, 2, 2)
    others = sum(int((np.asarray(a.status) == STATUS_OK).sum()) for a in result.actions[1:])
    assert shard.counts["ok_actions"] == 2 + others
    assert shard.pose_arrays[0]["outcomes"].shape == (4, TRIALS)


def test_a_pose_without_a_max_height_push_marks_none(box):
    spec, result = handmade(box, pose=1)
    result.actions[1] = dataclasses.replace(result.actions[1], max_height=-1)
    actions = rows_of(build_shard(spec, result, TRIALS).rows["actions"], 1)
    assert column(actions, "is_max_height") == [False] * 4


def test_results_that_cannot_be_stored_are_refused_by_name(box):
    spec, result = box

    def refused(match: str, **changes) -> None:
        with pytest.raises(ShardError, match=match):
            build_shard(spec, dataclasses.replace(result, **changes), TRIALS)

    for name in ("actions", "topple", "suction", "values"):
        n = len(result.poses)
        refused(rf"^box: {n - 1} {name} for {n} poses$", **{name: getattr(result, name)[:-1]})
    refused("^box: no stable poses$", poses=[], actions=[], topple=[], suction=[], values=[])

    def edited(field: str, pose: int, **changes):
        items = list(getattr(result, field))
        items[pose] = dataclasses.replace(items[pose], **changes)
        return {field: items}

    a = len(result.actions[1].status)
    refused(rf"^box pose 1: actions.points has shape \({a - 1}, 3\), expected \({a}, 3\)$",
            **edited("actions", 1, points=result.actions[1].points[:-1]))
    refused(r"^box pose 1: actions.normals has shape", **edited("actions", 1, normals=result.actions[1].normals[:, :2]))
    refused(r"^box pose 1: actions.directions has shape", **edited("actions", 1, directions=result.actions[1].directions.T))
    refused(r"^box pose 2: topple.next_pose has shape", **edited("topple", 2, next_pose=result.topple[2].next_pose[:, :-1]))
    refused(rf"^box pose 0: topple.outcomes has shape \({a}, {TRIALS + 1}\), expected \({a}, {TRIALS}\)$",
            **edited("topple", 0, outcomes=np.zeros((a, TRIALS + 1), np.int16)))
    for field, name in (("topple", "p_topple"), ("topple", "mean_force"), ("values", "q"), ("values", "greedy")):
        refused(rf"^box pose 0: {field}.{name} has shape \({a - 1},\), expected \({a},\)$",
                **edited(field, 0, **{name: getattr(getattr(result, field)[0], name)[:-1]}))
    policies = {p: c for p, c in result.values[2].policies.items() if p != "greedy"}
    refused(r"^box pose 2: no choice of policy \['greedy'\]$", **edited("values", 2, policies=policies))
    refused(r"^box pose 2: no choice of policy \['greedy', 'max_height', 'value_iteration'\]$",
            **edited("values", 2, policies={}))
    status = np.array(result.actions[0].status)
    for code in (len(STATUS_NAMES), -1):
        bad = status.copy()
        bad[1] = code
        refused(rf"^box pose 0: unknown action status code {code}$", **edited("actions", 0, status=bad))
    # A policy the vocabulary does not know is not stored, and the rest still is.
    extra = {**result.values[0].policies, "other": PolicyChoice(0, 1.0)}
    poses = build_shard(spec, dataclasses.replace(result, **edited("values", 0, policies=extra)), TRIALS).rows["poses"]
    assert not any(name.startswith("other") for name in poses.column_names)


def test_the_trials_given_are_the_outcome_arrays_width(box):
    """``n_trials`` is the T the outcomes must have and the file's attribute says."""
    spec, result = box
    with pytest.raises(ShardError, match="topple.outcomes has shape"):
        build_shard(spec, result, TRIALS + 1)
    assert build_shard(spec, result, TRIALS).attributes["n_trials"] == TRIALS
