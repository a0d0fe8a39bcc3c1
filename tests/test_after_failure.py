"""The after-failure study (pipeline.studies.after_failure): which pushes it reads, and its fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.studies.after_failure import (
    SLOPES,
    after_failed_pushes,
    after_failure_arrays,
    breakdown,
    brier,
    brier_differences,
    failed_before,
    fit_landing,
    fit_power,
    fit_slope,
    landing_arrays,
    landing_mapped,
    landing_score,
    main,
    mapped,
    read_runs,
    score,
    slope_power,
    told,
)


def push(trial, policy, p, toppled, action=0, pose=0):
    return {"trial": trial, "policy": policy, "object_id": "box", "pose": pose, "p_topple": p, "toppled": toppled, "action": action}


RUN = [
    push(0, "untried_vi", 0.9, False, 7),
    push(0, "value_iteration", 0.9, False, 7),
    push(0, "untried_vi", 0.6, True, 8),   # after a failure: kept
    push(0, "untried_vi", 0.5, False, 9, pose=1),  # after a topple, in a new pose: not
    push(1, "untried_vi", 0.2, True, 3),
    push(1, "value_iteration", 0.9, False, 7),
    push(1, "value_iteration", 0.9, False, 7),  # value iteration's, after its own failure: the same push
    push(0, "untried_vi", 0.4, True, 2, pose=1),   # after trial 0's failed third push
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
        push(0, "belief_vi", 0.4, False, 4, pose=1),  # a first try in the new pose
        push(0, "belief_vi", 0.6, True, 5, pose=1),   # after 0.4 failed there only: back to pose 0
        push(0, "belief_vi", 0.8, True, 6),   # back where 0.9 and 0.2 failed: the player remembers them
        push(1, "belief_vi", 0.3, False, 6),
        push(1, "greedy", 0.8, False, 6),     # another policy's trial 1: no part of it
        push(1, "belief_vi", 0.5, False, 7),  # after trial 1's 0.3
    ]
    found = failed_before(run, "belief_vi")
    assert [found.get(id(r)) for r in run] == [None, [0.9], [0.9, 0.2], None, [0.4], [0.9, 0.2], None, None, [0.3]]
    assert after_failed_pushes(run, "belief_vi") == [run[i] for i in (1, 2, 4, 5, 8)]


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
    edge = score(p, toppled, 2.0, None, failed_p=np.array([0.6, 0.6, 0.1, 0.1]))  # no slope given: k alone
    assert edge["bands"]["P_f >= 0.6"]["pushes"] == 2 and edge["bands"]["P_f < 0.6"]["pushes"] == 2, "0.6 is the likely band's"
    assert edge["predictors"]["p^k_f, k 2, slope 0"]["mean"] == pytest.approx(edge["predictors"]["p^2"]["mean"], abs=1e-15)
    empty = score(p, toppled, 2.0, None, 1.0, np.array([0.1, 0.2, 0.3, 0.4]))["bands"]["P_f >= 0.6"]
    assert empty == {"pushes": 0, "toppled": None, "predictors": {}}

    path = tmp_path / "pushes.jsonl"
    run = [push(0, "belief_vi", 0.9, False, 1), push(0, "belief_vi", 0.2, False, 2), push(0, "belief_vi", 0.7, True, 3)]
    path.write_text("\n".join(json.dumps(r) for r in run) + "\n")
    read = after_failure_arrays(read_runs([str(path)]), "belief_vi")
    np.testing.assert_array_equal(read[0], [0.2, 0.7])
    np.testing.assert_array_equal(read[1], [False, True])
    np.testing.assert_array_equal(read[2], [0.9, 0.9])
    np.testing.assert_array_equal(read[3], ["box", "box"])
    assert main(["fit-slope", "--power", "2", "--policy", "belief_vi", str(path)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["power"] == 2 and fitted["slope"] in SLOPES and fitted["bands"]["P_f >= 0.6"]["pushes"] == 2
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
    assert low < high, "two objects that differ: the resamples differ"
    alone = brier_differences(p[:3], toppled[:3], objects[:3], 2.0)["p^2 minus table P"]
    assert alone["interval"] == pytest.approx([alone["difference"]] * 2, abs=1e-15), "one object: nothing to resample"
    failed_p = np.array([0.9, 0.9, 0.1, 0.5, 0.5])
    sloped = brier_differences(p, toppled, objects, 2.0, 2.0, failed_p)
    expected = (mapped(p, 2.0, 2.0, failed_p) - toppled) ** 2 - power
    assert sloped["p^k_f (slope 2) minus p^2"]["difference"] == pytest.approx(expected.mean(), abs=1e-15)


def synthetic_runs(tmp_path, power: float, slope: float, n_trials: int = 3000, seed: int = 7) -> list[str]:
    """Two robust_policy --pushes files whose belief_vi pushes after a failure topple with
    P^k_f (k_f = max(1, power + slope (P_f - 1/2))), trial ids repeated across the files."""
    rng = np.random.default_rng(seed)
    paths = []
    for run in range(2):
        lines = []
        for trial in range(n_trials):
            failed_p, p = rng.uniform(0.05, 0.95, 2)
            k = max(1.0, power + slope * (failed_p - 0.5))
            lines.append(push(trial, "belief_vi", float(failed_p), False, 1))
            lines.append(push(trial, "belief_vi", float(p), bool(rng.random() < p**k), 2))
            lines.append(push(trial, "value_iteration", float(failed_p), False, 1))
            lines.append(push(trial, "value_iteration", float(failed_p), bool(rng.random() < 0.3), 1))
            for record in lines[-4:]:
                record["object_id"] = f"obj{trial % 40}"
        path = tmp_path / f"run{run}.jsonl"
        path.write_text("\n".join(json.dumps(r) for r in lines) + "\n")
        paths.append(str(path))
    return paths


def test_the_command_finds_what_made_the_outcomes(tmp_path, capsys):
    paths = synthetic_runs(tmp_path, 2.0, 3.0)

    def out() -> dict:
        return json.loads(capsys.readouterr().out)

    written = tmp_path / "fitted.json"
    assert main(["fit", "--policy", "belief_vi", *paths, "--json", str(written)]) == 0
    fitted = out()
    assert json.loads(written.read_text()) == fitted
    rate = fitted["toppled"]
    assert fitted["pushes"] == 6000 and 1.5 < fitted["power"] < 3.0, "one k: the slope's average"
    assert fitted["predictors"][f"constant {rate:.3f}"]["mean"] == pytest.approx(rate)
    assert main(["fit-slope", "--power", "2", "--policy", "belief_vi", *paths]) == 0
    sloped = out()
    assert sloped["power"] == 2.0 and sloped["slope"] == pytest.approx(3.0, abs=0.4)
    assert f"constant {rate:.3f}" in sloped["predictors"] and set(sloped["bands"]) == {"P_f < 0.6", "P_f >= 0.6"}
    assert main(["score", "--power", "1", "--slope", "0", "--policy", "belief_vi", *paths]) == 0, "the edges are allowed"
    edges = out()
    assert edges["predictors"]["p^1"]["brier"] == edges["predictors"]["table P"]["brier"]
    assert edges["differences"]["p^1 minus table P"] == {"difference": 0.0, "interval": [0.0, 0.0]}
    assert main(["score", "--power", "2", "--constant", "0.5", "--policy", "belief_vi", *paths]) == 0
    plain = out()
    assert "bands" not in plain and plain["predictors"]["constant 0.500"]["brier"] == pytest.approx(0.25)
    table_gap = plain["differences"]["p^2 minus table P"]
    assert plain["differences"]["objects"] == 40 and table_gap["interval"][0] < table_gap["difference"] < table_gap["interval"][1] < 0
    assert main(["score", "--power", "2", "--slope", "3", "--constant", "0.4", "--policy", "belief_vi", *paths]) == 0
    sloped_score = out()
    assert sloped_score["bands"]["P_f < 0.6"]["predictors"]["constant 0.400"]["mean"] == pytest.approx(0.4)
    assert sloped_score["differences"]["p^k_f (slope 3) minus p^2"]["difference"] < 0, "the true slope scores better"
    (tmp_path / "tiny").mkdir()
    tiny = synthetic_runs(tmp_path / "tiny", 2.0, 3.0, n_trials=2)  # refusals need no 12,000 pushes read
    belief = ["--policy", "belief_vi", *tiny]
    for wrong, words in ((["score", "--power", "0.99", *belief], "score needs --power K, K >= 1"),
                         (["fit-slope", *belief], "fit-slope needs --power K, K >= 1"),
                         (["score", "--power", "2", "--slope", "-0.1", *belief], "--slope must be 0 or more, got -0.1"),
                         (["fit", "--policy", "greedy", *tiny], "no greedy push follows a failed one"),
                         (["score", "--power", "2"], "score needs robust_policy --pushes files"),
                         (["report", "--fit", tiny[0]], "report needs --fit FILE... and --judge FILE...\n"),
                         (["refit", *tiny], "invalid choice: 'refit'")):
        with pytest.raises(SystemExit) as refused:
            main(wrong)
        err = capsys.readouterr().err
        assert refused.value.code == 2 and (err == words if words.endswith("\n") else words in err), (wrong, err)


def test_the_report_fits_on_one_set_judges_on_another_and_keeps_runs_apart(tmp_path, capsys):
    (tmp_path / "fit").mkdir()
    (tmp_path / "judge").mkdir()
    fit_paths = synthetic_runs(tmp_path / "fit", 2.0, 0.0, n_trials=1500)
    judge_paths = synthetic_runs(tmp_path / "judge", 3.0, 0.0, n_trials=800, seed=8)
    assert main(["report", "--policy", "belief_vi", "--fit", *fit_paths, "--judge", *judge_paths]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["power"] == pytest.approx(2.0, abs=0.3) and result["fit"]["pushes"] == 3000 and result["judged"]["pushes"] == 1600
    rate = round(result["fit"]["toppled"], 3)
    assert result["judged"]["predictors"][f"constant {rate:.3f}"]["mean"] == pytest.approx(rate, abs=1e-15), "the fit's rate"
    fit_rate = result["fit"]["toppled"]
    assert result["fit"]["predictors"][f"constant {fit_rate:.3f}"]["mean"] == pytest.approx(fit_rate, abs=1e-15)
    assert result["judged"]["toppled"] < result["fit"]["toppled"], "k = 3 topples less"
    # Trial ids repeat across runs: pooled, each run's trial 0 is its own (a failure in one is no failure in the other).
    for name, n in (("fit", 3000), ("judge", 1600)):
        belief = result["breakdown"][name]["belief_vi"]
        assert belief["first try"]["pushes"] == belief["another push"]["pushes"] == n, name
        assert result["breakdown"][name]["value_iteration"]["same push again"]["pushes"] == n
        told_them = result["told"][name]
        assert told_them["re-asking (value_iteration)"]["pushes"] == 2 * n
        reported = told_them["reporting failures (belief_vi)"]
        assert reported["pushes"] == 2 * n and reported["told"] < belief["first try"]["p_topple"] / 2 + belief["another push"]["p_topple"] / 2
        assert reported["toppled"] == pytest.approx(belief["another push"]["toppled"] / 2)


def test_the_bootstrap_resamples_objects_and_weighs_their_pushes():
    rng = np.random.default_rng(11)
    counts = [1, 2, 5, 9, 3, 7]
    objects = np.repeat([f"o{i}" for i in range(len(counts))], counts)
    p, toppled = rng.random(len(objects)), rng.random(len(objects)) < 0.4
    difference = (p**2 - toppled) ** 2 - (p - toppled) ** 2
    found = brier_differences(p, toppled, objects, 2.0, n_resamples=300, seed=4)["p^2 minus table P"]
    # By hand: the draws of default_rng(4) pick objects; a resample's value is its pushes' mean.
    names = sorted(set(objects))
    draws = np.random.default_rng(4).integers(0, len(names), size=(300, len(names)))
    sums = np.array([difference[objects == o].sum() for o in names])
    sizes = np.array([np.sum(objects == o) for o in names], float)
    by_hand = sums[draws].sum(axis=1) / sizes[draws].sum(axis=1)
    assert found["difference"] == pytest.approx(difference.mean(), abs=1e-15), "per push, not per object"
    assert found["interval"] == pytest.approx(list(np.percentile(by_hand, [2.5, 97.5])), abs=1e-15)
    again = brier_differences(p, toppled, objects, 2.0, n_resamples=300, seed=4)["p^2 minus table P"]
    other = brier_differences(p, toppled, objects, 2.0, n_resamples=300, seed=5)["p^2 minus table P"]
    assert again == found and other["interval"] != found["interval"], "the seed decides the draws"
    default = brier_differences(p, toppled, objects, 2.0)["p^2 minus table P"]
    assert default == brier_differences(p, toppled, objects, 2.0, seed=0)["p^2 minus table P"], "seed 0 by default"
    with pytest.raises(ValueError, match="a slope needs each push's failed P"):
        brier_differences(p, toppled, objects, 2.0, slope=1.0)
    with pytest.raises(ValueError, match="a slope needs each push's failed P"):
        mapped(p, 2.0, 1.0)


def test_the_likeliest_failure_is_the_one_that_counts(tmp_path):
    run = [push(0, "belief_vi", 0.2, False, 1), push(0, "belief_vi", 0.9, False, 2), push(0, "belief_vi", 0.4, True, 3),
           push(1, "belief_vi", 0.8, False, 1), push(1, "belief_vi", 0.1, False, 2), push(1, "belief_vi", 0.5, False, 3)]
    path = tmp_path / "pushes.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in run) + "\n")
    p, toppled, failed_p, _ = after_failure_arrays(read_runs([str(path)]), "belief_vi")
    np.testing.assert_array_equal(p, [0.9, 0.4, 0.1, 0.5])
    np.testing.assert_array_equal(toppled, [False, True, False, False])
    np.testing.assert_array_equal(failed_p, [0.2, 0.9, 0.8, 0.8])  # the largest, not the first nor the last


def landed(trial, p, toppled, landing, pose=0, object_id="box", policy="belief_vi"):
    return {**push(trial, policy, p, toppled, pose=pose), "object_id": object_id, "landing": landing}


def test_a_push_after_a_failure_is_told_apart_by_where_the_failed_pushes_land():
    run = [
        landed(0, 0.9, False, 2),
        landed(0, 0.8, False, 2),        # after a failure that lands in 2: same
        landed(0, 0.7, False, 3),        # another landing: not the same
        landed(1, 0.6, False, -1),       # nothing leaves its pose in the model
        landed(0, 0.5, True, 3),         # after the failure that lands in 3 (trial 0): same
        landed(1, 0.4, True, -1),        # after a failure that lands nowhere either: never the same
        landed(1, 0.3, True, -1, pose=1),  # another pose: not after a failure
        landed(0, 0.2, True, 5, policy="value_iteration"),
    ]
    p, toppled, same, objects = landing_arrays([run], "belief_vi")
    assert p.tolist() == [0.8, 0.7, 0.5, 0.4]
    assert same.tolist() == [True, False, True, False]
    assert toppled.tolist() == [False, False, True, True] and objects.tolist() == ["box"] * 4
    assert failed_before(run, "belief_vi", "landing")[id(run[4])] == [2, 2, 3], "every failed push of the pose, in order"
    with pytest.raises(ValueError, match="carry no model landing"):
        landing_arrays([RUN], "untried_vi")


def test_the_landing_candidate_takes_one_power_where_a_failed_push_lands_and_another_elsewhere():
    p, same = np.array([0.5, 0.5, 1.0 + 1e-9, -1e-9]), np.array([True, False, True, False])
    assert landing_mapped(p, same, 3.0, 1.5).tolist() == pytest.approx([0.125, 0.5**1.5, 1.0, 0.0])
    assert landing_mapped(p[:2], same[:2], 2.0, 2.0).tolist() == mapped(p[:2], 2.0).tolist(), "one power: the map"
    rng = np.random.default_rng(4)
    p = rng.random(40_000)
    same = rng.random(len(p)) < 0.6
    toppled = rng.random(len(p)) < np.where(same, p**3.0, p**1.2)
    k_same, k_other = fit_landing(p, same, toppled)
    assert k_same == pytest.approx(3.0, abs=0.2) and k_other == pytest.approx(1.2, abs=0.1)
    for one_group in (np.ones(10, bool), np.zeros(10, bool)):
        with pytest.raises(ValueError, match="both where a failed push would and elsewhere"):
            fit_landing(np.full(10, 0.5), one_group, np.zeros(10, bool))
    scored = landing_score(p, toppled, same, 2.0, (3.0, 1.2), 0.3)
    groups = scored["groups"]
    assert groups["landing where a failed push would"]["pushes"] == same.sum()
    assert groups["landing elsewhere"]["pushes"] == (~same).sum()
    for name, group in (("landing where a failed push would", same), ("landing elsewhere", ~same)):
        candidate = groups[name]["predictors"]["by landing, k 3 / 1.2"]
        assert candidate["brier"] == pytest.approx(np.mean((landing_mapped(p, same, 3.0, 1.2)[group] - toppled[group]) ** 2))
    everyone = scored["predictors"]
    assert set(everyone) == {"p^2", "by landing, k 3 / 1.2", "table P", "never topples", "constant 0.300"}
    assert everyone["by landing, k 3 / 1.2"]["brier"] < everyone["p^2"]["brier"], "what made the outcomes scores better"


def test_the_command_fits_and_scores_a_power_per_landing(tmp_path, capsys):
    rng = np.random.default_rng(5)
    runs = []
    for r in range(2):
        records = []
        for trial in range(3000):
            first_landing = int(rng.integers(0, 3))
            records.append(landed(trial, 0.9, False, first_landing, object_id=f"o{trial % 30}"))
            p, landing = float(rng.random()), int(rng.integers(0, 3))
            believed = p**3.0 if landing == first_landing else p**1.2
            records.append(landed(trial, p, bool(rng.random() < believed), landing, object_id=f"o{trial % 30}"))
        path = tmp_path / f"run{r}.jsonl"
        path.write_text("".join(json.dumps(x) + "\n" for x in records))
        runs.append(str(path))

    def out() -> dict:
        return json.loads(capsys.readouterr().out)

    assert main(["fit-landing", "--power", "2", "--policy", "belief_vi", *runs]) == 0
    fitted = out()
    assert fitted["powers"] == [pytest.approx(3.0, abs=0.35), pytest.approx(1.2, abs=0.15)] and fitted["pushes"] == 6000
    assert f"constant {fitted['toppled']:.3f}" in fitted["predictors"]
    judged = tmp_path / "judged.json"
    assert main(["score", "--power", "2", "--landing-powers", "3", "1.2", "--policy", "belief_vi", *runs,
                 "--json", str(judged)]) == 0
    scored = out()
    assert json.loads(judged.read_text()) == scored and scored["powers"] == [3.0, 1.2]
    gap = scored["differences"]["by landing (k 3 / 1.2) minus p^2"]
    assert scored["differences"]["objects"] == 30 and gap["interval"][0] < gap["difference"] < gap["interval"][1] < 0
    assert gap["difference"] == pytest.approx(scored["predictors"]["by landing, k 3 / 1.2"]["brier"]
                                              - scored["predictors"]["p^2"]["brier"])
    assert main(["score", "--power", "1", "--landing-powers", "1", "1", "--policy", "belief_vi", *runs]) == 0, "the edge is allowed"
    edge = out()
    assert edge["predictors"]["by landing, k 1 / 1"]["brier"] == edge["predictors"]["table P"]["brier"]
    old = tmp_path / "old.jsonl"
    old.write_text("".join(json.dumps(x) + "\n" for x in RUN))
    for wrong, words in ((["fit-landing", "--power", "2", str(old)], "carry no model landing"),
                         (["fit-landing", "--power", "2", "--landing-powers", "3", "1", *runs], "--landing-powers is for score\n"),
                         (["fit", "--landing-powers", "0", "0", *runs], "--landing-powers is for score\n"),
                         (["score", "--power", "2", "--landing-powers", "3", "0.99", *runs],
                          "--landing-powers must be 1 or more, got 3 0.99\n"),
                         (["score", "--power", "2", "--slope", "1", "--landing-powers", "3", "1", *runs],
                          "--landing-powers and --slope are two candidates: score one at a time\n"),
                         (["fit-landing", "--power", "2", "--slope", "1", *runs], "--slope is for score and fit-slope\n"),
                         (["fit-landing", *runs], "fit-landing needs --power K")):
        with pytest.raises(SystemExit) as refused:
            main(["--policy", "belief_vi", *wrong] if wrong[-1] != str(old) else wrong)
        err = capsys.readouterr().err
        assert refused.value.code == 2 and (err == words if words.endswith("\n") else words in err), (wrong, err)
