"""The after-failure study (pipeline.studies.after_failure): which pushes it reads, and its fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.studies.after_failure import (
    after_failed_pushes,
    breakdown,
    brier,
    brier_differences,
    failed_before,
    fit_power,
    fit_slope,
    main,
    mapped,
    read_pushes,
    score,
    slope_power,
    told,
)


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


def test_each_push_after_a_failure_knows_what_failed_in_its_pose():
    run = [
        push(0, "belief_vi", 0.9, False, 1),
        push(0, "belief_vi", 0.2, False, 2),  # after 0.9 failed
        push(0, "belief_vi", 0.7, True, 3),   # after 0.9 and 0.2 failed: topples to a new pose
        push(0, "belief_vi", 0.4, False, 4),  # a first try in the new pose
        push(0, "belief_vi", 0.6, True, 5),   # after 0.4 failed there only
        push(1, "belief_vi", 0.3, False, 6),
        push(1, "greedy", 0.8, False, 6),     # another policy's trial 1: no part of it
        push(1, "belief_vi", 0.5, False, 7),  # after trial 1's 0.3
    ]
    found = failed_before(run, "belief_vi")
    assert [found.get(id(r)) for r in run] == [None, [0.9], [0.9, 0.2], None, [0.4], None, None, [0.3]]
    assert after_failed_pushes(run, "belief_vi") == [run[i] for i in (1, 2, 4, 7)]


def test_the_candidate_slope_tilts_k_about_a_failed_push_of_one_half():
    np.testing.assert_allclose(slope_power(2.1, 2.2, np.array([0.5, 0.9, 0.1, 0.0, 1.0 + 1e-12, -1e-17])),
                               [2.1, 2.98, 1.22, 1.0, 3.2, 1.0], rtol=1e-14)
    assert slope_power(2.1, 5.0, np.array([0.1]))[0] == 1.0, "never above the table's P"
    np.testing.assert_array_equal(slope_power(2.1, 0.0, np.array([0.0, 0.7, 1.0])), 2.1)


def test_the_slope_fit_finds_the_slope_that_made_the_outcomes():
    rng = np.random.default_rng(5)
    p, failed_p = rng.random(30_000), rng.random(30_000)
    k = np.maximum(1.0, 2.0 + 3.0 * (failed_p - 0.5))
    assert fit_slope(p, failed_p, rng.random(len(p)) < p**k, 2.0) == pytest.approx(3.0, abs=0.3)
    assert fit_slope(p, failed_p, rng.random(len(p)) < p**2.0, 2.0) == pytest.approx(0.0, abs=0.2), "one k: no slope"
    np.testing.assert_allclose(mapped(p[:50], 2.0, 3.0, failed_p[:50]), p[:50] ** k[:50], rtol=1e-14)
    np.testing.assert_allclose(mapped(p[:50], 2.0, 0.0, failed_p[:50]), mapped(p[:50], 2.0), rtol=1e-14)


def test_the_slope_is_scored_per_band_of_the_failed_push(tmp_path, capsys):
    p, failed_p = np.array([0.5, 0.5, 0.8, 0.8]), np.array([0.2, 0.3, 0.9, 0.7])
    toppled = np.array([True, False, False, False])
    report = score(p, toppled, 2.0, 0.25, 2.0, failed_p)
    name = "p^k_f, k 2, slope 2"
    low, high = report["bands"]["P_f < 0.6"], report["bands"]["P_f >= 0.6"]
    assert (low["pushes"], low["toppled"], high["pushes"], high["toppled"]) == (2, 0.5, 2, 0.0)
    # k_f: 1.4, 1.6, 2.8, 2.4
    assert low["predictors"][name]["mean"] == pytest.approx((0.5**1.4 + 0.5**1.6) / 2)
    assert high["predictors"][name]["brier"] == pytest.approx((0.8 ** 5.6 + 0.8 ** 4.8) / 2)
    assert low["predictors"]["p^2"]["mean"] == 0.25 and high["predictors"]["never topples"]["brier"] == 0.0
    assert report["predictors"][name]["mean"] == pytest.approx((0.5**1.4 + 0.5**1.6 + 0.8**2.8 + 0.8**2.4) / 4)
    assert "bands" not in score(p, toppled, 2.0, None)

    path = tmp_path / "pushes.jsonl"
    run = [push(0, "belief_vi", 0.9, False, 1), push(0, "belief_vi", 0.2, False, 2), push(0, "belief_vi", 0.7, True, 3)]
    path.write_text("\n".join(json.dumps(r) for r in run) + "\n")
    read = read_pushes([str(path)], "belief_vi")
    np.testing.assert_array_equal(read[0], [0.2, 0.7])
    np.testing.assert_array_equal(read[1], [False, True])
    np.testing.assert_array_equal(read[2], [0.9, 0.9])
    assert main(["fit-slope", "--power", "2", "--policy", "belief_vi", str(path)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["power"] == 2 and 0 <= fitted["slope"] <= 6 and fitted["bands"]["P_f >= 0.6"]["pushes"] == 2
    written = tmp_path / "scored.json"
    assert main(["score", "--power", "2", "--slope", "1.5", "--policy", "belief_vi", str(path), "--json", str(written)]) == 0
    scored = json.loads(capsys.readouterr().out)
    assert "p^k_f, k 2, slope 1.5" in scored["predictors"] and json.loads(written.read_text()) == scored
    assert scored["differences"]["objects"] == 1 and "p^k_f (slope 1.5) minus p^2" in scored["differences"]
    for wrong in (["fit-slope", str(path)], ["score", "--power", "2", "--slope", "-1", str(path)]):
        with pytest.raises(SystemExit) as refused:
            main([*wrong, "--policy", "belief_vi"])
        assert refused.value.code == 2


def test_brier_differences_are_per_push_with_intervals_over_objects():
    p = np.array([0.5, 0.5, 0.9, 0.2, 0.8])
    toppled = np.array([False, True, False, False, True])
    objects = np.array(["a", "a", "a", "b", "b"])
    table, power = (p - toppled) ** 2, (p**2 - toppled) ** 2
    found = brier_differences(p, toppled, objects, 2.0)
    assert found["objects"] == 2
    assert found["p^2 minus table P"]["difference"] == pytest.approx(np.mean(power - table), abs=1e-15)
    low, high = found["p^2 minus table P"]["interval"]
    per_object = [np.mean((power - table)[objects == o]) for o in "ab"]
    assert min(per_object) - 1e-12 <= low <= high <= max(per_object) + 1e-12, "within the objects' own means"
    alone = brier_differences(p[:3], toppled[:3], objects[:3], 2.0)["p^2 minus table P"]
    assert alone["interval"] == pytest.approx([alone["difference"]] * 2, abs=1e-15), "one object: nothing to resample"
    failed_p = np.array([0.9, 0.9, 0.1, 0.5, 0.5])
    sloped = brier_differences(p, toppled, objects, 2.0, 2.0, failed_p)
    expected = (mapped(p, 2.0, 2.0, failed_p) - toppled) ** 2 - power
    assert sloped["p^k_f (slope 2) minus p^2"]["difference"] == pytest.approx(expected.mean(), abs=1e-15)
