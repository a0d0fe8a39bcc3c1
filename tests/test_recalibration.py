"""Probability recalibration of P(topple) (docs/MODEL.md C.7): fitters, the engine's tables, config checks."""

from dataclasses import replace

import numpy as np
import pytest
from shapes import random_object

from pipeline.api import evaluate
from pipeline.model.config import Config
from pipeline.model.poses import stable_poses
from pipeline.model.recalibration import (
    Knots,
    apply_map,
    check_knots,
    fit,
    fit_centred,
    fit_isotonic,
    fit_logistic,
    logistic_knots,
    pool_adjacent_violators,
    predict,
    recalibrate_rows,
)
from pipeline.studies.recalibrate import cross_validate
from pipeline.studies.validation import average_precision
from schema.vocabulary import STATUS_OK
from tests.test_validation import model_logs  # noqa: F401 (fixture)

RAW = Config().topple.counted()  # the counts alone: no smoothing (MODEL.md C.12), no map
# A steep, clearly non-identity map: lifts small probabilities, as the corpus fit does.
LIFT = Knots((0.0, 0.2, 1.0), (0.0, 0.5, 0.9))


def _config(topple):
    return replace(Config(), topple=topple)


# ---------------------------------------------------------------- fitters


def test_pool_adjacent_violators_pools_violating_neighbours_by_weight():
    fitted, block = pool_adjacent_violators(np.array([1.0, 3.0, 2.0, 4.0, 0.0]), np.array([1.0, 1.0, 3.0, 1.0, 1.0]))
    # 3 then 2 (weight 3) pool to 2.25; 4 then 0 pool to 2, which violates 2.25 and pools again:
    # (3 + 2 x 3 + 4 + 0) / 6.
    assert np.allclose(fitted, [1.0, 13 / 6, 13 / 6, 13 / 6, 13 / 6])
    assert list(block) == [0, 1, 1, 1, 1]


def test_isotonic_fit_is_monotone_and_recovers_a_monotone_map():
    rng = np.random.default_rng(0)
    p = rng.choice(np.arange(1, 100) / 100, 400)
    def truth(q):  # a known increasing map
        return 0.1 + 0.8 * q**2

    knots = fit_isotonic(p, truth(p), np.full(len(p), 10.0))
    assert np.all(np.diff(knots.x) > 0) and np.all(np.diff(knots.y) >= 0)
    assert knots.x[0] == 0.0 and knots.x[-1] == 1.0
    assert np.allclose(apply_map(p, knots.x, knots.y), truth(p))
    # Noisy observations of the same map: still monotone, and close to it on average.
    noisy = rng.binomial(10, truth(p)) / 10
    knots = fit_isotonic(p, noisy, np.full(len(p), 10.0))
    assert np.all(np.diff(knots.y) >= 0)
    assert np.mean(np.abs(apply_map(p, knots.x, knots.y) - truth(p))) < 0.05


def rises_between_flat_ends(x, y) -> bool:
    """Whether knot values y strictly increase everywhere but in a flat start and a flat end,
    past the (0, 0) anchor (the fitted p are all > 0)."""
    rises = np.diff(np.asarray(y, dtype=float)[np.asarray(x) > 0]) > 0
    where = np.flatnonzero(rises)
    return len(where) > 0 and bool(np.all(rises[where[0]:where[-1] + 1]))


def test_strict_pooling_also_pools_equal_neighbours():
    fitted, block = pool_adjacent_violators(np.array([0.1, 0.3, 0.3, 0.5]), np.ones(4), strict=True)
    assert list(block) == [0, 1, 1, 2] and np.allclose(fitted, [0.1, 0.3, 0.3, 0.5])
    _, loose = pool_adjacent_violators(np.array([0.1, 0.3, 0.3, 0.5]), np.ones(4))
    assert list(loose) == [0, 1, 2, 3], "plain isotonic keeps equal neighbours apart"


