"""Physics validation (pipeline.studies.validation): pybullet pushes against the toppling model."""

import numpy as np
import pytest
from shapes import box_object

from pipeline.model.config import VARIANTS, Config
from pipeline.studies.validation import (
    average_precision,
    total_variation,
    validate,
)


def test_total_variation_sup_form():
    p = np.array([0.2, 0.3, 0.5])
    assert total_variation(p, p) == 0.0
    assert total_variation([1.0, 0.0, 0.0], [0.0, 0.5, 0.5]) == 1.0
    assert total_variation([0.5, 0.5], [0.25, 0.75]) == pytest.approx(0.25)


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
