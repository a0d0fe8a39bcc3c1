"""Two runs of the policy study paired trial by trial: the records a run writes and how they pair."""

import json

import numpy as np
import pytest

from pipeline.studies.paired_trials import PairingError, compare, main, paired_gains
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)


def record(trial: int, start: int, gains: dict | None, useful: bool = True, object_id: str = "box") -> dict:
    return {"trial": trial, "start": start, "object": 0, "object_id": object_id, "outside": gains is None, "useful": useful,
            "gains": gains}


def write(path, records) -> str:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return str(path)


def test_the_records_reproduce_the_reports_gains_and_a_run_pairs_with_itself_at_zero(dataset, tmp_path, capsys):  # noqa: F811
    from pipeline.studies.robust_policy import main as study

    out = tmp_path / "trials.jsonl"
    assert study([str(dataset), "--trials", "8", "--seed", "1", "--json", str(tmp_path / "r.json"), "--trials-out", str(out)]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert "trial_records" not in report and report["trials"] == 8, "the records go to their own file"
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["trial"] for r in records] == list(range(8))
    counted = [r for r in records if r["useful"] and not r["outside"]]
    assert len(counted) == report["useful_trials"] > 0
    for policy in ("value_iteration", "belief_horizon_vi"):
        gains = np.array([r["gains"][policy] - r["gains"]["max_height"] for r in counted])
        assert np.isclose(gains.mean(), report["policies"][policy]["gain_over_max_height"])
        assert np.isclose(np.mean([r["gains"][policy] for r in counted]), report["policies"][policy]["physical_gain_useful"])
    capsys.readouterr()
    assert main([str(out), str(out), "--policies", "value_iteration"]) == 0
    assert "B minus A +0.0000" in capsys.readouterr().out
    # Without --trials-out the study writes its report and no records.
    assert study([str(dataset), "--trials", "8", "--seed", "1", "--json", str(tmp_path / "plain.json")]) == 0
    assert json.loads((tmp_path / "plain.json").read_text())["policies"] == report["policies"]


def test_a_pair_counts_the_trials_either_run_calls_useful_and_neither_leaves_outside(tmp_path):
    a = write(tmp_path / "a.jsonl", [record(0, 3, {"vi": 0.5}), record(1, 4, {"vi": 0.1}, useful=False),
                                     record(2, 5, None), record(3, 6, {"vi": 0.2}, useful=False)])
    b = write(tmp_path / "b.jsonl", [record(0, 3, {"vi": 0.7}), record(1, 4, {"vi": 0.4}),
                                     record(2, 5, {"vi": 0.9}), record(3, 6, {"vi": 0.2}, useful=False)])
    from pipeline.studies.paired_trials import read_trials

    gain_a, gain_b = paired_gains(read_trials(a), read_trials(b), "vi")
    assert gain_a.tolist() == [0.5, 0.1] and gain_b.tolist() == [0.7, 0.4], "trial 2 left outside, trial 3 useful in neither"
    result = compare([(a, b), (a, b)], ["vi"])["policies"]["vi"]
    assert result["pairs"][0]["b_minus_a"] == pytest.approx(0.25) and result["pairs"][0]["trials"] == 2
    assert result["runs_mean"] == pytest.approx(0.25) and result["runs_se"] == pytest.approx(0.0)
    assert result["pooled"] == pytest.approx(0.25) and result["trials"] == 4


def test_a_gain_over_a_baseline_pairs_the_difference_of_differences(tmp_path, capsys):
    """Issue 9's measure, value iteration over Max-Height, compared between two runs of the same trials."""
    a = write(tmp_path / "a.jsonl", [record(0, 3, {"vi": 0.5, "mh": 0.3}), record(1, 4, {"vi": 0.1, "mh": 0.2})])
    b = write(tmp_path / "b.jsonl", [record(0, 3, {"vi": 0.7, "mh": 0.2}), record(1, 4, {"vi": 0.4, "mh": 0.4})])
    result = compare([(a, b)], ["vi"], over="mh")
    assert result["over"] == "mh"
    pair = result["policies"]["vi"]["pairs"][0]
    assert pair["a"] == pytest.approx((0.2 - 0.1) / 2) and pair["b"] == pytest.approx((0.5 + 0.0) / 2)
    assert pair["b_minus_a"] == pytest.approx(((0.5 - 0.2) + (0.0 + 0.1)) / 2)
    assert compare([(a, b)], ["mh"], over="mh")["policies"]["mh"]["pooled"] == 0.0
    # Never pushing gains 0 on every trial, though no record holds it: over Max-Height, minus its gain.
    never = compare([(a, b)], ["never_push"], over="mh")["policies"]["never_push"]["pairs"][0]
    assert never["a"] == pytest.approx(-0.25) and never["b"] == pytest.approx(-0.3)
    with pytest.raises(PairingError, match="no policy 'never'"):
        compare([(a, b)], ["vi"], over="never")
    assert main([a, b, "--over", "mh", "--policies", "vi"]) == 0
    assert "B minus A +0.2000" in capsys.readouterr().out


