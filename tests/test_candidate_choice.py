"""The candidate-choice study: choosers scored by hand on made-up candidates, then on a real planner log."""

import json

import numpy as np
import pytest

from pipeline.studies.candidate_choice import (
    CHOOSERS,
    CLASSES,
    Candidates,
    candidates,
    direction_class,
    main,
    rank_correlation,
    start_choices,
    summary,
)
from pipeline.studies.landing_trust import TrustError, object_datasets
from tests.test_landing_trust import oracle_log  # noqa: F401 (fixture)
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)


def made_up(plays, row_value, q, u_z, start, objects, topple=None, moved=None) -> Candidates:
    n = len(plays)
    plays = [np.asarray(p, dtype=float) for p in plays]
    return Candidates(np.asarray(start), np.asarray(objects), np.asarray(row_value, dtype=float), np.asarray(q, dtype=float),
                      np.zeros(n) if topple is None else np.asarray(topple, dtype=float), np.asarray(u_z, dtype=float), plays,
                      [p > 0 for p in plays] if moved is None else [np.asarray(m, dtype=bool) for m in moved], {})


def test_direction_classes_split_at_their_limits():
    assert direction_class(np.array([-1.0, -0.31, -0.3, 0.0, 0.29, 0.3, 1.0])).tolist() == [0, 0, 1, 1, 1, 2, 2]
    assert CLASSES[0] == "above" and CLASSES[2] == "below"


