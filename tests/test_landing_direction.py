"""Candidate LD: landings doubted by push direction ((LD.1)), and the fit of its shares on traced plays."""

import json

import numpy as np
import pytest

from pipeline.model.landing_direction import CLASSES, checked_doubts, direction_classes, doubted_rows, mean_landing
from pipeline.studies.candidate_choice import direction_class
from pipeline.studies.landing_direction import fit_class, main, ml_share, play_terms

# Pose 0 of four poses: a push from above (P 0.5, all into pose 2), from the side (P 0.8, into 1 and 3),
# one from below that never topples, one not ok (NaN), and one from the side at the class edge.
ROWS = np.array([[0.5, 0.0, 0.5, 0.0],
                 [0.2, 0.4, 0.0, 0.4],
                 [1.0, 0.0, 0.0, 0.0],
                 [np.nan] * 4,
                 [0.9, 0.1, 0.0, 0.0]])
U_Z = np.array([-0.8, 0.0, 0.9, -0.5, -0.3])


def test_the_classes_split_pushes_as_the_studies_do_at_their_float32_edges():
    u_z = np.array([-1.0, -0.7, -0.30000001, -0.3, -0.29999, 0.0, 0.29999, 0.3, 0.30000001, 1.0])
    np.testing.assert_array_equal(direction_classes(u_z), direction_class(u_z))
    assert direction_classes(U_Z).tolist() == [0, 1, 2, 0, 1]
    assert CLASSES == ("above", "side", "below")


def test_the_mean_landing_is_over_the_pushes_that_leave_each_given_a_topple():
    landing, leaving, mean = mean_landing(ROWS, 0)
    np.testing.assert_allclose(leaving, [0.5, 0.8, 0.0, 0.0, 0.1])
    np.testing.assert_allclose(landing[0], [0, 0, 1, 0])
    np.testing.assert_allclose(landing[1], [0, 0.5, 0, 0.5])
    assert not landing[2].any() and not landing[3].any()
    np.testing.assert_allclose(mean, np.mean([[0, 0, 1, 0], [0, 0.5, 0, 0.5], [0, 1, 0, 0]], axis=0))
    assert mean.sum() == pytest.approx(1.0)
    assert not mean_landing(ROWS[2:4], 0)[2].any()  # nothing leaves: no mean landing


def test_doubted_rows_move_each_class_share_to_the_mean_landing_and_keep_every_stay():
    mean = mean_landing(ROWS, 0)[2]
    doubted = doubted_rows(ROWS, 0, U_Z, (0.5, 0.25, 1.0))
    # (LD.1) by hand: above moves half, the side a quarter; the stays (P(topple)) never move.
    np.testing.assert_allclose(doubted[0], [0.5, *(0.5 * (0.5 * np.array([0, 1, 0]) + 0.5 * mean[1:]))])
    np.testing.assert_allclose(doubted[1], [0.2, *(0.8 * (0.75 * np.array([0.5, 0, 0.5]) + 0.25 * mean[1:]))])
    np.testing.assert_allclose(doubted[4], [0.9, *(0.1 * (0.75 * np.array([1, 0, 0]) + 0.25 * mean[1:]))])
    np.testing.assert_array_equal(doubted[2], ROWS[2])  # nothing leaves: kept, whatever its class's share
    assert np.isnan(doubted[3]).all()  # not ok: kept NaN
    np.testing.assert_allclose(np.nansum(doubted, axis=1), np.nansum(ROWS, axis=1))
    np.testing.assert_array_equal(doubted[:, 0], ROWS[:, 0])
    # Every share 0: the rows themselves; a share of 1: the mean landing at the push's own P(topple).
    assert doubted_rows(ROWS, 0, U_Z, (0, 0, 0)) is ROWS
    np.testing.assert_allclose(doubted_rows(ROWS, 0, U_Z, (1, 1, 1))[1, 1:], 0.8 * mean[1:])
    # Another start pose: its own stay and mean.
    other = doubted_rows(ROWS[:3], 1, U_Z[:3], (1, 0, 0))
    np.testing.assert_array_equal(other[:, 1], ROWS[:3, 1])


def test_doubted_shares_are_three_numbers_in_the_unit_interval():
    np.testing.assert_array_equal(checked_doubts([0, 0.5, 1]), [0, 0.5, 1])
    for bad in ([0.5, 0.5], [0, 0, 1.01], [-0.1, 0, 0], [np.nan, 0, 0]):
        with pytest.raises(ValueError, match="the doubted shares are 3 numbers in \\[0, 1\\], one per push direction"):
            checked_doubts(bad)
    with pytest.raises(ValueError) as refused:
        checked_doubts([0.5, 0.5])
    assert str(refused.value).endswith("(above, side, below); got [0.5, 0.5]")  # what they are for, and what came


def test_rows_given_as_integers_are_doubted_in_floats():
    # Rows of whole counts (a push that always leaves, into pose 1 or 2): the doubt's shares are fractions, not
    # truncated to the input's integer type.
    rows = np.array([[0, 1, 0], [0, 0, 1]])
    doubted = doubted_rows(rows, 0, np.array([-0.9, 0.0]), (0.5, 0.5, 0.5))
    np.testing.assert_allclose(doubted, [[0, 0.75, 0.25], [0, 0.25, 0.75]])
    landing, leaving, mean = mean_landing(rows, 0)
    np.testing.assert_allclose(landing, rows)
    np.testing.assert_allclose(mean, [0, 0.5, 0.5])
    np.testing.assert_array_equal(leaving, [1.0, 1.0])