def test_centred_fit_puts_one_knot_at_each_blocks_weighted_centre():
    p = np.array([0.1, 0.2, 0.4, 0.6, 0.8])
    observed = np.array([0.0, 0.3, 0.1, 0.5, 0.5])  # 0.2 and 0.4 violate; 0.6 and 0.8 tie
    weight = np.array([1.0, 1.0, 3.0, 1.0, 1.0])
    knots = fit_centred(p, observed, weight)
    # Blocks {0.1}, {0.2, 0.4} (weights 1 and 3), {0.6, 0.8}: the last block is constant from
    # its centre to its largest p; anchored at (0, 0), flat to x = 1.
    assert np.allclose(knots.x, [0.0, 0.1, (0.2 + 3 * 0.4) / 4, 0.7, 0.8, 1.0])
    assert np.allclose(knots.y, [0.0, 0.0, (0.3 + 3 * 0.1) / 4, 0.5, 0.5, 0.5])


def test_centred_fit_keeps_a_blocks_value_over_all_of_its_pushes():
    # One block: every push is predicted its observed rate, none pulled towards the (0, 0) anchor.
    knots = fit_centred(np.array([0.2, 0.5, 0.9]), np.full(3, 0.4), np.ones(3))
    assert np.allclose(predict(np.array([0.2, 0.5, 0.9]), knots), 0.4)


def test_centred_knots_stay_strictly_increasing_for_probabilities_one_bit_apart():
    p = np.array([0.3, np.nextafter(0.3, 1.0)])
    knots = fit_centred(p, np.array([0.1, 0.2]), np.full(2, 107.0))
    check_knots(knots.x, knots.y)
    assert np.allclose(predict(p, knots), [0.1, 0.2])


def test_centred_fit_is_strictly_increasing_inside_its_knots_and_keeps_the_ranking():
    rng = np.random.default_rng(4)
    p = rng.choice(np.arange(1, 100) / 100, 500)
    truth = 0.05 + 0.7 * p**1.5
    observed = rng.binomial(10, truth) / 10
    centred, isotonic = fit_centred(p, observed, np.full(len(p), 10.0)), fit_isotonic(p, observed, np.full(len(p), 10.0))
    assert np.all(np.diff(centred.x) > 0) and rises_between_flat_ends(centred.x, centred.y), "strictly increasing between block centres"
    rising = np.flatnonzero(np.diff(centred.y[1:]) > 0) + 1  # knots past the anchor that rise to the next
    inside = (p >= centred.x[rising[0]]) & (p <= centred.x[rising[-1] + 1])
    mapped = predict(p, centred)
    assert np.array_equal(np.argsort(mapped[inside], kind="stable"), np.argsort(p[inside], kind="stable"))
    topples = observed > 0.5
    assert average_precision(predict(p, isotonic), topples) < average_precision(p, topples), "isotonic's steps tie pushes"
    assert abs(average_precision(mapped, topples) - average_precision(p, topples)) < 0.01
    assert np.mean(np.abs(mapped - truth)) < 0.05


def test_logistic_fit_recovers_known_parameters_and_is_strictly_increasing():
    p = np.arange(1, 100) / 100
    a, b = 0.6, 0.4
    observed = 1 / (1 + np.exp(-(a * np.log(p / (1 - p)) + b)))
    fitted = fit_logistic(p, observed, np.full(len(p), 10.0))
    assert np.allclose(fitted, (a, b), atol=1e-6)
    knots = logistic_knots(*fitted)
    assert np.all(np.diff(knots.y[1:]) > 0) and knots.y[0] == 0.0
    # A strictly increasing map keeps the order of distinct probabilities: ranking (AP) is unchanged.
    assert np.array_equal(np.argsort(predict(p, knots)), np.argsort(p))


def test_fit_ignores_pushes_the_engine_never_moves():
    p = np.array([0.0, 0.0, 0.5, 0.5])
    observed = np.array([1.0, 1.0, 0.2, 0.2])
    knots = fit("isotonic", p, observed, np.ones(4))
    assert np.isclose(apply_map(0.5, knots.x, knots.y), 0.2)
    assert np.array_equal(predict(p, knots)[:2], [0.0, 0.0])


def test_cross_validation_is_grouped_by_object_and_scores_every_method():
    rng = np.random.default_rng(1)
    objects = np.repeat(np.arange(12), 20)
    p = rng.uniform(0.01, 1, len(objects))
    observed = np.clip(p * 0.6 + 0.2, 0, 1)
    cv = cross_validate(p, observed, np.full(len(p), 10.0), objects, [f"o{i}" for i in range(12)], 4, 0)
    assert sorted(name for fold in cv["folds"] for name in fold) == sorted(f"o{i}" for i in range(12))
    for method in ("isotonic", "logistic", "centred"):
        assert cv["methods"][method]["ece"] < cv["identity"]["ece"]