def test_rank_correlation_by_hand_with_ties_and_constants():
    assert rank_correlation([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert rank_correlation([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # ranks 0..3 against 0, 2, 1, 3: 1 - 6 * 2 / (4 * 15) = 0.8
    assert rank_correlation([1, 2, 3, 4], [1, 3, 2, 4]) == pytest.approx(0.8)
    # a tie shares its mean rank: x ranks 0, 1.5, 1.5, 3 against 0, 1, 2, 3
    x, y = np.array([0, 1.5, 1.5, 3]), np.arange(4.0)
    assert rank_correlation([5, 7, 7, 9], [1, 2, 3, 4]) == pytest.approx(np.corrcoef(x, y)[0, 1])
    assert np.isnan(rank_correlation([1, 1, 1], [1, 2, 3])) and np.isnan(rank_correlation([1, 2, 3], [0, 0, 0]))


def test_one_start_each_chooser_by_hand():
    # Three candidates: the rows like the first, Q the second, physics the third.
    c = made_up(plays=[[0.2, 0.4, 0.2, 0.4], [0.0, 0.0, 0.6, 0.6], [0.9, 0.7, 0.9, 0.9]], row_value=[0.8, 0.5, 0.6],
                q=[0.1, 0.9, 0.2], u_z=[-0.5, 0.0, 0.0], start=[0, 0, 0], objects=["a"])
    choice = start_choices(c, np.arange(3))
    assert choice["rows"] == pytest.approx(0.3) and choice["q"] == pytest.approx(0.3)
    assert choice["mean"] == pytest.approx((0.3 + 0.3 + 0.85) / 3)
    # even plays (0.2, 0.0 | 0.2, 0.6 | 0.9, 0.9) choose the third, judged on its odd plays (0.8);
    # odd plays (0.4, 0.4 | 0.0, 0.6 | 0.7, 0.9) choose the third, judged on its even plays (0.9).
    assert choice["oracle"] == pytest.approx(0.85)
    assert CLASSES[choice["class"]] == "above"


def test_the_split_halves_keep_a_lucky_play_from_judging_itself():
    # The second push's one great play chooses it on the even half only; the odd half judges it at 0.
    c = made_up(plays=[[0.5, 0.5], [1.0, 0.0]], row_value=[1, 0], q=[1, 0], u_z=[0, 0], start=[0, 0], objects=["a"])
    choice = start_choices(c, np.arange(2))
    assert choice["oracle"] == pytest.approx(0.5 * (0.0 + 0.5))  # even -> push 1 judged 0.0; odd -> push 0 judged 0.5
    assert choice["oracle"] < max(p.mean() for p in c.plays)


def test_summary_pools_starts_splits_the_gap_by_the_rows_choice_and_clusters_by_object():
    # Start 0 (object a): the rows choose from above, 0.2 below the oracle; start 1 (object b): from the side, no gap;
    # start 2 (object b) has one candidate and start 3 (object c) single plays: neither counts.
    c = made_up(plays=[[0.2, 0.2], [0.4, 0.4], [0.5, 0.5], [0.1, 0.1], [0.9, 0.9], [0.3], [0.8]],
                row_value=[0.9, 0.1, 0.9, 0.1, 0.5, 0.9, 0.1], q=[0, 1, 1, 0, 0, 0, 0], u_z=[-0.9, 0, 0, 0, 0, 0, 0],
                start=[0, 0, 1, 1, 2, 3, 3], objects=["a", "b", "b", "c"])
    result = summary(c)
    assert result["starts"] == 2 and result["objects"] == 2 and result["pushes"] == 7
    value = result["value"]
    assert value["rows"]["mean"] == pytest.approx((0.2 + 0.5) / 2) and value["q"]["mean"] == pytest.approx((0.4 + 0.5) / 2)
    assert value["oracle"]["mean"] == pytest.approx((0.4 + 0.5) / 2) and value["mean"]["mean"] == pytest.approx((0.3 + 0.3) / 2)
    gap = result["oracle_minus_rows"]
    assert gap["mean"] == pytest.approx(0.1) and gap["objects"] == 2
    assert gap["se"] == pytest.approx(np.std([0.2, 0.0], ddof=1) / np.sqrt(2))  # one start an object: the ordinary SE
    by = result["by_rows_choice"]
    assert set(by) == {"above", "side"} and by["above"]["mean"] == pytest.approx(0.2) and by["side"]["mean"] == pytest.approx(0.0)
    assert by["above"]["share_of_gap"] == pytest.approx(1.0) and by["above"]["se"] is None  # one object: no SE
    assert set(CHOOSERS) == set(value)


def test_the_rank_correlation_reads_the_rows_p_against_the_topple_rate_within_a_class():
    moved = [[1, 1], [1, 0], [0, 0], [0, 0], [1, 1]]
    c = made_up(plays=[[0.5, 0.5]] * 5, row_value=[0.5] * 5, q=[0] * 5, u_z=[0, 0, 0, 0, -0.9], start=[0] * 5, objects=["a"],
                topple=[0.9, 0.5, 0.1, 0.2, 0.1], moved=moved)
    result = summary(c, min_class_pushes=4)
    side = result["topple_rank_correlation"]["side"]
    assert side["starts"] == 1 and side["mean"] == pytest.approx(rank_correlation([0.9, 0.5, 0.1, 0.2], [1, 0.5, 0, 0]))
    assert "above" not in result["topple_rank_correlation"]  # one push from above, fewer than four
    assert summary(c, min_class_pushes=6)["topple_rank_correlation"] == {}


def test_no_start_to_score_is_an_error():
    c = made_up(plays=[[0.3], [0.8]], row_value=[1, 0], q=[0, 0], u_z=[0, 0], start=[0, 0], objects=["a"])
    with pytest.raises(TrustError, match="two candidates"):
        summary(c)


def test_a_real_log_is_read_against_the_rows_q_and_v_s_the_planner_saw(dataset, oracle_log):  # noqa: F811 (fixtures)
    from pipeline.studies.logreader import read_log
    from pipeline.studies.policy_experiment import ACTION_SPAN
    from pipeline.studies.robust_policy import next_pose_rows
    from schema.reader import Dataset

    log = read_log([oracle_log])
    c = candidates(log, object_datasets([dataset]))
    assert len(c.start) == len(log.pushes) > 0 and not c.rejected
    opened = Dataset.open(dataset)
    poses = opened.table("poses").to_pandas()
    for i, push in enumerate(log.pushes):
        mine = poses[poses.object_id == push.object_id].sort_values("pose")
        v_s = mine.v_s.to_numpy(float)
        pose, action = divmod(push.push_id, ACTION_SPAN)
        row = next_pose_rows(opened, push.object_id, mine.n_actions.astype(int).tolist())[pose][action]
        actions = opened.object_rows("actions", push.object_id).to_pandas()
        assert c.row_value[i] == pytest.approx(row @ v_s) and c.topple[i] == pytest.approx(1 - row[pose])
        assert c.q[i] == pytest.approx(actions[(actions.pose == pose) & (actions.action == action)].q.item())
        assert c.u_z[i] == push.direction[2] and c.objects[c.start[i]] == push.object_id
        expected = [v_s[o] if o >= 0 else 0.0 for o in push.outcomes]
        np.testing.assert_allclose(c.plays[i], expected)
        assert c.moved[i].tolist() == (np.asarray(push.outcomes) != pose).tolist()


def test_the_command_prints_writes_its_record_and_refuses_in_one_line(dataset, oracle_log, tmp_path, capsys):  # noqa: F811
    record = tmp_path / "choice.json"
    assert main([str(oracle_log), "--datasets", str(dataset), "--json", str(record)]) == 0
    out = capsys.readouterr().out
    written = json.loads(record.read_text())
    assert "oracle - rows" in out and written["starts"] > 0 and written["logs"] == [str(oracle_log)]
    assert written["datasets"] == [str(dataset)]
    assert written["oracle_minus_rows"]["mean"] == pytest.approx(written["value"]["oracle"]["mean"] - written["value"]["rows"]["mean"])
    (tmp_path / "file").write_text("x")
    assert main([str(oracle_log), "--datasets", str(dataset), "--json", str(tmp_path / "file" / "r.json")]) == 2
    refused = capsys.readouterr()
    assert refused.err.count("\n") == 1 and refused.out == ""  # refused before the log is read
    with pytest.raises(SystemExit) as exit_:
        main([str(oracle_log)])  # the datasets are required
    assert exit_.value.code == 2 and "--datasets" in capsys.readouterr().err
    assert main([str(oracle_log), "--datasets", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1


def test_the_choosers_read_their_own_candidate_and_the_halves_step_by_two():
    # Six plays each; the rows like the third push, Q the second, and the halves differ from thirds.
    plays = [[0.0] * 6, [0.3, 0.3, 0.3, 0.9, 0.3, 0.3], [0.6, 0.0, 0.6, 0.0, 0.6, 0.0]]
    c = made_up(plays=plays, row_value=[0.1, 0.2, 0.9], q=[0.1, 0.9, 0.2], u_z=[0.5, -0.5, 0.5], start=[0, 0, 0], objects=["a"])
    choice = start_choices(c, np.arange(3))
    assert choice["rows"] == pytest.approx(0.3) and choice["q"] == pytest.approx(0.4) and CLASSES[choice["class"]] == "below"
    # even plays: 0, 0.3, 0.6 -> the third, judged on its odd plays (0); odd plays: 0, 0.5, 0 -> the second, judged on
    # its even plays (0.3)
    assert choice["oracle"] == pytest.approx(0.5 * (0.0 + 0.3))


def test_starts_that_cannot_be_scored_are_skipped_wherever_they_come():
    # Start 0 has one candidate, start 1 single plays; the scored start comes last.
    c = made_up(plays=[[0.5, 0.5], [0.2], [0.9], [0.1, 0.3], [0.7, 0.7]], row_value=[1, 1, 0, 1, 0], q=[0] * 5,
                u_z=[0] * 5, start=[0, 1, 1, 2, 2], objects=["a", "b", "c"])
    result = summary(c)
    assert result["starts"] == 1 and result["value"]["rows"]["mean"] == pytest.approx(0.2)


def test_rank_correlations_are_clustered_by_their_starts_objects():
    # Two objects, a start each, four side pushes: one start ranks perfectly, the other backwards.
    topple = [0.1, 0.2, 0.3, 0.4] * 2
    moved = [[0, 0], [0, 1], [1, 1], [1, 1]] + [[1, 1], [1, 1], [0, 1], [0, 0]]
    c = made_up(plays=[[0.5, 0.5]] * 8, row_value=[0] * 8, q=[0] * 8, u_z=[0] * 8, start=[0] * 4 + [1] * 4, objects=["a", "b"],
                topple=topple, moved=moved)
    side = summary(c)["topple_rank_correlation"]["side"]
    rhos = [rank_correlation(topple[:4], [0, 0.5, 1, 1]), rank_correlation(topple[4:], [1, 1, 0.5, 0])]
    assert side["objects"] == 2 and side["mean"] == pytest.approx(np.mean(rhos))
    assert side["se"] == pytest.approx(np.std(rhos, ddof=1) / np.sqrt(2))


def test_a_constant_ranking_is_nan_without_a_warning():
    with np.errstate(all="raise"):
        assert np.isnan(rank_correlation([0.2, 0.2, 0.2], [0, 1, 1])) and np.isnan(rank_correlation([0.1, 0.2, 0.3], [1, 1, 1]))


def test_the_text_gives_every_chooser_the_gap_by_class_and_the_correlations():
    c = made_up(plays=[[0.2, 0.2], [0.4, 0.4], [0.5, 0.5], [0.1, 0.1], [0.3, 0.3], [0.6, 0.6]], row_value=[0.9, 0.1, 0.9, 0.1, 0.9, 0.1],
                q=[0] * 6, u_z=[-0.9, 0, 0, 0, -0.9, 0], start=[0, 0, 1, 1, 2, 2], objects=["a", "b", "c"])
    result = summary(c)
    result.update(logs=["log"], datasets=["d"])
    from pipeline.studies.candidate_choice import text

    lines = text(result).splitlines()
    assert lines[0].startswith("3 starts with two candidates or more on 3 objects (6 pushes;")
    assert [line.split()[0] for line in lines[1:5]] == list(CHOOSERS)
    assert lines[1] == "  rows    {:.4f} +/- {:.4f}".format(result["value"]["rows"]["mean"], result["value"]["rows"]["se"])
    assert lines[5] == "oracle - rows {:+.4f} +/- {:.4f}; by the direction of the rows' choice:".format(
        result["oracle_minus_rows"]["mean"], result["oracle_minus_rows"]["se"])
    # From above: two objects, 0.2 and 0.3 below the oracle, all of the gap; from the side one object, no SE.
    assert lines[6] == "  above      2 starts: +0.2500 +/- 0.0500, 100% of the gap"
    assert lines[7] == "  side       1 starts: +0.0000, 0% of the gap"
    assert lines[8].startswith("within a start, rank correlation") and len(lines) == 9


def test_pushes_the_datasets_cannot_place_are_counted_and_a_play_outside_is_worth_nothing(dataset, oracle_log):  # noqa: F811
    from dataclasses import replace

    from pipeline.studies.logreader import read_log
    from pipeline.studies.policy_experiment import ACTION_SPAN

    log = read_log([oracle_log])
    datasets = object_datasets([dataset])
    first, second = log.pushes[0], log.pushes[1]
    bad = [replace(first, object_id="elsewhere"), replace(second, object_id="nowhere"),
           replace(first, push_id=first.pose * ACTION_SPAN + ACTION_SPAN - 1),  # no such action
           replace(second, push_id=(second.pose + 1) * ACTION_SPAN),  # another start pose
           replace(first, push_id=first.pose * ACTION_SPAN + n_actions_of(datasets[first.object_id], first))]  # one past the last
    # Plays outside the pose set and in every pose.
    v_s = stored_v_s(datasets[first.object_id], first.object_id)
    outside = replace(first, outcomes=np.array([-1, *range(len(v_s)), -1]))
    c = candidates(replace(log, pushes=[*bad, outside, *log.pushes]), datasets)
    assert c.rejected == {"object in none of the datasets": 2, "push id names no ok push of its start pose": 3}
    assert len(c.start) == len(log.pushes) + 1
    np.testing.assert_allclose(c.plays[0], [0.0, *v_s, 0.0])
    assert c.moved[0].tolist() == [True, *(np.arange(len(v_s)) != first.pose), True]
    # An object whose dataset holds other stable poses than the log's (here none): its pushes set aside, unread.
    twin = log.objects[first.object_id]
    c = candidates(replace(log, pushes=[replace(first, object_id="twin"), *log.pushes], objects={**log.objects, "twin": twin}),
                   {**datasets, "twin": datasets[first.object_id]})
    assert c.rejected == {"the dataset's stable poses differ from the log's": 1} and len(c.start) == len(log.pushes)
    with pytest.raises(TrustError, match="no push of the log"):
        candidates(replace(log, pushes=bad), datasets)


def stored_v_s(opened, object_id) -> np.ndarray:
    """(P,) float, an object's V_s per pose as the dataset stores them."""
    poses = opened.table("poses", columns=["object_id", "pose", "v_s"]).to_pandas()
    return poses[poses.object_id == object_id].sort_values("pose").v_s.to_numpy(float)


def n_actions_of(opened, push) -> int:
    """The number of actions of a logged push's start pose in a dataset."""
    poses = opened.table("poses", columns=["object_id", "pose", "n_actions"]).to_pandas()
    return int(poses[(poses.object_id == push.object_id) & (poses.pose == push.pose)].n_actions.item())


def test_with_no_gap_no_share_of_it_is_given():
    c = made_up(plays=[[0.5, 0.5], [0.1, 0.1]], row_value=[1, 0], q=[0, 0], u_z=[0, 0], start=[0, 0], objects=["a"])
    result = summary(c)
    assert result["oracle_minus_rows"]["mean"] == 0 and result["by_rows_choice"]["side"]["share_of_gap"] is None
    from pipeline.studies.candidate_choice import text

    assert "of the gap" not in text({**result, "logs": [], "datasets": []})