def test_the_maximum_likelihood_share_by_hand():
    # n1 topples the push's own landing names (own 1, mean 0) and n2 only the mean names: lambda = n2 / (n1 + n2).
    for n1, n2 in ((1, 1), (3, 1), (1, 4)):
        share = ml_share(np.r_[np.ones(n1), np.zeros(n2)], np.r_[np.zeros(n1), np.ones(n2)])
        assert share == pytest.approx(n2 / (n1 + n2), abs=1e-8)
    # The mean never names a landing better: no share; only the mean names them: all of it.
    assert ml_share(np.array([0.9, 0.6]), np.array([0.1, 0.6])) == 0.0
    assert ml_share(np.array([0.0, 0.2]), np.array([0.5, 0.3])) == 1.0
    assert ml_share(np.zeros(0), np.zeros(0)) == 0.0
    # An interior maximum: the score's slope is zero there.
    own, mean = np.array([0.8, 0.1, 0.5]), np.array([0.2, 0.6, 0.4])
    share = ml_share(own, mean)
    assert 0 < share < 1
    assert np.sum((mean - own) / ((1 - share) * own + share * mean)) == pytest.approx(0.0, abs=1e-6)


def terms(object_id, direction, own, mean, value_own=0.5, value_mean=0.3, value_landed=0.2):
    return {"object_id": object_id, "direction": direction, "own": own, "mean": mean, "value_own": value_own,
            "value_mean": value_mean, "value_landed": value_landed}


def test_a_class_fit_counts_only_informative_topples_and_reports_the_value_shift():
    found = fit_class([terms("a", "above", 1.0, 0.0), terms("b", "above", 0.0, 1.0), terms("c", "above", 0.0, 0.0)])
    assert found["share"] == pytest.approx(0.5, abs=1e-8)
    assert found["topples"] == 3 and found["informative"] == 2 and found["objects"] == 3
    assert found["value_landed_minus_expected"]["rows"]["mean"] == pytest.approx(0.2 - 0.5)
    assert found["value_landed_minus_expected"]["doubted"]["mean"] == pytest.approx(0.2 - (0.5 * 0.5 + 0.5 * 0.3))
    assert found["log_score"]["rows"] == -np.inf and found["log_score"]["doubted"] == pytest.approx(np.log(0.5))
    low, high = found["share_95"]
    assert 0.0 <= low <= found["share"] <= high <= 1.0
    empty = fit_class([])
    assert empty["share"] == 0.0 and empty["share_95"] is None and empty["log_score"]["rows"] is None


def test_play_terms_read_each_pushed_topple_that_landed_in_the_pose_set():
    rows = {"o": [ROWS, ROWS[:, [1, 0, 2, 3]]]}
    values = {"o": np.array([0.1, 0.2, 0.9, 0.4])}
    play = {"object_id": "o", "pose": 0, "action": 1, "direction": "side", "toppled": True, "kind": "tips first", "landed": 3}
    found = play_terms([play, {**play, "toppled": False, "landed": 0}, {**play, "landed": -1},
                        {**play, "kind": "no contact"}, {**play, "action": 2, "landed": 1}], rows, values)
    assert len(found) == 1  # stayed, left the pose set, untouched, or a push its rows never topple: none count
    mean = mean_landing(ROWS, 0)[2]
    assert found[0]["own"] == pytest.approx(0.5) and found[0]["mean"] == pytest.approx(mean[3])
    assert found[0]["value_own"] == pytest.approx(0.5 * 0.2 + 0.5 * 0.4)
    assert found[0]["value_mean"] == pytest.approx(mean @ values["o"]) and found[0]["value_landed"] == 0.4


def test_the_command_fits_plays_of_a_real_dataset_and_refuses_unknown_objects(dataset, tmp_path, capsys):  # noqa: F811
    from pipeline.studies.landing_trust import pose_columns
    from schema.reader import Dataset

    object_id = min(pose_columns(Dataset.open(dataset), ["n_actions"]))
    plays = tmp_path / "plays.jsonl"
    plays.write_text(json.dumps({"object_id": object_id, "pose": 0, "action": 0, "direction": "side", "toppled": False,
                                 "kind": "stays", "landed": 0}) + "\n")
    out = tmp_path / "fit.json"
    assert main([str(dataset), str(plays), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["plays"] == 1 and result["shares"] == [0.0, 0.0, 0.0]
    assert "--landing-direction 0.00 0.00 0.00" in capsys.readouterr().out
    plays.write_text(json.dumps({"object_id": "no_such_object", "pose": 0, "action": 0, "direction": "side",
                                 "toppled": True, "kind": "tips first", "landed": 1}) + "\n")
    assert main([str(dataset), str(plays)]) == 2
    assert "the plays name objects the dataset does not have: no_such_object" in capsys.readouterr().err
    plays.write_text(json.dumps({"object_id": object_id, "pose": 0, "action": 0, "toppled": True, "kind": "tips first"}) + "\n")
    assert main([str(dataset), str(plays)]) == 2
    assert "a play lacks the field 'landed'" in capsys.readouterr().err
    assert main([str(dataset), str(tmp_path / "none.jsonl")]) == 2
    assert "none.jsonl" in capsys.readouterr().err


from tests.test_policies_physics import dataset  # noqa: F401 (fixture)
