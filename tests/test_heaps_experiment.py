"""The heap experiment (pipeline.heaps.experiment): the regression finds a planted effect,
the command writes the tables and report, and a rerun resumes instead of recomputing."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from pipeline.heaps import experiment
from schema.heaps import HEAP_OBJECTS, HEAPS, PUSHES

POLICIES = ("quasi_random", "boundary_shear", "free_space")


def synthetic_pushes(effect: float, heaps: int = 60, seed: int = 3) -> pd.DataFrame:
    """Gains = heap offset + ``effect`` for boundary_shear + noise; free_space has no effect."""
    rng = np.random.default_rng(seed)
    offsets = rng.normal(0.0, 0.2, heaps)
    rows = [
        {"heap": h, "policy": p, "parallel_jaw_gain": offsets[h] + (effect if p == "boundary_shear" else 0.0) + rng.normal(0.0, 0.05)}
        for h in range(heaps)
        for p in POLICIES
    ]
    return pd.DataFrame(rows)


def test_the_regression_finds_a_planted_policy_effect_despite_heap_offsets():
    result = experiment.regression(synthetic_pushes(0.1), "parallel_jaw")
    shear, free = result["effects"]["boundary_shear"], result["effects"]["free_space"]
    assert result["n_obs"] == 180 and result["n_heaps"] == 60
    assert shear["coef"] == pytest.approx(0.1, abs=0.03) and shear["p"] < 1e-6
    assert abs(free["coef"]) < 0.03 and free["p"] > 0.01
    assert result["ols_cluster"]["boundary_shear"]["coef"] == pytest.approx(0.1, abs=0.03)


def test_the_regression_says_why_it_cannot_run():
    one_heap = synthetic_pushes(0.1, heaps=1)
    assert "error" in experiment.regression(one_heap, "parallel_jaw")
    flat = synthetic_pushes(0.0).assign(parallel_jaw_gain=lambda d: d["heap"] * 0.01)  # heap effects only
    assert "error" in experiment.regression(flat, "parallel_jaw")


def test_summary_stats_are_the_mean_and_standard_error_per_policy():
    pushes = synthetic_pushes(0.1).assign(suction_gain=0.0, overall_gain=1.0)
    stats = experiment.summary_stats(pushes)
    gains = pushes.loc[pushes["policy"] == "boundary_shear", "parallel_jaw_gain"]
    assert stats["parallel_jaw"]["boundary_shear"]["mean"] == pytest.approx(gains.mean())
    assert stats["parallel_jaw"]["boundary_shear"]["sem"] == pytest.approx(gains.std(ddof=1) / np.sqrt(len(gains)))
    assert stats["suction"]["free_space"] == {"n": 60, "mean": 0.0, "sem": 0.0}


TEST_HEAPS = 20
"""The issue's test run: --heaps 20 (about 20 s on 2 cores)."""


@pytest.mark.slow
def test_a_small_run_writes_the_tables_and_resumes(tmp_path, monkeypatch):
    out = tmp_path / "heaps"
    assert experiment.main(["--heaps", str(TEST_HEAPS), "--out", str(out), "--no-progress"]) == experiment.EXIT_OK
    heaps = pq.read_table(out / "heaps.parquet")
    pushes = pq.read_table(out / "pushes.parquet")
    objects = pq.read_table(out / "heap_objects.parquet")
    assert heaps.schema.equals(HEAPS) and pushes.schema.equals(PUSHES) and objects.schema.equals(HEAP_OBJECTS)
    heaps, pushes = heaps.to_pandas(), pushes.to_pandas()
    assert heaps["hard"].sum() == TEST_HEAPS and heaps["hard"].iloc[-1]  # stops at the last hard heap
    names = experiment.policies()[0]
    assert len(pushes) == TEST_HEAPS * len(names) and set(pushes["policy"]) == set(names)
    # A push's gain is after minus before, and a policy without a push changes nothing.
    for g in ("suction", "parallel_jaw", "overall"):
        np.testing.assert_allclose(pushes[f"{g}_gain"], pushes[f"{g}_after"] - pushes[f"{g}_before"])
    assert (pushes.loc[~pushes["planned"], "overall_gain"] == 0).all()
    hard = heaps[heaps["hard"]]
    assert (hard["overall_confidence"] < experiment.HeapConfig().grasp_threshold).all()
    report = json.loads((out / "report.json").read_text())
    assert report["hard_heaps"] == TEST_HEAPS and report["heaps_dropped"] == len(heaps)

    # Rerun: every heap comes from its record, none is computed again.
    def no_compute(*args):
        raise AssertionError("a finished heap was computed again")

    monkeypatch.setattr(experiment, "run_heap", no_compute)
    assert experiment.main(["--heaps", str(TEST_HEAPS), "--out", str(out), "--no-progress"]) == experiment.EXIT_OK
    # Records made with other parameters are refused with a one-line error.
    assert experiment.main(["--heaps", str(TEST_HEAPS), "--out", str(out), "--seed", "1", "--no-progress"]) == experiment.EXIT_USAGE


def test_bad_arguments_are_a_usage_error(tmp_path, capsys):
    assert experiment.main(["--heaps", "0", "--out", str(tmp_path)]) == experiment.EXIT_USAGE
    assert "at least 1" in capsys.readouterr().err


def test_the_run_goes_to_a_dask_scheduler_and_says_when_it_cannot_reach_one(tmp_path, capsys):
    from distributed import LocalCluster

    unreachable = ["--heaps", "1", "--out", str(tmp_path / "none"), "--scheduler", "tcp://127.0.0.1:1", "--no-progress"]
    assert experiment.main(unreachable) == experiment.EXIT_USAGE
    assert "cannot connect to the dask scheduler at tcp://127.0.0.1:1" in capsys.readouterr().err
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        local = ["--heaps", "1", "--no-progress", "--max-drops", "2"]
        assert experiment.main([*local, "--out", str(tmp_path / "dask"), "--scheduler", cluster.scheduler_address]) == 0
    assert experiment.main([*local, "--out", str(tmp_path / "local")]) == 0
    dask, local_run = (pq.read_table(tmp_path / d / "pushes.parquet") for d in ("dask", "local"))
    assert dask.num_rows > 0 and dask.equals(local_run), "the scheduler changes where heaps run, not what they give"
