"""The policy experiment of thesis 4.4.3, replayed on a finished dataset.

Each trial drops a random object (uniformly) into a random stable pose (weighted by
the pose's drop probability).  Each policy then pushes until it chooses not to (at
most ``max_steps`` pushes), each next pose drawn from the stored P(x' | x, u), and
the trial records the suction quality V_s before and after.  As in the thesis, a
trial counts as *useful* when the object is not already in its best pose and some
push is expected to raise V_s (the Greedy policy would act).

All three policies see the same random draws (common random numbers), so the
differences between them are the policies' own.  Only the dataset's tables are
read; no geometry is recomputed.

    toppledb policies data/dataset [--trials 20000] [--plot docs/policy_experiment.png]
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schema.reader import Dataset
from schema.vocabulary import NO_OP, POLICIES

THESIS_GAIN_OVER_MAX_HEIGHT = {"greedy": 0.255, "value_iteration": 0.284}
"""Absolute gain in suction grasp reliability over Max-Height (thesis 4.4.3, figure 4.10)."""
MAX_STEPS = 5
"""Pushes a trial allows in the thesis's experiment (4.4.3), which those gains are of."""


@dataclass
class PolicyTables:
    """What the policies need, as flat arrays over every (object, pose).

    first_pose : (O + 1,) int, row of each object's pose 0; probability, v_s : (N,) float
    actions : dict policy -> (N,) int, the policy's push (NO_OP for none)
    keys : (M,) int64, sorted (row, action) keys of the transitions; next_row : (M,) int;
    cumulative : (M,) float, running sum of the transition probabilities in key order
    """

    object_ids: list[str]
    first_pose: np.ndarray
    probability: np.ndarray
    v_s: np.ndarray
    actions: dict[str, np.ndarray]
    keys: np.ndarray
    next_row: np.ndarray
    cumulative: np.ndarray


ACTION_SPAN = 1 << 20
"""Transition key = row * ACTION_SPAN + action; far above any pose's action count."""


def load_tables(root: str | Path | Dataset) -> PolicyTables:
    """Read the poses table and the transitions of every policy's chosen push."""
    dataset = root if isinstance(root, Dataset) else Dataset.open(root)
    poses = dataset.table(
        "poses",
        columns=["object_id", "pose", "probability", "v_s"] + [f"{p}_action" for p in POLICIES],
    ).sort_by([("object_id", "ascending"), ("pose", "ascending")])
    object_column = poses["object_id"].to_numpy(zero_copy_only=False)
    object_ids, first = np.unique(object_column, return_index=True)
    first_pose = np.append(first, len(object_column))
    # Sorted by (object, pose) with poses numbered 0..P-1: row = first_pose[object] + pose.
    row_of = lambda objects, pose: first[np.searchsorted(object_ids, objects)] + pose  # noqa: E731
    actions = {p: poses[f"{p}_action"].to_numpy() for p in POLICIES}

    # Keys of every policy's chosen pushes (row * ACTION_SPAN + action).
    chosen = np.concatenate([np.flatnonzero(a != NO_OP).astype(np.int64) * ACTION_SPAN + a[a != NO_OP] for a in actions.values()])
    table = dataset.partitioned("transitions", columns=["object_id", "pose", "action", "next_pose", "probability"])
    objects = table["object_id"].to_numpy(zero_copy_only=False)
    rows = row_of(objects, table["pose"].to_numpy())
    action = table["action"].to_numpy()
    keys = rows.astype(np.int64) * ACTION_SPAN + action
    wanted = np.isin(keys, chosen)
    order = np.argsort(keys[wanted], kind="stable")
    keys = keys[wanted][order]
    next_row = row_of(objects, table["next_pose"].to_numpy())[wanted][order]
    probability = table["probability"].to_numpy()[wanted][order]
    return PolicyTables(
        object_ids=list(object_ids),
        first_pose=first_pose,
        probability=poses["probability"].to_numpy(),
        v_s=poses["v_s"].to_numpy(),
        actions=actions,
        keys=keys,
        next_row=next_row,
        cumulative=np.cumsum(probability),
    )


def draw_starts(tables: PolicyTables, n_trials: int, rng: np.random.Generator) -> np.ndarray:
    """Start rows: a uniform object, then one of its poses weighted by drop probability."""
    objects = rng.integers(len(tables.object_ids), size=n_trials)
    lo, hi = tables.first_pose[objects], tables.first_pose[objects + 1]
    # Inverse CDF within each object's poses (probabilities renormalised over the kept poses).
    cumulative = np.concatenate([[0.0], np.cumsum(tables.probability)])
    total = cumulative[hi] - cumulative[lo]
    target = cumulative[lo] + rng.random(n_trials) * total
    return np.clip(np.searchsorted(cumulative, target, side="right") - 1, lo, hi - 1)