# ---------------------------------------------------------------- transition rows


def test_recalibrated_rows_stay_distributions_and_match_the_map():
    rows = np.array([
        [0.6, 0.3, 0.1],  # p = 0.4
        [1.0, 0.0, 0.0],  # never topples: left alone
        [np.nan, np.nan, np.nan],  # not ok
        [0.0, 0.25, 0.75],  # always topples
    ])
    out, p = recalibrate_rows(rows, 0, LIFT.x, LIFT.y)
    ok = ~np.isnan(rows).any(axis=1)
    assert np.allclose(out[ok].sum(axis=1), 1.0) and np.all(out[ok] >= 0)
    assert np.allclose(p[ok], 1 - out[ok, 0])
    assert np.allclose(p[ok], [apply_map(0.4, LIFT.x, LIFT.y), 0.0, 0.9])
    assert np.array_equal(out[1], rows[1]) and np.all(np.isnan(out[2])) and np.isnan(p[2])
    # The toppled mass keeps its split between next poses: (0.3, 0.1) -> 3:1, (0.25, 0.75) -> 1:3.
    assert np.isclose(out[0, 1] / out[0, 2], 3.0) and np.isclose(out[3, 2] / out[3, 1], 3.0)
    unchanged, p_unchanged = recalibrate_rows(rows, 0, (), ())
    assert np.array_equal(unchanged, rows, equal_nan=True)
    assert np.array_equal(p_unchanged, 1 - rows[:, 0], equal_nan=True)


@pytest.fixture(scope="module")
def random_pose():
    obj = random_object(3)
    return obj, stable_poses(obj)


def test_engine_without_knots_gives_the_counted_table(random_pose):
    obj, pose_set = random_pose
    result = evaluate(obj, pose_set, 0, n_contacts=60, n_trials=40, seed=3, config=_config(RAW))
    table, ok = result.table, result.actions.status == STATUS_OK
    landed = np.append(pose_set.poses[0].edge_final_pose, 0)[table.outcomes[ok]]  # (n_ok, T), -1 reads "stays"
    counted = np.stack([np.bincount(row, minlength=len(pose_set.poses)) for row in landed]) / 40
    assert np.array_equal(table.next_pose[ok], counted)
    # The thesis's variants never apply the knots, whatever the config says.
    robust_raw = evaluate(obj, pose_set, 0, n_contacts=60, n_trials=40, seed=3, variant="robust", config=_config(RAW))
    robust_knots = evaluate(obj, pose_set, 0, n_contacts=60, n_trials=40, seed=3, variant="robust",
                            config=_config(replace(RAW, recalibration_x=LIFT.x, recalibration_y=LIFT.y)))
    assert np.array_equal(robust_raw.table.next_pose, robust_knots.table.next_pose, equal_nan=True)


def test_engine_applies_the_map_consistently(random_pose):
    obj, pose_set = random_pose
    pose = 2  # pushes topple here under the default model (on pose 0 tip_path stops them all, MODEL.md C.14)
    raw = evaluate(obj, pose_set, pose, n_contacts=60, n_trials=40, seed=3, config=_config(RAW)).table
    lifted = evaluate(obj, pose_set, pose, n_contacts=60, n_trials=40, seed=3,
                      config=_config(replace(RAW, recalibration_x=LIFT.x, recalibration_y=LIFT.y))).table
    ok = ~np.isnan(raw.p_topple)
    assert np.allclose(lifted.next_pose[ok].sum(axis=1), 1.0)
    assert np.allclose(lifted.p_topple[ok], 1 - lifted.next_pose[ok, pose])
    assert np.allclose(lifted.p_topple[ok], predict(raw.p_topple[ok], LIFT))
    assert (raw.p_topple[ok] > 0).any() and (lifted.p_topple[ok] > raw.p_topple[ok]).any()
    assert np.array_equal(lifted.outcomes, raw.outcomes)  # the trials themselves are untouched


