"""The oracle budget study: its candidates, its physics rows, and its budgets against the model's."""

import itertools

import numpy as np
import pytest

from pipeline.studies.oracle_policy import estimated_topple, landing_row, restricted_budgets, top_pushes
from pipeline.studies.robust_policy import horizon_actions
from schema.vocabulary import NO_OP
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)


def test_top_pushes_are_the_choosable_ok_pushes_of_highest_q_best_first():
    q = np.array([0.5, np.nan, 0.9, 0.7, 0.95, 0.7])
    choosable = np.array([True, True, True, True, False, True])
    assert top_pushes(q, choosable, 3).tolist() == [2, 3, 5]  # 4 is not choosable, 1 not ok; the tie goes to 3
    assert top_pushes(q, choosable, 10).tolist() == [2, 3, 5, 0]
    assert top_pushes(q, ~choosable | np.isnan(q), 2).tolist() == [4]
    # Ties go to the lower id however many there are (numpy's default sort is not stable past 16).
    q = np.random.default_rng(0).integers(0, 3, 300).astype(float)
    top = top_pushes(q, np.ones(300, dtype=bool), 150)
    assert np.all(np.diff(q[top]) <= 0) and all(a < b for a, b in itertools.pairwise(top) if q[a] == q[b])


def test_landing_row_counts_outside_as_staying_and_sums_to_one():
    row = landing_row(np.array([2, 2, 0, -1, 1, 2, 2, 2]), pose=1, n_poses=4)
    assert row.tolist() == [1 / 8, 2 / 8, 5 / 8, 0.0]
    # The estimate's P(topple) is the same reading: everything but staying (or leaving the set).
    assert estimated_topple(np.array([2, 2, 0, -1, 1, 2, 2, 2]), 1) == pytest.approx(1 - row[1])


def two_pose_world():
    """Pose 0 (V_s 0.2) has three pushes towards pose 1 (V_s 0.9); pose 1 has one push back.

    The model ranks push 0 first (0.8), push 1 second (0.5), push 2 third (0.3); physics
    topples push 0 once in four and push 1 and push 2 every time."""
    v_s = np.array([0.2, 0.9])
    rows = [np.array([[0.2, 0.8], [0.5, 0.5], [0.7, 0.3]]), np.array([[1.0, 0.0]])]
    choosable = [np.ones(3, dtype=bool), np.ones(1, dtype=bool)]
    landed = {0: {0: np.array([0, 0, 1, 0]), 1: np.array([1, 1, 1, 1]), 2: np.array([1, 1, 1, 1])}}
    return v_s, rows, choosable, landed


def test_the_oracle_takes_the_push_physics_topples_and_the_model_budget_the_push_it_believes():
    v_s, rows, choosable, landed = two_pose_world()
    starts = {0: (top_pushes(np.array([0.8, 0.5, 0.3]), choosable[0], 3), np.zeros(0, dtype=np.int64))}
    # One push left (with two, push 0 and then the sure push 1 would be worth as much as push 1 now).
    tables = restricted_budgets(v_s, rows, choosable, starts, landed, (1, 2), max_pushes=1)
    assert tables["candidates_1"][0, 0] == tables["candidates_2"][0, 0] == 0  # the model's favourite
    assert tables["oracle_1"][0, 0] == 0  # the only candidate it knows
    assert tables["oracle_2"][0, 0] == 1  # knows push 1 topples every time; push 2 is not a candidate
    for name, table in tables.items():  # the best pose: grasp
        assert table[0, 1] == NO_OP, name


def test_always_pushes_are_candidates_whatever_k():
    v_s, rows, choosable, landed = two_pose_world()
    starts = {0: (np.array([0]), np.array([2]))}  # only the top push is ranked; push 2 is always there
    tables = restricted_budgets(v_s, rows, choosable, starts, landed, (1,), max_pushes=1)
    assert tables["candidates_1"][0, 0] == 0 and tables["oracle_1"][0, 0] == 2


