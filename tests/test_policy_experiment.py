"""The thesis 4.4.3 policy experiment on hand-built tables with known answers."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from handmade import write_minimal_manifest

from pipeline.cli import main
from pipeline.studies.policy_experiment import experiment
from schema.reader import Dataset


def _write(root, p_success):
    """One object, two equally likely poses: pose 0 ungraspable, pose 1 perfect.

    In pose 0 Greedy and Value Iteration push action 3, which reaches pose 1 with
    probability ``p_success`` and otherwise leaves the object where it was; Max-Height
    pushes action 7, which never topples.  In pose 1 every policy grasps.
    """
    pq.write_table(pa.table({
        "object_id": ["cup", "cup"], "pose": [0, 1], "probability": [0.5, 0.5], "v_s": [0.0, 1.0],
        "max_height_action": [7, -1], "greedy_action": [3, -1], "value_iteration_action": [3, -1],
    }), root / "poses.parquet")
    part = root / "transitions" / "object_id=cup"
    part.mkdir(parents=True)
    pq.write_table(pa.table({
        "pose": pa.array([0, 0, 0], pa.int32()), "action": pa.array([3, 3, 7], pa.int32()),
        "next_pose": pa.array([1, 0, 0], pa.int32()), "probability": [p_success, 1 - p_success, 1.0],
    }), part / "part-0.parquet")


@pytest.mark.parametrize("steps", [1, 3])
def test_gains_follow_the_transition_probabilities(tmp_path, steps):
    _write(tmp_path, p_success=0.3)
    result = experiment(Dataset(tmp_path, manifest=None), n_trials=20_000, max_steps=steps, seed=1)
    # Half the drops land in pose 0, where toppling is useful.
    assert abs(result["useful_trials"] / 20_000 - 0.5) < 0.02
    policies = result["policies"]
    assert policies["max_height"]["mean_gain_useful"] == 0.0
    expected = 1 - 0.7**steps  # keeps pushing until it topples, at most `steps` times
    for policy in ("greedy", "value_iteration"):
        assert abs(policies[policy]["mean_gain_useful"] - expected) < 0.02
        assert policies[policy]["gain_over_max_height"] == policies[policy]["mean_gain_useful"]
    # Common random numbers: both policies push the same action, so they see the same outcomes.
    assert np.array_equal(policies["greedy"]["gains_useful"], policies["value_iteration"]["gains_useful"])


def test_cli_reports_and_refuses_a_missing_dataset(tmp_path, capsys):
    _write(tmp_path, p_success=1.0)
    assert main(["policies", str(tmp_path)]) == 2, "tables without a manifest are no finished dataset"
    assert "no manifest.json" in capsys.readouterr().err
    write_minimal_manifest(tmp_path, {"cup": 2})
    assert main(["policies", str(tmp_path), "--trials", "500", "--plot", str(tmp_path / "p.png")]) == 0
    out = capsys.readouterr().out
    assert "points over Max-Height" in out and (tmp_path / "p.png").is_file()
    assert main(["policies", str(tmp_path / "nowhere")]) == 2
    assert "no such dataset directory" in capsys.readouterr().err
