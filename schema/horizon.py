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

A build that believes its failures (``mdp.believe_failures``, the default) serves the same
budget over a fresh and a failed-here state per pose (``belief_budget_choices``, docs/MODEL.md
(12.14)): a push that leaves the object where it was says the pose's pushes topple less than
the table's P, so a failure is not worth a fresh retry.  It made +0.008 V_s more than the
table's budget on corpus objects, +0.007 on held-out ones (docs/VALIDATION.md, "The budget
believing failures").

Inputs are one object's arrays in the served layout (``service.store.ObjectData``): actions
pose after pose (``action_offsets``), transitions as CSR over action rows
(``transition_offsets``, ``next_pose``, ``probability``), empty unless the push is ok.
numpy only: the service and the pipeline's studies share it.
"""

from __future__ import annotations

import numpy as np

from . import retry
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
    A limit at or below -1 passes every push without reading ``direction_z``: no unit direction's z
    lies below it, and the service's directions are a memory-mapped column (the default budget's
    limit would map 26 MB of it for nothing).
    """
    if min_direction_z <= -1.0:
        return np.ones(len(direction_z), dtype=bool)
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
        actions[h], values[h] = _best_per_pose(q, v_s, action_offsets)
        value = values[h]
    return actions, values


def _best_per_pose(q: np.ndarray, v_s: np.ndarray, action_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose the push of largest ``q`` if it beats grasping now by ``IMPROVEMENT``.

    q : (N,) float, -inf for rows no choice may take;  v_s : (P,) float
    returns : action (P,) int (index within its pose, NO_OP: grasp), value (P,) float (V_s on NO_OP)
    """
    actions = np.full(len(v_s), NO_OP, dtype=np.int64)
    best = np.array(v_s, dtype=np.float64)
    for x in range(len(v_s)):
        start, stop = int(action_offsets[x]), int(action_offsets[x + 1])
        if stop > start:
            u = int(np.argmax(q[start:stop]))  # first of equal values: deterministic
            if q[start + u] > v_s[x] + IMPROVEMENT:
                actions[x], best[x] = u, q[start + u]
    return actions, best


def belief_budget_choices(
    v_s: np.ndarray,
    action_offsets: np.ndarray,
    transition_offsets: np.ndarray,
    next_pose: np.ndarray,
    probability: np.ndarray,
    max_pushes_left: int,
    power: float,
    choosable: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``budget_choices`` for a robot that reports its failures: the budget over the fresh and
    failed-here states of each pose (docs/MODEL.md (12.14)).

    A push that left the object where it was is news about the pose: from there a push of
    P(topple) p topples with p^k (k = ``power``, ``schema.retry.after_failure``) and lands where
    its row's topples land.  With S_h(x, u) = sum_{x' != x} P(x' | x, u) V0_{h-1}(x'):

        V0_0 = V1_0 = V_s
        Q0_h = S_h + (1 - p) V1_{h-1}(x),   Q1_h = p^(k-1) S_h + (1 - p^k) V1_{h-1}(x)
        V_i,h(x) = max(V_s(x), max_u Q_i,h(x, u))  over the choosable pushes

    k = 1 believes nothing: V1 = V0 and Q0_h is ``budget_choices``' Q_h.

    v_s, action_offsets, transition_offsets, next_pose, probability, max_pushes_left,
      choosable : as ``budget_choices``;  power : k >= 1
    returns : actions (H, P) int, the fresh pose's push with h = row + 1 pushes left (NO_OP:
      grasp now); fresh (H, P) float, V0_h; failed (H, P) float, V1_h, the value of a pose
      where a push has just failed (its best push by Q1_h: ``pose_belief_q``)
    """
    if not power >= 1.0:
        raise ValueError(f"belief_budget_choices needs power >= 1, got {power}")
    v_s = np.asarray(v_s, dtype=np.float64)
    n_poses, n_rows = len(v_s), len(transition_offsets) - 1
    rows = _BeliefTerms.of(np.repeat(np.arange(n_poses), np.diff(action_offsets)), transition_offsets, next_pose, probability, power)
    ok = np.flatnonzero(np.diff(transition_offsets) > 0)
    if choosable is not None:
        ok = ok[np.asarray(choosable, dtype=bool)[ok]]
    actions = np.full((max_pushes_left, n_poses), NO_OP, dtype=np.int64)
    fresh, failed = np.empty((max_pushes_left, n_poses)), np.empty((max_pushes_left, n_poses))
    value0, value1 = v_s, v_s
    for h in range(max_pushes_left):
        q0, q1 = rows.q(value0, value1)
        best0, best1 = np.full(n_rows, -np.inf), np.full(n_rows, -np.inf)
        best0[ok], best1[ok] = q0[ok], q1[ok]
        actions[h], fresh[h] = _best_per_pose(best0, v_s, action_offsets)
        _, failed[h] = _best_per_pose(best1, v_s, action_offsets)
        value0, value1 = fresh[h], failed[h]
    return actions, fresh, failed


def solve_budgets(v_s: np.ndarray, csr: tuple, max_pushes_left: int, belief_power: float | None,
                  choosable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The budgets a build serves: (12.14) (``belief_budget_choices``) when it plans with its
    failures (``belief_power``, its k), else (12.8) (``budget_choices``), whose V1 is its V0.
    csr : (action_offsets, transition_offsets, next_pose, probability), ``csr_from_rows``' layout;
    v_s, max_pushes_left, choosable : as ``budget_choices``;  returns : actions, V0, V1, (H, P) each"""
    if belief_power is None:
        actions, values = budget_choices(v_s, *csr, max_pushes_left, choosable)
        return actions, values, values
    return belief_budget_choices(v_s, *csr, max_pushes_left, belief_power, choosable)


def budget_q(
    v_s: np.ndarray,
    fresh: np.ndarray,
    failed: np.ndarray,
    pushes_left: int,
    pose: int,
    rows: slice,
    transition_offsets: np.ndarray,
    next_pose: np.ndarray,
    probability: np.ndarray,
    belief_power: float | None,
    after_failure: bool,
) -> np.ndarray:
    """What ranks the pushes of ``pose`` with ``pushes_left`` pushes left, given ``solve_budgets``'
    V0 and V1 (``fresh``, ``failed``): Q0_h of (12.14) fresh and Q1_h once a push from the pose has
    failed (``after_failure``) when the build plans with its failures (``belief_power``), else (12.8)'s
    Q_h (``pose_q``), which a failure does not change.  returns : (A,) float, NaN unless ok"""
    fresh, failed = values_before(v_s, fresh, failed, pushes_left)
    if belief_power is None:
        return pose_q(fresh, rows, transition_offsets, next_pose, probability)
    q0, q1 = pose_belief_q(fresh, failed, pose, rows, transition_offsets, next_pose, probability, belief_power)
    return q1 if after_failure else q0


def values_before(v_s: np.ndarray, fresh: np.ndarray, failed: np.ndarray, pushes_left: int) -> tuple[np.ndarray, np.ndarray]:
    """V0_{h-1} and V1_{h-1} for h = ``pushes_left`` pushes left: ``belief_budget_choices``' rows
    h - 2 (``fresh``, ``failed``: (H, P) each), or V_s twice with one push left (nothing after it).
    returns : two (P,) float arrays"""
    if not 1 <= pushes_left <= len(fresh):
        raise ValueError(f"pushes_left must be 1..{len(fresh)}, got {pushes_left}")
    return (v_s, v_s) if pushes_left == 1 else (fresh[pushes_left - 2], failed[pushes_left - 2])


def pose_belief_q(
    fresh: np.ndarray,
    failed: np.ndarray,
    pose: int,
    rows: slice,
    transition_offsets: np.ndarray,
    next_pose: np.ndarray,
    probability: np.ndarray,
    power: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Q0_h and Q1_h of one pose's candidates given V0_{h-1} and V1_{h-1} (``fresh``, ``failed``;
    V_s for one push left), as ``belief_budget_choices`` computes them (the same bits).

    pose : the pose the rows push from;  rows : its action rows;  transition_offsets,
      next_pose, probability : the object's transitions (``budget_choices``);  power : k >= 1
    returns : q0, q1 (A,) float, NaN for the rows with no transitions (not ok)
    """
    if not power >= 1.0:
        raise ValueError(f"pose_belief_q needs power >= 1, got {power}")
    counts = np.diff(transition_offsets[rows.start : rows.stop + 1])
    span = slice(int(transition_offsets[rows.start]), int(transition_offsets[rows.stop]))
    terms = _BeliefTerms.of(np.full(len(counts), pose), np.concatenate([[0], np.cumsum(counts)]), next_pose[span],
                            probability[span], power)
    q0, q1 = terms.q(np.asarray(fresh, dtype=np.float64), np.asarray(failed, dtype=np.float64))
    return np.where(counts > 0, q0, np.nan), np.where(counts > 0, q1, np.nan)


class _BeliefTerms:
    """The per-row terms of (12.14) over CSR transitions: owner (K,) int, each transition's row;
    row_pose (N,) int, the pose each row pushes from; weight (K,) float, the row-normalised
    probabilities of the transitions that leave the row's pose (0 for those that stay); stay
    (N,) float, P(x | x, u); failed_ratio, failed_topple (N,) float, p^(k-1) and
    p^k (``retry.failed_ratios``)."""

    def __init__(self, owner, row_pose, next_pose, weight, stay, failed_ratio, failed_topple):
        self.owner, self.row_pose, self.next_pose, self.weight = owner, row_pose, next_pose, weight
        self.stay, self.failed_ratio, self.failed_topple = stay, failed_ratio, failed_topple

    @classmethod
    def of(cls, row_pose: np.ndarray, transition_offsets: np.ndarray, next_pose: np.ndarray, probability: np.ndarray,
           power: float) -> _BeliefTerms:
        n_rows = len(transition_offsets) - 1
        owner = np.repeat(np.arange(n_rows), np.diff(transition_offsets))
        weight = np.asarray(probability, dtype=np.float64)
        weight = weight / np.bincount(owner, weights=weight, minlength=n_rows)[owner]
        own = np.asarray(next_pose) == row_pose[owner]
        stay = np.bincount(owner, weights=np.where(own, weight, 0.0), minlength=n_rows)
        return cls(owner, row_pose, np.asarray(next_pose), np.where(own, 0.0, weight), stay, *retry.failed_ratios(1.0 - stay, power))

    def q(self, fresh: np.ndarray, failed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Q0, Q1) of every row, (N,) float each, from V0_{h-1} and V1_{h-1} ((P,) float)."""
        leave = np.bincount(self.owner, weights=self.weight * fresh[self.next_pose], minlength=len(self.stay))
        here = failed[self.row_pose]
        return leave + self.stay * here, self.failed_ratio * leave + (1.0 - self.failed_topple) * here


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