def test_runs_of_other_trials_or_starts_are_refused_in_one_line(tmp_path, capsys):
    a = write(tmp_path / "a.jsonl", [record(0, 3, {"vi": 0.5}), record(1, 4, {"vi": 0.1})])
    other_start = write(tmp_path / "b.jsonl", [record(0, 3, {"vi": 0.5}), record(1, 7, {"vi": 0.1})])
    fewer = write(tmp_path / "c.jsonl", [record(0, 3, {"vi": 0.5})])
    with pytest.raises(PairingError, match="trial 1 starts in pose row 4 of box in one run and 7 of box in the other"):
        compare([(a, other_start)], ["vi"])
    with pytest.raises(PairingError, match="played different trials"):
        compare([(a, fewer)], ["vi"])
    with pytest.raises(PairingError, match="trial 0 has no policy 'mh'; it played vi"):
        compare([(a, a)], ["mh"])
    other_object = write(tmp_path / "d.jsonl", [record(0, 3, {"vi": 0.5}), record(1, 4, {"vi": 0.1}, object_id="cup")])
    with pytest.raises(PairingError, match="trial 1 starts in pose row 4 of box in one run and 4 of cup"):
        compare([(a, other_object)], ["vi"])
    bad = {"not json": "{not json\n",
           "not a trial record (KeyError": json.dumps({"trial": 0, "start": 3}) + "\n",
           "needs each policy's gain": json.dumps(record(0, 3, None) | {"outside": False}) + "\n",
           "trial 0 appears twice": (json.dumps(record(0, 3, {"vi": 0.5})) + "\n") * 2}
    for message, content in bad.items():
        (tmp_path / "bad.jsonl").write_text(content)
        assert main([a, str(tmp_path / "bad.jsonl")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and (message in err or message == "not json" and "line 1: not a trial record" in err)
    assert main([a, a, a]) == 2
    assert "3 files do not make pairs" in capsys.readouterr().err
    assert main([a, str(tmp_path / "missing.jsonl")]) == 2
    assert "missing.jsonl" in capsys.readouterr().err


def test_the_pooled_difference_is_also_clustered_by_object_when_the_records_name_them(tmp_path, capsys):
    from pipeline.studies.pooled_gain import clustered_mean_se

    a = write(tmp_path / "a.jsonl", [record(0, 3, {"vi": 0.5}, object_id="box"), record(1, 4, {"vi": 0.1}, object_id="cup"),
                                     record(2, 5, {"vi": 0.0}, object_id="mug")])
    b = write(tmp_path / "b.jsonl", [record(0, 3, {"vi": 0.7}, object_id="box"), record(1, 4, {"vi": 0.4}, object_id="cup"),
                                     record(2, 5, {"vi": 0.2}, object_id="mug")])
    a2 = write(tmp_path / "a2.jsonl", [record(0, 3, {"vi": 0.2}, object_id="box"), record(1, 9, {"vi": 0.3}, object_id="mug")])
    b2 = write(tmp_path / "b2.jsonl", [record(0, 3, {"vi": 0.2}, object_id="box"), record(1, 9, {"vi": 0.6}, object_id="mug")])
    result = compare([(a, b), (a2, b2)], ["vi"])["policies"]["vi"]
    differences = np.array([0.2, 0.3, 0.2, 0.0, 0.3])
    expected = clustered_mean_se(differences, ["box", "cup", "mug", "box", "mug"])[1]
    assert result["pooled"] == pytest.approx(differences.mean()) and result["pooled_objects_se"] == pytest.approx(expected)
    assert main([a, b, a2, b2, "--policies", "vi"]) == 0
    assert f"+/- {expected:.4f} clustered by object" in capsys.readouterr().out
    # Two objects that a run pairs with itself differ by nothing: an SE of zero, not none.
    assert compare([(a2, a2)], ["vi"])["policies"]["vi"]["pooled_objects_se"] == 0.0
    # Records of one object, or naming none, have no spread between objects to measure.
    same = write(tmp_path / "same.jsonl", [record(0, 3, {"vi": 0.5}), record(1, 4, {"vi": 0.1})])
    assert compare([(same, same)], ["vi"])["policies"]["vi"]["pooled_objects_se"] is None
    unnamed = write(tmp_path / "unnamed.jsonl", [record(0, 3, {"vi": 0.5}, object_id=None), record(1, 4, {"vi": 0.1}, object_id="cup")])
    assert compare([(unnamed, unnamed)], ["vi"])["policies"]["vi"]["pooled_objects_se"] is None
