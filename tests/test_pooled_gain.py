"""A policy's gain pooled over runs, with its standard error over runs, over trials and by object."""

import json
import warnings

import numpy as np
import pytest

from pipeline.studies.paired_trials import PairingError
from pipeline.studies.pooled_gain import clustered_mean_se, main, pool
from tests.test_paired_trials import record, write
from tests.test_policies_physics import dataset  # noqa: F401 (fixture)


def gains(vi: float, mh: float = 0.0) -> dict:
    return {"value_iteration": vi, "max_height": mh}


def test_one_value_a_cluster_is_the_ordinary_standard_error():
    values = np.array([0.3, -0.1, 0.25, 0.0, 0.7])
    mean, se, groups = clustered_mean_se(values, ["a", "b", "c", "d", "e"])
    assert groups == 5 and mean == pytest.approx(values.mean())
    assert se == pytest.approx(values.std(ddof=1) / np.sqrt(5))
    # Two clusters are the fewest with a spread: the SE of two values is half their distance.
    assert clustered_mean_se(np.array([0.3, -0.1]), ["a", "b"])[1:] == (pytest.approx(0.2), 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no 0/0 on the way
        mean, se, groups = clustered_mean_se(np.zeros(0), [])
    assert np.isnan(mean) and np.isnan(se) and groups == 0, "no values: no mean"


def test_clusters_of_equal_values_count_as_one_draw_each():
    # Four objects, three identical trials each: twelve trials carry four objects' worth of evidence,
    # so the SE is that of the four objects' means, not of twelve independent values.
    per_object = np.array([0.1, 0.5, -0.2, 0.4])
    values = np.repeat(per_object, 3)
    mean, se, groups = clustered_mean_se(values, [c for c in "wxyz" for _ in range(3)])
    assert groups == 4 and mean == pytest.approx(per_object.mean())
    assert se == pytest.approx(per_object.std(ddof=1) / 2)
    assert se > values.std(ddof=1) / np.sqrt(12)
    # Unequal sizes weigh each object by its trials: the mean is the trials' mean.
    mean, _, _ = clustered_mean_se(np.array([1.0, 1.0, 1.0, 0.0]), ["a", "a", "a", "b"])
    assert mean == pytest.approx(0.75)
    assert np.isnan(clustered_mean_se(np.array([1.0, 2.0]), ["a", "a"])[1]), "one object: no spread to measure"


def test_runs_pool_their_counted_trials_and_cluster_by_object_across_runs(tmp_path):
    first = write(tmp_path / "s1.jsonl", [record(0, 3, gains(0.5, 0.1), object_id="a"), record(1, 4, gains(0.2), object_id="b"),
                                          record(2, 5, None, object_id="c"), record(3, 6, gains(0.9), useful=False, object_id="c")])
    second = write(tmp_path / "s2.jsonl", [record(0, 3, gains(0.6, 0.2), object_id="a"), record(1, 8, gains(0.0), object_id="b"),
                                           record(2, 5, gains(0.3, 0.3), object_id="c")])
    result = pool([first, second])
    differences = np.array([0.4, 0.2, 0.4, 0.0, 0.0])
    assert result["trials"] == 5 and result["objects"] == 3, "trial 2 of s1 left the set; trial 3 was not useful"
    assert result["pooled"] == pytest.approx(differences.mean())
    assert [r["trials"] for r in result["runs"]] == [2, 3] and [r["file"] for r in result["runs"]] == [first, second]
    assert [r["mean"] for r in result["runs"]] == pytest.approx([0.3, 0.4 / 3])
    assert result["runs_se"] == pytest.approx(np.std([0.3, 0.4 / 3], ddof=1) / np.sqrt(2))
    assert result["trials_se"] == pytest.approx(differences.std(ddof=1) / np.sqrt(5))
    sums, counts = np.array([0.8, 0.2, 0.0]), np.array([2, 2, 1])
    expected = np.sqrt(3 / 2 * np.sum((sums - differences.mean() * counts) ** 2)) / 5
    assert result["objects_se"] == pytest.approx(expected)
    low, high = result["objects_interval_95"]
    assert (low + high) / 2 == pytest.approx(result["pooled"]) and high - low == pytest.approx(2 * 1.959964 * expected)
    assert pool([first, second], policy="max_height", baseline="value_iteration")["pooled"] == pytest.approx(-differences.mean())


def test_never_pushing_pools_as_zero_gain_on_every_counted_trial(tmp_path):
    run = write(tmp_path / "s.jsonl", [record(0, 3, gains(0.5, 0.1), object_id="a"), record(1, 4, gains(0.2, -0.3), object_id="b"),
                                       record(2, 5, gains(0.9, 0.4), useful=False, object_id="c"),
                                       record(3, 6, gains(0.0, 0.2), object_id="c")])
    never = pool([run], "never_push", "max_height")
    height = pool([run], "max_height", "never_push")
    assert never["trials"] == 3 and never["pooled"] == pytest.approx(-np.mean([0.1, -0.3, 0.2]))
    assert height["pooled"] == pytest.approx(-never["pooled"]) and height["objects_se"] == pytest.approx(never["objects_se"])
    # Against value iteration: minus its gain, trial by trial.
    assert pool([run], "never_push", "value_iteration")["pooled"] == pytest.approx(-np.mean([0.5, 0.2, 0.0]))


def test_the_pool_of_a_real_run_is_the_runs_reported_gain(dataset, tmp_path, capsys):  # noqa: F811
    from pipeline.studies.robust_policy import main as study

    out = tmp_path / "trials.jsonl"
    assert study([str(dataset), "--trials", "8", "--seed", "1", "--json", str(tmp_path / "r.json"), "--trials-out", str(out)]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    capsys.readouterr()
    assert main([str(out), str(out), "--policy", "belief_horizon_vi", "--json", str(tmp_path / "p.json")]) == 0
    result = json.loads((tmp_path / "p.json").read_text())
    assert result["pooled"] == pytest.approx(report["policies"]["belief_horizon_vi"]["gain_over_max_height"])
    assert result["trials"] == 2 * report["useful_trials"] and result["runs_se"] == pytest.approx(0.0)
    assert capsys.readouterr().out.startswith(f"belief_horizon_vi minus max_height, pooled over {result['trials']} useful trials of 2 runs")


def test_what_cannot_be_pooled_is_refused_in_one_line(tmp_path, capsys):
    good = write(tmp_path / "good.jsonl", [record(0, 3, gains(0.5)), record(1, 4, gains(0.1), object_id="cup")])
    no_object = write(tmp_path / "old.jsonl", [record(0, 3, gains(0.5), object_id=None)])
    with pytest.raises(PairingError, match="old.jsonl: trial 0 names no object_id"):
        pool([good, no_object])
    with pytest.raises(PairingError, match="trial 0 has no policy 'aware_vi'; it played max_height, value_iteration"):
        pool([good], policy="aware_vi")
    one = write(tmp_path / "one.jsonl", [record(0, 3, gains(0.5)), record(1, 4, gains(0.1), useful=False)])
    with pytest.raises(PairingError, match="1 counted trial"):
        pool([one])
    with pytest.raises(PairingError, match=r"0 counted trial\(s\) in 0 run\(s\)"):
        pool([])
    for args, message in [([str(tmp_path / "missing.jsonl")], "missing.jsonl: No such file"),
                          ([good, "--json", str(tmp_path / "good.jsonl" / "p.json")], "good.jsonl is not a directory")]:
        assert main(args) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


def test_a_run_without_counted_trials_is_listed_but_has_no_mean_and_the_text_shows_the_record(tmp_path, capsys):
    good = write(tmp_path / "good.jsonl", [record(0, 3, gains(0.5, 0.1), object_id="a"), record(1, 4, gains(0.1), object_id="b")])
    idle = write(tmp_path / "idle.jsonl", [record(0, 3, gains(0.9), useful=False), record(1, 4, None)])
    assert main([good, idle, "--json", str(tmp_path / "p.json")]) == 0, "two counted trials are the fewest that pool"
    result = json.loads((tmp_path / "p.json").read_text())
    assert (result["policy"], result["baseline"]) == ("value_iteration", "max_height"), "the defaults"
    assert [(r["trials"], r["mean"]) for r in result["runs"]] == [(2, pytest.approx(0.25)), (0, None)]
    assert result["runs_mean"] == pytest.approx(0.25) and result["runs_se"] is None, "one run with a mean: no spread over runs"
    # The text reports the record's numbers, a dash where there is none.
    low, high = result["objects_interval_95"]
    lines = capsys.readouterr().out.splitlines()
    assert lines[1] == (f"  SE over runs - (the runs' mean {result['runs_mean']:+.4f}); over trials {result['trials_se']:.4f}; "
                        f"clustered by object {result['objects_se']:.4f}, 95 % [{low:+.4f}, {high:+.4f}]")
    assert [line.split() for line in lines[2:]] == [["2", "trials", f"{0.25:+.4f}", "good.jsonl"], ["0", "trials", "-", "idle.jsonl"]]
    assert main([good, good, "--policy", "max_height", "--baseline", "value_iteration", "--json", str(tmp_path / "p.json")]) == 0
    result = json.loads((tmp_path / "p.json").read_text())
    assert result["pooled"] == pytest.approx(-0.25) and result["runs_se"] == 0
    assert f"  SE over runs {0:.4f} (the runs' mean {-0.25:+.4f})" in capsys.readouterr().out


def test_help_names_the_default_policies(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")  # argparse wraps to the terminal width
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--policy POLICY (default: value_iteration; never_push: 0 on every trial)" in text and "--baseline BASELINE (default: max_height)" in text


def test_one_object_has_no_clustered_se_and_the_record_stays_json(tmp_path, capsys):
    # Two trials of one object: an SE over trials, none between objects; the record is strict JSON
    # (null, not NaN) and the text shows a dash and no interval.
    one = write(tmp_path / "one.jsonl", [record(0, 3, gains(0.5, 0.1)), record(1, 4, gains(0.2, 0.1))])
    assert main([one, "--json", str(tmp_path / "p.json")]) == 0
    text = (tmp_path / "p.json").read_text()
    result = json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} in the record"))
    assert result["objects"] == 1 and result["objects_se"] is None and result["objects_interval_95"] is None
    assert result["trials_se"] == pytest.approx(0.15)
    out = capsys.readouterr().out
    assert "clustered by object -" in out and "nan" not in out and "95 %" not in out