# ---------------------------------------------------------------- config checks


@pytest.mark.parametrize(
    "x, y, message",
    [
        ("0,0.5,1", "0,0.6,0.4", "non-decreasing"),
        ("0,0.5,0.4", "0,0.1,0.2", "strictly increasing"),
        ("0,1.5", "0,1", "must be in [0, 1]"),
        ("0,1", "-0.1,1", "must be in [0, 1]"),
        ("0,1", "0", "as many values"),
        ("0.5", "0.5", "at least 2 knots"),
        ("0,a", "0,1", "list of numbers"),
    ],
)
def test_bad_knots_are_refused_with_a_clear_error(x, y, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        Config().with_overrides({"topple.recalibration_x": x, "topple.recalibration_y": y})


def test_knots_round_trip_through_dict_and_toml(tmp_path):
    config = Config().with_overrides({"topple.recalibration_x": [0, 0.5, 1], "topple.recalibration_y": "0,0.7,0.9"})
    assert config.topple.recalibration_y == (0.0, 0.7, 0.9)
    assert Config.from_dict(config.to_dict()) == config
    path = tmp_path / "knots.toml"
    path.write_text("[topple]\nrecalibration_x = [0.0, 0.5, 1.0]\nrecalibration_y = [0.0, 0.7, 0.9]\n")
    # A file with its own map and no down or side map gets none (MODEL.md C.15, C.16): the default's
    # belong to the default's map.
    assert Config.from_toml(path) == config.with_overrides({"topple.down_map": [], "topple.side_map": []})
    path.write_text(path.read_text() + f"down_map = {list(config.topple.down_map)}\n")
    assert Config.from_toml(path) == config.with_overrides({"topple.side_map": []})
    path.write_text(path.read_text() + f"side_map = {list(config.topple.side_map)}\n")
    assert Config.from_toml(path) == config
    assert isinstance(config.to_dict()["topple"]["recalibration_x"], list)  # as JSON reads it back (manifest)


# ---------------------------------------------------------------- the command


def test_the_command_fits_the_methods_it_is_given_and_refuses_unknown_ones(model_logs, tmp_path, capsys):  # noqa: F811
    import json

    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    out, record = tmp_path / "map.toml", tmp_path / "map.json"
    common = ["--corpus", "none", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}", "--seed", "2",
              "--set", "seed=2", "--out", str(out), "--json", str(record)]
    assert main([str(path), "--methods", "centred", *common]) == 0
    result = json.loads(record.read_text())
    written = Config.from_toml(out).topple
    assert result["chosen"] == "centred" and result["methods"] == ["centred"]
    assert set(result["cross_validated"]["methods"]) == {"isotonic", "logistic", "centred"}, "every method is scored"
    assert list(written.recalibration_x) == result["knots"]["x"] and rises_between_flat_ends(written.recalibration_x, written.recalibration_y)
    assert "chosen among centred" in out.read_text()
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        main([str(path), "--methods", "splines", *common])
    assert refused.value.code == 2 and "invalid choice: 'splines'" in capsys.readouterr().err
    # On a base model with other noise (a ``toppledb calibrate`` file, say), the written file
    # carries that noise with the map fitted on it; loaded alone it is the model the map was fitted for.
    base = tmp_path / "noise.toml"
    base.write_text('[topple]\nmu_table_mean = 0.5\nrecalibration_x = []\nrecalibration_y = []\n')
    assert main([str(path), "--config", str(base), "--methods", "isotonic", *common]) == 0
    written = Config.from_toml(out).topple
    assert written.mu_table_mean == 0.5 and list(written.recalibration_x) == json.loads(record.read_text())["knots"]["x"]
    assert written.variant == Config().topple.variant and "base model: " in out.read_text()
    # The variant and the corrections are pinned, so the file stays this model when the defaults change.
    assert f'corrections = "{Config().topple.corrections}"' in out.read_text() and 'variant = "corrected"' in out.read_text()


# ---------------------------------------------------------------- mutation-testing gaps (stop 71)