def step(tables: PolicyTables, rows: np.ndarray, actions: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """Next rows after pushing ``actions`` in ``rows`` (all of them real pushes)."""
    keys = rows.astype(np.int64) * ACTION_SPAN + actions
    lo = np.searchsorted(tables.keys, keys, side="left")
    hi = np.searchsorted(tables.keys, keys, side="right")
    if np.any(hi <= lo):
        raise ValueError("a policy's push has no stored transitions")
    before = np.where(lo > 0, tables.cumulative[lo - 1], 0.0)
    total = tables.cumulative[hi - 1] - before
    picked = np.searchsorted(tables.cumulative, before + uniforms * total, side="left")
    return tables.next_row[np.clip(picked, lo, hi - 1)]


def run_policy(tables: PolicyTables, policy: str, starts: np.ndarray, uniforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Final rows and number of pushes of ``policy`` from every start.

    uniforms : (max_steps, n) float, the shared draws of each step
    """
    rows = starts.copy()
    pushes = np.zeros(len(rows), dtype=np.int64)
    for draws in uniforms:
        action = tables.actions[policy][rows]
        acting = np.flatnonzero(action != NO_OP)
        if len(acting) == 0:
            break
        rows[acting] = step(tables, rows[acting], action[acting], draws[acting])
        pushes[acting] += 1
    return rows, pushes


def best_pose_value(tables: PolicyTables) -> np.ndarray:
    """(N,) float: the highest V_s among each row's object's poses."""
    per_object = np.maximum.reduceat(tables.v_s, tables.first_pose[:-1])
    return np.repeat(per_object, np.diff(tables.first_pose))


def useful_starts(tables: PolicyTables, rows: np.ndarray) -> np.ndarray:
    """(n,) bool: the start rows where pushing can pay (thesis 4.4.3's useful trials): the object
    is not in its best pose and the Greedy policy would push."""
    return (tables.v_s[rows] < best_pose_value(tables)[rows]) & (tables.actions["greedy"][rows] != NO_OP)


def experiment(root: str | Path | Dataset, n_trials: int = 20_000, max_steps: int = MAX_STEPS, seed: int = 0) -> dict:
    """Run every policy on the same trials; mean V_s gains over the useful ones."""
    tables = load_tables(root)
    rng = np.random.default_rng(seed)
    starts = draw_starts(tables, n_trials, rng)
    uniforms = rng.random((max_steps, n_trials))
    useful = useful_starts(tables, starts)
    result = {"trials": n_trials, "useful_trials": int(useful.sum()), "max_steps": max_steps, "policies": {}}
    for policy in POLICIES:
        final, pushes = run_policy(tables, policy, starts, uniforms)
        gain = tables.v_s[final] - tables.v_s[starts]
        result["policies"][policy] = {
            "mean_gain_useful": _mean(gain[useful]),
            "mean_gain_all": float(gain.mean()),
            "mean_pushes_useful": _mean(pushes[useful]),
            "gains_useful": gain[useful],
        }
    base = result["policies"]["max_height"]["mean_gain_useful"]
    for policy in ("greedy", "value_iteration"):
        mean = result["policies"][policy]["mean_gain_useful"]
        result["policies"][policy]["gain_over_max_height"] = None if base is None else mean - base
    return result


def _mean(values: np.ndarray) -> float | None:
    """The mean, or None for no values (JSON null, as ``policies_physics.mean_se`` gives): a dataset
    without a useful trial has no gain to report, and NaN is not JSON."""
    return float(values.mean()) if len(values) else None


def plot(result: dict, path: str | Path) -> None:
    """The policies' mean gains as bars, written atomically in the format ``path``'s suffix names."""
    import matplotlib

    from ..build.atomic import write_figure_atomic

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4))
    names = list(POLICIES)
    means = [result["policies"][p]["mean_gain_useful"] for p in names]
    # No useful trial: empty bars labelled so, rather than a failed plot.
    axis.bar([n.replace("_", " ") for n in names], [m or 0.0 for m in means], color=["#999999", "#4c78a8", "#f58518"])
    for x, mean in enumerate(means):
        axis.text(x, mean or 0.0, "none useful" if mean is None else f"{mean:+.3f}", ha="center", va="bottom")
    axis.set(
        ylabel="mean change in V_s",
        title=f"Policies on {result['useful_trials']} useful of {result['trials']} trials",
    )
    figure.tight_layout()
    write_figure_atomic(path, figure, dpi=110)
    plt.close(figure)


def summary(result: dict) -> str:
    steps = result["max_steps"]
    lines = [f"{result['useful_trials']} useful trials of {result['trials']} (at most {steps} push{'es' if steps != 1 else ''} each)"]
    if not result["useful_trials"]:
        # Every drop lands in its object's best pose, or where Greedy would not push: a mean over
        # no trials is no number, so the line says so instead of printing nan.
        lines.append("no useful trials (no start where a push can raise V_s): no policy gains to compare")
        return "\n".join(lines)
    for policy in POLICIES:
        r = result["policies"][policy]
        line = f"{policy:16s} mean V_s gain {r['mean_gain_useful']:+.3f} ({r['mean_pushes_useful']:.2f} pushes)"
        if policy in THESIS_GAIN_OVER_MAX_HEIGHT:
            line += f", {100 * r['gain_over_max_height']:+.1f} points over Max-Height"
            # The thesis's figures are of its experiment's pushes until the policy stops; a shorter
            # budget is another experiment, so they are shown only beside the default one.
            if steps == MAX_STEPS:
                line += f" (thesis {100 * THESIS_GAIN_OVER_MAX_HEIGHT[policy]:+.1f})"
        lines.append(line)
    return "\n".join(lines)
