"""The thesis 4.4.3 policy experiment on hand-built tables with known answers."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from handmade import write_minimal_manifest

from pipeline.cli import main
from pipeline.studies.policy_experiment import PolicyTables, draw_starts, experiment
from schema.reader import Dataset


def _write(root, p_success, drop=(0.5, 0.5)):
    """One object, two poses dropped into with probabilities ``drop``: pose 0 ungraspable, pose 1 perfect.

    In pose 0 Greedy and Value Iteration push action 3, which reaches pose 1 with
    probability ``p_success`` and otherwise leaves the object where it was; Max-Height
    pushes action 7, which never topples.  In pose 1 every policy grasps.
    """
    pq.write_table(pa.table({
        "object_id": ["cup", "cup"], "pose": [0, 1], "probability": list(drop), "v_s": [0.0, 1.0],
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
    assert "points over Max-Height" in out and (tmp_path / "p.png").read_bytes().startswith(b"\x89PNG")
    # The suffix names the format, and the figure is written whole or not at all.
    assert main(["policies", str(tmp_path), "--trials", "500", "--plot", str(tmp_path / "figures" / "p.svg")]) == 0
    assert b"<svg" in (tmp_path / "figures" / "p.svg").read_bytes() and len(list((tmp_path / "figures").iterdir())) == 1
    capsys.readouterr()
    assert main(["policies", str(tmp_path / "nowhere")]) == 2
    assert "no such dataset directory" in capsys.readouterr().err


def test_no_useful_trial_is_said_in_words_and_null_in_the_json(tmp_path, capsys):
    """Every drop lands in the best pose: no mean to report, so no nan on the console and no bare
    NaN (not JSON) on the JSON line; null, as ``policies-physics`` writes."""
    _write(tmp_path, p_success=0.3, drop=(0.0, 1.0))
    write_minimal_manifest(tmp_path, {"cup": 2})
    assert main(["policies", str(tmp_path), "--trials", "200", "--plot", str(tmp_path / "p.png")]) == 0
    out = capsys.readouterr().out
    assert "0 useful trials of 200" in out and "no useful trials" in out and "nan" not in out.lower()

    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    record = json.loads(out.strip().splitlines()[-1], parse_constant=refuse)
    for policy in record["policies"].values():
        assert policy["mean_gain_useful"] is None and policy["mean_pushes_useful"] is None
        assert policy.get("gain_over_max_height", None) is None and policy["mean_gain_all"] == 0.0
    assert (tmp_path / "p.png").read_bytes().startswith(b"\x89PNG")


def _drop_tables(probability, poses_per_object):
    """PolicyTables with only what ``draw_starts`` reads: objects, their pose rows, drop probabilities."""
    first_pose = np.concatenate([[0], np.cumsum(poses_per_object)])
    return PolicyTables(
        object_ids=[f"o{i}" for i in range(len(poses_per_object))], first_pose=first_pose,
        probability=np.asarray(probability, dtype=float), v_s=np.zeros(len(probability)), actions={},
        keys=np.zeros(0, np.int64), next_row=np.zeros(0, int), cumulative=np.zeros(0),
    )


def test_starts_pick_a_uniform_object_then_a_pose_by_drop_probability():
    # Object 0 has three poses; object 1 one pose. Object 0's stored probabilities sum to
    # 0.5 only (poses dropped by the build are gone): they are renormalised to 0.6, 0.3, 0.1.
    tables = _drop_tables([0.3, 0.15, 0.05, 1.0], [3, 1])
    n = 40_000
    starts = draw_starts(tables, n, np.random.default_rng(5))
    frequency = np.bincount(starts, minlength=4) / n
    expected = np.array([0.5 * 0.6, 0.5 * 0.3, 0.5 * 0.1, 0.5])  # objects are equally likely, whatever their pose count
    assert np.all(np.abs(frequency - expected) <= 4 * np.sqrt(expected * (1 - expected) / n))
    # A pose with zero drop probability is never a start.
    never = draw_starts(_drop_tables([0.0, 1.0, 0.0], [3]), 5_000, np.random.default_rng(6))
    assert np.all(never == 1)


def test_useful_trials_follow_the_drop_probabilities(tmp_path):
    # Only drops into pose 0 are useful (pose 1 is already the best), so their share is P(pose 0).
    _write(tmp_path, p_success=0.3, drop=(0.8, 0.2))
    result = experiment(Dataset(tmp_path, manifest=None), n_trials=20_000, max_steps=1, seed=2)
    assert abs(result["useful_trials"] / 20_000 - 0.8) < 0.02
    # Greedy's mean gain over all trials: 0.8 of them start in pose 0 and topple with 0.3.
    assert abs(result["policies"]["greedy"]["mean_gain_all"] - 0.8 * 0.3) < 0.02


def test_the_summary_sets_the_thesis_beside_its_own_experiment_only():
    from pipeline.studies.policy_experiment import MAX_STEPS, summary
    from schema.vocabulary import POLICIES

    policy = {"mean_gain_useful": 0.2, "mean_pushes_useful": 1.0, "gain_over_max_height": 0.1}
    result = {"useful_trials": 3, "trials": 10, "policies": dict.fromkeys(POLICIES, policy)}
    five = summary(result | {"max_steps": MAX_STEPS})
    assert "(at most 5 pushes each)" in five and "+10.0 points over Max-Height (thesis +28.4)" in five
    one = summary(result | {"max_steps": 1})
    assert "(at most 1 push each)" in one and "+10.0 points over Max-Height" in one and "thesis" not in one