def test_pooled_blocks_hold_the_weighted_mean_of_their_members_and_never_fall():
    """What characterises the weighted isotonic fit: each block's value is its members' weighted
    mean, and no block's value falls below its predecessor's."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        y, w = rng.uniform(0, 1, 12), rng.integers(1, 6, 12).astype(float)
        fitted, block = pool_adjacent_violators(y, w)
        values = [np.average(y[block == b], weights=w[block == b]) for b in range(block[-1] + 1)]
        assert np.allclose(fitted, np.asarray(values)[block])
        assert np.all(np.diff(values) >= 0) and np.all(np.diff(block) >= 0)


def test_isotonic_knots_are_a_flat_step_from_each_blocks_smallest_p_to_its_largest():
    p = np.array([0.1, 0.2, 0.3, 0.5, 0.6, 0.8])
    observed = np.array([0.6, 0.4, 0.2, 0.7, 0.5, 0.9])  # blocks {0.1, 0.2, 0.3} at 0.4, {0.5, 0.6} at 0.6, {0.8}
    knots = fit_isotonic(p, observed, np.ones(6))
    assert np.allclose(knots.x, [0.0, 0.1, 0.3, 0.5, 0.6, 0.8, 1.0])
    assert np.allclose(knots.y, [0.0, 0.4, 0.4, 0.6, 0.6, 0.9, 0.9])


def test_centred_map_is_flat_from_the_first_blocks_smallest_p_to_its_centre():
    knots = fit_centred(np.array([0.2, 0.4, 0.8]), np.array([0.3, 0.1, 0.9]), np.ones(3))
    # First block {0.2, 0.4} at 0.2, centred at 0.3; the smallest fitted p keeps the block's value.
    assert np.allclose(knots.x, [0.0, 0.2, 0.3, 0.8, 1.0]) and np.allclose(knots.y, [0.0, 0.2, 0.2, 0.9, 0.9])
    assert np.allclose(predict(np.array([0.2, 0.25, 0.3]), knots), 0.2)


def test_centred_knots_stay_inside_their_blocks_where_the_weighted_mean_rounds_up():
    # (3 x 0.05) / 3 is 0.05 and one bit: a centre one bit past its block's only p, where the next block starts.
    low = 0.05
    assert (3 * low) / 3 > low
    p = np.array([low, np.nextafter(low, 1.0)])
    knots = fit_centred(p, np.array([0.1, 0.2]), np.full(2, 3.0))
    check_knots(knots.x, knots.y)
    assert np.allclose(knots.x[1:3], p) and np.allclose(predict(p, knots), [0.1, 0.2])


@pytest.mark.parametrize("fitter", [fit_isotonic, fit_centred])
def test_fits_on_pushes_at_p_0_and_1_give_knots_anchored_once(fitter):
    p = np.array([0.0, 0.0, 0.5, 1.0, 1.0])
    knots = fitter(p, np.array([0.1, 0.2, 0.5, 0.8, 1.0]), np.ones(5))
    check_knots(knots.x, knots.y)
    assert knots.x[0] == 0.0 and knots.x[-1] == 1.0 and knots.x.count(0.0) == knots.x.count(1.0) == 1
    assert np.allclose(apply_map(np.array([0.0, 0.5, 1.0]), knots.x, knots.y), [0.15, 0.5, 0.9])


def test_the_logit_is_clipped_at_both_ends():
    from pipeline.model.recalibration import LOGIT_FLOOR, logit

    ends = logit(np.array([0.0, 1.0]))
    assert np.all(np.isfinite(ends)) and ends[1] == pytest.approx(-ends[0])
    assert ends[1] == pytest.approx(np.log((1 - LOGIT_FLOOR) / LOGIT_FLOOR))


def test_an_anti_monotone_logistic_fit_is_the_constant_weighted_rate():
    p = np.array([0.2, 0.8])
    observed, weight = np.array([0.9, 0.1]), np.array([1.0, 3.0])  # the likelier push toppled less
    a, b = fit_logistic(p, observed, weight)
    assert a == 0.0 and b == pytest.approx(np.log(0.3 / 0.7))
    assert np.allclose(predict(np.array([0.1, 0.5, 0.9]), logistic_knots(a, b)), 0.3)


def test_logistic_knots_are_the_map_at_every_hundredth():
    from pipeline.model.recalibration import LOGISTIC_GRID

    a, b = 0.6, 0.4
    knots = logistic_knots(a, b)
    x = np.arange(LOGISTIC_GRID) / (LOGISTIC_GRID - 1)
    assert len(knots.x) == LOGISTIC_GRID and np.allclose(knots.x, x)
    inside = x[1:-1]
    assert np.allclose(knots.y[1:-1], 1 / (1 + np.exp(-(a * np.log(inside / (1 - inside)) + b))))
    assert knots.y[0] == 0.0 and knots.y[-1] > knots.y[-2]


def test_fit_refuses_a_log_with_nothing_to_move_and_an_unknown_method():
    from pipeline.model.recalibration import RecalibrationError

    with pytest.raises(RecalibrationError, match=r"^no push with a predicted P\(topple\) > 0 to fit a recalibration on$"):
        fit("isotonic", np.zeros(3), np.ones(3), np.ones(3))
    with pytest.raises(RecalibrationError, match=r"^unknown recalibration method 'splines'; choose one of isotonic, logistic, centred$"):
        fit("splines", np.full(3, 0.5), np.ones(3), np.ones(3))


def test_predict_never_moves_a_push_the_engine_never_saw_topple():
    lifted = Knots((0.0, 1.0), (0.2, 0.9))  # g(0) = 0.2 > 0
    assert np.allclose(predict(np.array([0.0, 0.5]), lifted), [0.0, 0.55])


def test_apply_map_without_knots_is_the_identity_and_nan_passes_through():
    p = np.array([0, 1])  # integers: floats come back
    same = apply_map(p, (), ())
    assert same.dtype == float and np.array_equal(same, [0.0, 1.0])
    assert np.array_equal(apply_map(np.array([np.nan, 0.2]), LIFT.x, LIFT.y), [np.nan, 0.5], equal_nan=True)


def test_rows_without_knots_come_back_bit_for_bit_and_integer_rows_as_floats():
    rows = np.array([[0.1, 0.9, 0.0], [0.7, 0.1, 0.2]])  # 1 - (1 - 0.1) is not 0.1 in floats
    out, p = recalibrate_rows(rows, 0, (), ())
    assert np.array_equal(out, rows) and np.array_equal(p, 1 - rows[:, 0])
    deterministic = np.array([[1, 0, 0], [0, 1, 0]])  # a table of 0/1 outcomes
    for x, y, moved in (((), (), 1.0), (LIFT.x, LIFT.y, 0.9)):
        out, p = recalibrate_rows(deterministic, 0, x, y)
        assert out.dtype == float and np.allclose(out, [[1, 0, 0], [1 - moved, moved, 0]]) and np.allclose(p, [0, moved])


def test_knots_of_another_shape_are_refused_as_such():
    from pipeline.model.recalibration import RecalibrationError

    with pytest.raises(RecalibrationError, match="as many values"):
        check_knots([[0.0, 0.5], [1.0, 1.0]], [0.0, 1.0])


@pytest.mark.parametrize(
    "x, y, message",
    [
        ([0.0, 1.5], [0.0, 1.0], "topple.recalibration_x must be in [0, 1], got 0 .. 1.5"),
        ([0.0, 1.0], [-0.1, 1.0], "topple.recalibration_y must be in [0, 1], got -0.1 .. 1"),
        ([0.0, np.nan], [0.0, 1.0], "topple.recalibration_x must be in [0, 1], got nan .. nan"),
        ([0.0, 0.5, 0.5, 1.0], [0.0, 0.1, 0.2, 1.0], "topple.recalibration_x must be strictly increasing"),
        ([0.0, 1.0], [0.5, 0.2], "topple.recalibration_y must be non-decreasing (the map must be monotone)"),
        ([0.5], [0.5], "topple.recalibration_x/_y need at least 2 knots (or none for the identity)"),
    ],
)
def test_check_knots_refuses_what_the_config_fields_would_let_through_in_one_line(x, y, message):
    """``check_knots`` on its own: the config's field bounds refuse a value outside [0, 1] before it is
    called, so its range check is met only by a caller without the config; equal knots reach it either way."""
    from pipeline.model.recalibration import RecalibrationError

    with pytest.raises(RecalibrationError) as refused:
        check_knots(x, y)
    assert str(refused.value) == message
