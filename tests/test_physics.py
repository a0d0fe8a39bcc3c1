"""Physics validation (pipeline.studies.validation): pybullet pushes against the toppling model."""

import numpy as np
import pytest
from shapes import box_object, pose_with_down, standing_box

from pipeline.api import evaluate
from pipeline.model.config import VARIANTS, Config
from pipeline.studies.validation import (
    average_precision,
    empirical_distribution,
    simulate_push,
    total_variation,
    validate,
)

MU_TABLE = Config().topple.mu_table_mean


@pytest.fixture(scope="module")
def box():
    return standing_box()


def test_box_pushed_high_topples_onto_the_adjacent_face_as_the_model_predicts(box):
    obj, pose_set, standing = box
    point, direction = np.array([0.025, 0.0, 0.13]), np.array([-1.0, 0.0, 0.0])
    simulated = simulate_push(obj, pose_set, standing, point, direction, Config(), noise=False)
    predicted = evaluate(obj, pose_set, standing, points=point[None], directions=direction[None], variant="baseline")
    assert simulated == pose_with_down(pose_set, [-1, 0, 0])
    assert predicted.table.next_pose[0, simulated] == 1.0


def test_box_pushed_low_slides_and_stays(box):
    obj, pose_set, standing = box
    low = 0.5 * 0.05 / (2 * MU_TABLE)  # half the height below which sliding wins
    simulated = simulate_push(obj, pose_set, standing, np.array([0.025, 0.0, low]), np.array([-1.0, 0.0, 0.0]), Config(), noise=False)
    assert simulated == standing


def test_noisy_push_is_reproducible_from_the_rng(box):
    obj, pose_set, standing = box
    args = (obj, pose_set, standing, np.array([0.025, 0.0, 0.13]), np.array([-1.0, 0.0, 0.0]), Config())
    first = [simulate_push(*args, np.random.default_rng(3)) for _ in range(2)]
    assert first[0] == first[1]


def test_total_variation_sup_form():
    p = np.array([0.2, 0.3, 0.5])
    assert total_variation(p, p) == 0.0
    assert total_variation([1.0, 0.0, 0.0], [0.0, 0.5, 0.5]) == 1.0
    assert total_variation([0.5, 0.5], [0.25, 0.75]) == pytest.approx(0.25)


def test_empirical_distribution_puts_unknown_poses_last():
    assert np.allclose(empirical_distribution(np.array([0, 0, 2, -1]), 3), [0.5, 0, 0.25, 0.25])


def test_average_precision():
    labels = np.array([True, True, False, False])
    assert average_precision([0.9, 0.8, 0.3, 0.1], labels) == 1.0
    assert average_precision([0.1, 0.2, 0.8, 0.9], labels) == pytest.approx((1 / 3 + 2 / 4) / 2)
    # One tie of all scores: precision is the base rate, whatever the order.
    assert average_precision([1.0, 1.0, 1.0, 1.0], labels) == pytest.approx(0.5)
    assert np.isnan(average_precision([0.5, 0.5], [False, False]))


def test_tiny_validate_gives_metrics_in_unit_interval():
    result = validate([box_object()], n_actions=2, n_repeats=2, config=Config(), seed=0, n_contacts=60, n_trials=10)
    assert result.counts["actions"] > 0 and result.counts["pushes"] == 2 * result.counts["actions"]
    assert set(result.metrics) == set(VARIANTS)
    for variant in VARIANTS:
        for key in ("tv", "map"):
            assert 0.0 <= result.metrics[variant][key] <= 1.0, (variant, key, result.metrics[variant][key])
    for record in result.records:
        assert record.empirical.sum() == pytest.approx(1.0)
        for predicted in record.predicted.values():
            assert predicted.sum() == pytest.approx(1.0)


def test_main_prints_the_table_and_a_json_last_line(capsys):
    import json

    from pipeline.studies.validation import main

    assert main(["--objects", "1", "--actions", "1", "--repeats", "1", "--contacts", "40", "--trials", "5", "--max-poses", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert any(line.startswith("robust") for line in lines)
    last = json.loads(lines[-1])
    assert set(last["metrics"]) == set(VARIANTS) and last["counts"]["objects"] == 1
