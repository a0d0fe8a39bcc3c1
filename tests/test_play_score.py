"""play_score: the next-pose Brier of a play by hand, and two datasets' rows compared by push direction."""

import json

import numpy as np
import pytest

from pipeline.studies.play_score import brier, landing_given_topple, main, scored


def test_the_brier_of_a_play_by_hand_counts_the_pose_set_and_outside():
    row = np.array([0.2, 0.5, 0.3])  # start pose 0 stays 0.2
    assert brier(row, 1) == pytest.approx(0.2**2 + 0.5**2 + 0.3**2)  # landed where the row said 0.5
    assert brier(row, 0) == pytest.approx(0.8**2 + 0.5**2 + 0.3**2)  # stayed
    assert brier(row, -1) == pytest.approx(0.2**2 + 0.5**2 + 0.3**2 + 1.0)  # outside the pose set, which the row gives 0
    assert brier(np.array([0.5, 0.3]), -1) == pytest.approx(0.5**2 + 0.3**2 + 0.8**2)  # the row leaves 0.2 outside
    assert brier(np.array([1.0, 0.0]), 0) == 0.0


def test_two_rows_compared_by_direction_clustered_by_object():
    plays = [{"object_id": "a", "pose": 0, "action": 0, "direction": "above", "kind": "tips first", "landed": 1},
             {"object_id": "b", "pose": 0, "action": 1, "direction": "above", "kind": "stays", "landed": 0},
             {"object_id": "a", "pose": 0, "action": 2, "direction": "side", "kind": "tips first", "landed": 1},
             {"object_id": "c", "pose": 0, "action": 0, "direction": "above", "kind": "no contact", "landed": 1}]
    base = lambda o, x, u: np.array([0.5, 0.5])
    variant = lambda o, x, u: np.array([0.0, 1.0]) if u == 0 else np.array([0.5, 0.5])
    out = scored(plays, base, variant)
    above = out["above"]
    assert above["base"]["plays"] == 2  # the untouched start is not the push's
    assert above["base"]["mean"] == pytest.approx(0.5)
    assert above["variant"]["mean"] == pytest.approx((0.0 + 0.5) / 2)
    assert above["variant_minus_base"]["mean"] == pytest.approx(-0.25) and above["variant_minus_base"]["objects"] == 2
    assert out["side"]["variant_minus_base"]["mean"] == 0.0 and "below" not in out
    # The topples into another pose: object a's from above (into pose 1) and from the side.
    given = above["landing_given_topple"]
    assert given["base"]["topples"] == 1 and given["base"]["mean"] == 1.0 and given["variant"]["mean"] == 1.0
    assert landing_given_topple(np.array([0.5, 0.2, 0.3]), 0, 2) == pytest.approx(0.6)
    assert landing_given_topple(np.array([1.0, 0.0]), 0, 1) == 0.0  # a row that never leaves


def test_the_command_reads_plays_against_two_real_datasets_and_refuses_an_unknown_object(dataset, tmp_path, capsys):  # noqa: F811
    from pipeline.studies.landing_trust import pose_columns
    from schema.reader import Dataset

    object_id = min(pose_columns(Dataset.open(dataset), ["n_actions"]))
    plays = tmp_path / "H_a.jsonl"
    plays.write_text(json.dumps({"object_id": object_id, "pose": 0, "action": 0, "direction": "side", "kind": "stays",
                                 "landed": 0}) + "\n")
    out = tmp_path / "score.json"
    assert main([str(dataset), str(dataset), str(plays), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["plays"] == 1 and result["by_direction"]["side"]["variant_minus_base"]["mean"] == 0.0
    assert "difference +0.0000" in capsys.readouterr().out
    plays.write_text(json.dumps({"object_id": "nothing", "pose": 0, "action": 0, "direction": "side", "kind": "stays",
                                 "landed": 0}) + "\n")
    assert main([str(dataset), str(dataset), str(plays)]) == 2
    assert "has no object nothing" in capsys.readouterr().err


from tests.test_policies_physics import dataset  # noqa: F401 (fixture)
