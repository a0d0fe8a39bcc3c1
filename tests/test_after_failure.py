"""The after-failure study (pipeline.studies.after_failure): which pushes it reads, and its fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.studies.after_failure import after_failed_pushes, breakdown, brier, fit_power, main, mapped, score, told


def push(trial, policy, p, toppled, action=0):
    return {"trial": trial, "policy": policy, "object_id": "box", "p_topple": p, "toppled": toppled, "action": action}


RUN = [
    push(0, "untried_vi", 0.9, False, 7),
    push(0, "value_iteration", 0.9, False, 7),
    push(0, "untried_vi", 0.6, True, 8),   # after a failure: kept
    push(0, "untried_vi", 0.5, False, 9),  # after a topple: not
    push(1, "untried_vi", 0.2, True, 3),
    push(1, "value_iteration", 0.9, False, 7),
    push(1, "value_iteration", 0.9, False, 7),  # value iteration's, after its own failure: the same push
    push(0, "untried_vi", 0.4, True, 2),   # after trial 0's failed third push
]


def test_only_the_pushes_right_after_a_failure_of_the_same_policy_and_trial():
    assert [r["p_topple"] for r in after_failed_pushes(RUN, "untried_vi")] == [0.6, 0.4]
    assert [r["p_topple"] for r in after_failed_pushes(RUN, "value_iteration")] == [0.9]
    assert after_failed_pushes(RUN, "greedy") == []


def test_the_fit_finds_the_power_that_made_the_outcomes():
    rng = np.random.default_rng(2)
    p = rng.random(20_000)
    toppled = rng.random(len(p)) < p**3
    assert fit_power(p, toppled) == pytest.approx(3.0, abs=0.15)
    assert fit_power(p, rng.random(len(p)) < p) == pytest.approx(1.0, abs=0.1), "honest P keeps k = 1"


def test_the_score_shows_the_trivial_predictors_beside_the_map():
    p, toppled = np.array([0.5, 0.8, 0.1, 0.0]), np.array([False, True, False, False])
    report = score(p, toppled, 2.0, 0.25)
    predictors = report["predictors"]
    assert report["pushes"] == 4 and report["toppled"] == 0.25
    assert predictors["never topples"]["brier"] == 0.25
    assert predictors["constant 0.250"]["brier"] == pytest.approx(0.1875)
    assert predictors["p^2"]["mean"] == pytest.approx((0.25 + 0.64 + 0.01) / 4)
    assert predictors["table P"]["brier"] == pytest.approx(brier(p, toppled)) == pytest.approx((0.25 + 0.04 + 0.01) / 4)


def test_the_breakdown_tells_first_tries_repeats_and_other_pushes_apart():
    untried = breakdown(RUN, "untried_vi", 2.0)
    assert untried["first try"] == {"pushes": 3, "p_topple": pytest.approx((0.9 + 0.5 + 0.2) / 3), "toppled": pytest.approx(1 / 3)}
    assert untried["another push"] == {"pushes": 2, "p_topple": pytest.approx(0.5), "toppled": 1.0, "p^2": pytest.approx(0.26)}
    assert "same push again" not in untried
    assert breakdown(RUN, "value_iteration", 2.0)["same push again"] == {"pushes": 1, "p_topple": 0.9, "toppled": 0.0}


def test_a_client_is_told_the_table_unless_it_reports_its_failures():
    assert told(RUN, "untried_vi", None)["told"] == pytest.approx((0.9 + 0.6 + 0.5 + 0.2 + 0.4) / 5)
    reported = told(RUN, "untried_vi", 2.0)
    assert reported["told"] == pytest.approx((0.9 + 0.36 + 0.5 + 0.2 + 0.16) / 5)
    assert reported["gap"] == pytest.approx(reported["told"] - 3 / 5)


def test_the_command_fits_and_scores(tmp_path, capsys):
    path = tmp_path / "pushes.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in RUN) + "\n")
    assert main(["fit", str(path)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["pushes"] == 2 and 1.0 <= fitted["power"] <= 6.0
    assert main(["score", "--power", "2", str(path)]) == 0, "files after the options too"
    assert json.loads(capsys.readouterr().out)["predictors"]["p^2"]["mean"] == pytest.approx((0.36 + 0.16) / 2)
    gains = tmp_path / "run.json"
    gains.write_text(json.dumps({"policies": {"untried_vi": {"gain_over_max_height": 0.1, "pushes": 5}}}))
    out = tmp_path / "report.json"
    assert main(["report", "--fit", str(path), "--judge", str(path), "--gains", str(gains), "--json", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written == json.loads(capsys.readouterr().out)
    assert written["judged"]["pushes"] == 2 and written["gains"][str(gains)] == {"untried_vi": {"gain_over_max_height": 0.1}}
    assert set(written["told"]["judge"]) == {"re-asking (value_iteration)", "reporting failures (untried_vi)"}
    with pytest.raises(SystemExit) as half:
        main(["report", "--fit", str(path)])
    assert half.value.code == 2
    with pytest.raises(SystemExit) as missing:
        main(["score", str(path)])
    assert missing.value.code == 2
    with pytest.raises(SystemExit) as nothing:
        main(["fit", str(path), "--policy", "greedy"])
    assert nothing.value.code == 2


def test_the_fit_reads_probabilities_rounded_outside_0_1_as_their_clipped_values():
    # As the service does (schema.retry.after_failure): a NaN or complex power would make the
    # least-Brier search return its first power whatever the outcomes say.
    rounded = np.array([-1e-17, 1.0 + 2e-16, 0.5])
    np.testing.assert_allclose(mapped(rounded, 2.1), [0.0, 1.0, 0.5**2.1], rtol=1e-15, atol=0)
    rng = np.random.default_rng(3)
    p = np.append(rng.uniform(0.05, 0.95, 4000), -1e-17)
    toppled = np.append(rng.random(4000) < p[:-1] ** 3.0, False)
    assert fit_power(p, toppled) == pytest.approx(3.0, abs=0.3)