def test_a_pose_that_topples_into_a_start_pose_is_valued_at_what_the_budget_knows_there():
    """Pose 2 (not a start) can push into start pose 0 or grasp; the model thinks pose 0's best
    push a sure topple to pose 1, physics that it never topples: with two pushes left the model's
    budget pushes from pose 2 (on to pose 0, then pose 1), the oracle grasps."""
    v_s = np.array([0.2, 0.9, 0.5])
    rows = [np.array([[0.0, 1.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])]
    choosable = [np.ones(1, dtype=bool)] * 3
    starts = {0: (np.array([0]), np.zeros(0, dtype=np.int64))}
    landed = {0: {0: np.array([0, 0, 0, 0])}}
    tables = restricted_budgets(v_s, rows, choosable, starts, landed, (1,), max_pushes=2)
    free = horizon_actions(v_s, rows, 2, choosable)
    assert free[0, 2] == 0 and tables["candidates_1"][0, 2] == 0  # the model: via pose 0 to pose 1
    assert tables["oracle_1"][0, 2] == NO_OP  # knowing pose 0's push fails, grasp at 0.5
    assert tables["oracle_1"][0, 0] == NO_OP and tables["candidates_1"][0, 0] == 0


def test_the_model_budget_keeps_to_the_candidates_too():
    v_s, rows, choosable, landed = two_pose_world()
    starts = {0: (np.array([2]), np.zeros(0, dtype=np.int64))}  # the model's favourite, push 0, is not a candidate
    tables = restricted_budgets(v_s, rows, choosable, starts, landed, (1,), max_pushes=1)
    assert tables["candidates_1"][0, 0] == 2 and tables["oracle_1"][0, 0] == 2
    assert horizon_actions(v_s, rows, 1, choosable)[0, 0] == 0


def test_with_every_push_a_candidate_and_physics_agreeing_both_are_the_unrestricted_budget():
    v_s, rows, choosable, _ = two_pose_world()
    # Four plays that land as the model says (0.5 / 0.5 is exact; 0.8 and 0.3 are not, so give
    # the model rows four-play fractions).
    rows = [np.array([[0.25, 0.75], [0.5, 0.5], [0.75, 0.25]]), np.array([[1.0, 0.0]])]
    landed = {0: {0: np.array([0, 1, 1, 1]), 1: np.array([0, 0, 1, 1]), 2: np.array([0, 0, 0, 1])}}
    starts = {0: (top_pushes(np.array([0.8, 0.5, 0.3]), choosable[0], 3), np.zeros(0, dtype=np.int64))}
    tables = restricted_budgets(v_s, rows, choosable, starts, landed, (3,), max_pushes=3)
    free = horizon_actions(v_s, rows, 3, choosable)
    assert np.array_equal(tables["candidates_3"], free) and np.array_equal(tables["oracle_3"], free)


def test_a_small_run_reproduces_the_experiments_policies_and_keeps_the_oracle_to_its_candidates(dataset, tmp_path):  # noqa: F811
    from pipeline.studies import playlog, policies_physics
    from pipeline.studies.oracle_policy import experiment
    from pipeline.studies.policy_experiment import ACTION_SPAN
    from schema.pushlog import row_problems

    report, pushes, landed = experiment(dataset, 24, seed=1, repeats=2, ks=(1, 2), workers=1, log=tmp_path / "log")
    assert not report["failed_objects"] and report["useful_trials"] > 0
    assert report["estimate_plays"] > 0 and report["estimate_plays"] % 2 == 0
    # The estimate's plays as a push log: one row per play, each push's repeats under its id.
    table = playlog.read_log(tmp_path / "log").to_pydict()
    assert len(table["push_id"]) == report["estimate_plays"]
    assert all(problem is None for problem in row_problems(playlog.read_log(tmp_path / "log")))
    logged: dict[tuple, list[int]] = {}
    for object_id, push_id, pose, action, repeat in zip(table["object_id"], table["push_id"], table["start_pose"],
                                                        table["action"], table["repeat"]):
        assert (pose, action) == (push_id // ACTION_SPAN, push_id % ACTION_SPAN)
        logged.setdefault((object_id, pose, action), []).append(repeat)
    assert logged == {(o, p, a): [0, 1] for o, poses in landed.items() for p, actions in poses.items() for a in actions}
    # Each play's landing is filed under its own push: the logged final pose settles where the estimate says.
    from pipeline.model.config import Config
    from pipeline.model.evaluation import load_object
    from pipeline.model.poses import settle, stable_poses
    from pipeline.studies.robust_policy import horizon_actions, next_pose_rows, read_candidates
    from schema import horizon
    from schema.reader import Dataset

    data = Dataset.open(dataset)
    config = Config.from_dict(data.manifest.parameters.model_dump())
    plans = policies_physics.object_plans(data, sorted(landed))
    for object_id, poses in landed.items():
        obj = load_object(plans[object_id].spec, config)
        pose_set = stable_poses(obj, config.poses)
        for i in np.flatnonzero(np.array(table["object_id"]) == object_id):
            final = np.reshape(table["final_transform"][i], (4, 4))
            assert settle(pose_set, obj, final[:3, :3]) == poses[table["start_pose"][i]][table["action"][i]][
                table["repeat"][i]]
        # The pushes always among a start pose's candidates: Max-Height's, value iteration's, the budget's first.
        candidates = read_candidates(data, object_id)
        rows = next_pose_rows(data, object_id, [len(c.q) for c in candidates])
        choosable = [horizon.choosable_pushes(c.directions[:, 2], config.mdp.min_direction_z) for c in candidates]
        budget = horizon_actions(plans[object_id].v_s, rows, 3, choosable)
        for pose, actions in poses.items():
            always = {int(plans[object_id].actions[p][pose]) for p in ("max_height", "value_iteration")} | {int(budget[0, pose])}
            assert always - {NO_OP} <= set(actions), (object_id, pose)
    reference = policies_physics.experiment(dataset, 24, seed=1, workers=1)
    for policy in ("max_height", "value_iteration"):  # common random numbers: the same pushes, the same outcomes
        assert report["policies"][policy]["physical_gain_useful"] == pytest.approx(
            reference["policies"][policy]["physical_gain_useful"])
    assert {p.policy for p in pushes} <= set(report["policies"])
    # At an estimated start pose the restricted budgets push only candidates, at most k of them
    # beyond the pushes always there (Max-Height's, value iteration's, the budget's first).
    for k in (1, 2):
        for kind in ("candidates", "oracle"):
            at_starts = [p for p in pushes if p.policy == f"{kind}_{k}" and p.pose in landed[p.object_id]]
            assert at_starts and all(p.action in landed[p.object_id][p.pose] for p in at_starts)
            assert report["policies"][f"{kind}_{k}"]["estimated_pushes"] == len(at_starts)
    assert all(len(actions) <= 2 + 3 for poses in landed.values() for actions in poses.values())
    assert all(len(plays) == 2 for poses in landed.values() for actions in poses.values() for plays in actions.values())
    again, _, landed_again = experiment(dataset, 24, seed=1, repeats=2, ks=(1, 2), workers=2)
    for policy, r in report["policies"].items():  # the estimate's own stream: the same for any worker count
        assert again["policies"][policy] == r, policy
    assert {o: {p: {a: v.tolist() for a, v in x.items()} for p, x in poses.items()} for o, poses in landed.items()} == \
        {o: {p: {a: v.tolist() for a, v in x.items()} for p, x in poses.items()} for o, poses in landed_again.items()}


def test_candidates_are_the_choosable_pushes_unless_every_ok_push_is_asked_for(dataset):  # noqa: F811 (fixture)
    from pipeline.studies.oracle_policy import experiment
    from pipeline.studies.robust_policy import read_candidates
    from schema import horizon
    from schema.reader import Dataset

    data = Dataset.open(dataset)
    min_z = data.manifest.parameters.mdp.min_direction_z
    report, _, landed = experiment(dataset, 8, seed=1, repeats=1, ks=(30,), workers=1)
    wide, _, landed_wide = experiment(dataset, 8, seed=1, repeats=1, ks=(30,), workers=1, every_ok=True)
    assert report["every_ok"] is False and wide["every_ok"] is True
    policies = {"max_height", "value_iteration", "horizon_vi", "candidates_30", "oracle_30"}
    assert set(report["policies"]) == set(wide["policies"]) == policies
    poses_table = data.table("poses", columns=["object_id", "pose", "max_height_action"]).to_pydict()
    max_height = {(o, p): a for o, p, a in zip(poses_table["object_id"], poses_table["pose"], poses_table["max_height_action"])}
    from_above = 0
    for object_id, poses in landed.items():
        candidates = read_candidates(data, object_id)
        for pose, actions in poses.items():
            c = candidates[pose]
            choosable = horizon.choosable_pushes(c.directions[:, 2], min_z)
            ranked = np.argsort(-np.where(np.isfinite(c.q), c.q, -np.inf), kind="stable")
            ranked = ranked[np.isfinite(c.q[ranked])]  # ok pushes only, best first
            wide_top = set(ranked[:30].tolist())
            assert wide_top <= set(landed_wide[object_id][pose])  # the best ok pushes, from above or not
            assert set(ranked[choosable[ranked]][:30].tolist()) <= set(actions)  # the best choosable ones
            from_above += sum(not choosable[a] for a in wide_top)
            # Beyond the ranked ones, only the policies' own pushes; of those only Max-Height's may be unchoosable.
            assert all(choosable[a] or a == max_height[(object_id, pose)] for a in actions), "a push from above"
    assert from_above > 0, "no start pose ranks a push from above among its best: the test tests nothing"


def test_cli_errors_are_one_line(tmp_path, capsys):
    from pipeline.studies.oracle_policy import main

    assert main([str(tmp_path / "missing"), "--trials", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err


def test_an_object_whose_poses_differ_from_the_datasets_is_reported_not_played(dataset):  # noqa: F811 (fixture)
    from dataclasses import replace

    from pipeline.model.config import Config
    from pipeline.studies import policies_physics
    from pipeline.studies.oracle_policy import estimate_object
    from schema.reader import Dataset

    data = Dataset.open(dataset)
    config = Config.from_dict(data.manifest.parameters.model_dump())
    object_id = data.manifest.corpus.objects[0].object_id
    plan = policies_physics.object_plans(data, [object_id])[object_id]
    pushes = {0: (np.array([0]), np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))}
    moved = replace(plan, transforms=plan.transforms + 1e-3)  # another code's pose frames
    _, outcome, log = estimate_object(moved, pushes, config, config, 1, 0)
    assert isinstance(outcome, str) and "stable poses differ" in outcome and log.table.num_rows == 0
    _, outcome, log = estimate_object(plan, pushes, config, config, 1, 0)
    assert set(outcome) == {0} and outcome[0].shape == (1, 1) and log.table.num_rows == 1
