"""Pushes chosen for a budget: value iteration over a finite number of pushes left.

The dataset's value iteration (thesis 4.3, gamma = 0.95) has no budget: a push that
topples with probability 0.1 onto a better pose is worth almost as much as a sure one,
because it can be tried again and again.  A robot that will push at most ``h`` more times
and then grasp wants the push that maximises the expected V_s when the budget is spent:

    V_0(x) = V_s(x)
    Q_h(x, u) = sum_x' P(x' | x, u) V_{h-1}(x')          (no discount: the budget is the limit)
    V_h(x) = max(V_s(x), max_u Q_h(x, u))

With one push left this is the greedy policy (``greedy`` column); as the budget grows it
approaches value iteration without discount.  Played in pybullet with 3 pushes, it ended
-0.001 to +0.039 V_s above value iteration (two seeds, corpus and held-out objects; on
average +0.017; docs/VALIDATION.md, "Pushes for a budget").

Inputs are one object's arrays in the served layout (``service.store.ObjectData``): actions
pose after pose (``action_offsets``), transitions as CSR over action rows
(``transition_offsets``, ``next_pose``, ``probability``), empty unless the push is ok.
numpy only: the service and the pipeline's studies share it.
"""

from __future__ import annotations

import numpy as np

from .vocabulary import NO_OP

MAX_PUSHES_LEFT = 10
"""Largest budget a request may give: beyond a few pushes the choice stops changing."""
IMPROVEMENT = 1e-9
"""A push must beat grasping now by more than this: stored probabilities are float32, so
"stay in this pose" may sum to 1 only within ~1e-7 before the rows are renormalised."""


def choosable_pushes(direction_z: np.ndarray, min_direction_z: float) -> np.ndarray:
    """(N,) bool, the pushes greedy and value iteration may choose: those whose direction's
    vertical component (pose frame, z up) is at least ``min_direction_z`` (``mdp.min_direction_z``).

    Compared in float32, as the served tables store directions, so the dataset job and the
    service choose from the same pushes.  direction_z : (N,) float
    """
    return np.asarray(direction_z, dtype=np.float32) >= np.float32(min_direction_z)


def budget_choices(
    v_s: np.ndarray,
    action_offsets: np.ndarray,
    transition_offsets: np.ndarray,
    next_pose: np.ndarray,
    probability: np.ndarray,
    max_pushes_left: int,
    choosable: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The best push of every pose for every budget from 1 to ``max_pushes_left`` pushes.

    v_s : (P,) float;  action_offsets : (P + 1,) int, pose x's actions are rows
      action_offsets[x] : action_offsets[x + 1];  transition_offsets : (N + 1,) int over the
      N action rows;  next_pose : (K,) int;  probability : (K,) float
    choosable : (N,) bool, the rows a choice may take (``choosable_pushes``); default all
    returns : actions (H, P) int, the action (index within its pose) to push with h = row + 1
      pushes left, NO_OP where grasping now is at least as good; values (H, P) float, V_h:
      the expected V_s when the budget is spent, following these choices
    """
    v_s = np.asarray(v_s, dtype=np.float64)
    n_poses, n_rows = len(v_s), len(transition_offsets) - 1
    counts = np.diff(transition_offsets)
    ok = np.flatnonzero(counts > 0)
    owner = np.repeat(np.arange(n_rows), counts)
    probability = np.asarray(probability, dtype=np.float64)
    probability = probability / np.bincount(owner, weights=probability, minlength=n_rows)[owner]

    actions = np.full((max_pushes_left, n_poses), NO_OP, dtype=np.int64)
    values = np.empty((max_pushes_left, n_poses))
    value = v_s
    if choosable is not None:
        ok = ok[np.asarray(choosable, dtype=bool)[ok]]  # rows no choice may take stay at -inf
    for h in range(max_pushes_left):
        q = np.full(n_rows, -np.inf)
        q[ok] = np.bincount(owner, weights=probability * value[next_pose], minlength=n_rows)[ok]
        best = v_s.copy()
        for x in range(n_poses):
            start, stop = int(action_offsets[x]), int(action_offsets[x + 1])
            if stop > start:
                u = int(np.argmax(q[start:stop]))  # first of equal values: deterministic
                if q[start + u] > v_s[x] + IMPROVEMENT:
                    actions[h, x], best[x] = u, q[start + u]
        values[h] = value = best
    return actions, values


def pose_q(
    value: np.ndarray,
    rows: slice,
    transition_offsets: np.ndarray,
    next_pose: np.ndarray,
    probability: np.ndarray,
) -> np.ndarray:
    """Q_h of one pose's candidates given V_{h-1} (``value``), as ``budget_choices`` computes it
    (each row's probabilities renormalised, then summed in stored order, so the same bits).

    value : (P,) float, V_{h-1} (V_s for one push left);  rows : the pose's action rows
    transition_offsets, next_pose, probability : the object's transitions (``budget_choices``)
    returns : (A,) float, NaN for the rows with no transitions (not ok)
    """
    value = np.asarray(value, dtype=np.float64)
    counts = np.diff(transition_offsets[rows.start : rows.stop + 1])
    span = slice(int(transition_offsets[rows.start]), int(transition_offsets[rows.stop]))
    owner = np.repeat(np.arange(len(counts)), counts)
    weight = np.asarray(probability[span], dtype=np.float64)
    weight = weight / np.bincount(owner, weights=weight, minlength=len(counts))[owner]
    q = np.bincount(owner, weights=weight * value[next_pose[span]], minlength=len(counts))
    return np.where(counts > 0, q, np.nan)


def csr_from_rows(rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One object's per-pose matrices of P(x' | x, u) -> ``budget_choices``' layout.

    rows : P arrays (A_x, P) float, NaN rows for pushes that are not ok
    returns : action_offsets (P + 1,), transition_offsets (N + 1,), next_pose (K,) int,
      probability (K,) float: the nonzero entries, row by row
    """
    n_poses = len(rows)
    stacked = np.concatenate(rows) if rows else np.zeros((0, n_poses))
    action_offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows], dtype=np.int64)])
    values = np.where(np.isnan(stacked).any(axis=1)[:, None], 0.0, stacked)
    row, column = np.nonzero(values > 0)  # row-major: sorted by row
    transition_offsets = np.concatenate([[0], np.cumsum(np.bincount(row, minlength=len(stacked)))])
    return action_offsets, transition_offsets, column, values[row, column]
