"""The after-failure study (pipeline.studies.after_failure): which pushes it reads, and its fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.studies.after_failure import after_failed_pushes, brier, fit_power, main, score


def push(trial, policy, p, toppled):
    return {"trial": trial, "policy": policy, "object_id": "box", "p_topple": p, "toppled": toppled}


RUN = [
    push(0, "untried_vi", 0.9, False),
    push(0, "value_iteration", 0.9, False),
    push(0, "untried_vi", 0.6, True),   # after a failure: kept
    push(0, "untried_vi", 0.5, False),  # after a topple: not
    push(1, "untried_vi", 0.2, True),
    push(1, "value_iteration", 0.9, False),
    push(1, "value_iteration", 0.9, False),  # value iteration's, after its own failure
    push(0, "untried_vi", 0.4, True),   # after trial 0's failed third push
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


def test_the_command_fits_and_scores(tmp_path, capsys):
    path = tmp_path / "pushes.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in RUN) + "\n")
    assert main(["fit", str(path)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["pushes"] == 2 and 1.0 <= fitted["power"] <= 6.0
    assert main(["score", str(path), "--power", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["predictors"]["p^2"]["mean"] == pytest.approx((0.36 + 0.16) / 2)
    with pytest.raises(SystemExit) as missing:
        main(["score", str(path)])
    assert missing.value.code == 2
    with pytest.raises(SystemExit) as nothing:
        main(["fit", str(path), "--policy", "greedy"])
    assert nothing.value.code == 2
