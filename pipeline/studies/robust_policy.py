"""A push choice robust to the model's own error: value iteration over neighbourhood-smoothed Q.

Greedy and value iteration take the argmax of ~1,000 candidate pushes per pose.  Each
candidate's P(x' | x, u) is a Monte Carlo estimate (``topple.n_trials`` draws) of a model
that is itself wrong by some contact error, so the argmax prefers the candidates whose
estimate is most *over*-stated (the winner's curse): the chosen pushes are predicted to
topple about 0.50 of the time and topple 0.35 in physics (``reports/policies_physics.json``).

``smoothed_vi`` ranks each candidate by the mean Q_T of the ``ok`` candidates of the same
pose whose contact point lies within ``radius`` of its own and whose push direction is
within ``max_angle`` of its own (the candidate included).  Q is linear in the transition
row, so this is the Q_T of the push under an extra contact/direction error of that size
(its neighbours' outcomes averaged), and averaging k estimates shrinks the Monte Carlo
noise the argmax feeds on.  A pose pushes only where gamma * (smoothed Q) beats V_s, as
value iteration does with the raw Q; a candidate with fewer than ``min_neighbours`` ok
neighbours is not chosen (a lone push on a sliver of the hull is exactly the fragile kind).

Only the dataset's tables are read (``point``, ``direction``, ``status``, ``q``,
``p_topple``), so the policy could be stored as a fourth policy column; here it is a study:

    python -m pipeline.studies.robust_policy DATASET --trials 600 [--radius 0.02 --max-angle 0.5 --min-neighbours 5]

plays max_height, value_iteration, ``smoothed_vi``, ``horizon_vi`` (value iteration for
the experiment's push budget, ``schema.horizon``), ``untried_vi`` (what /plan's
``failed_actions`` serves), ``once_vi`` (value iteration without retries, docs/MODEL.md
(12.9)), ``aware_vi`` (``untried_vi`` ranking the pushes after a failure by their believed
P(topple)^k, ``aware_choice``), ``belief_vi`` (12.13) and ``belief_horizon_vi`` (12.14, what
``/plan`` serves for ``pushes_left`` in a build that believes failures), ``budget_vi`` (its fresh push only, a
client that sends ``pushes_left`` and not its failures) and ``chosen_horizon_vi`` (``horizon_vi`` choosing by
neighbourhood, (12.15)) in pybullet from the same starts and
noise draws as ``toppledb policies-physics`` (common random numbers, so max_height and
value_iteration reproduce that report's numbers), and reports each policy's V_s gain over
max_height on useful trials, the 'never push' baseline, and predicted (raw and smoothed)
against physical topple rates of the chosen pushes, where their topples came to rest against where
the model lands them (``landing_summary``), with per-push diagnostics.  With ``--landing-prior ALPHA``
it also plays value iteration, ``belief_vi`` and ``belief_horizon_vi`` planned over rows whose landings
are shrunk toward their pose's mean landing by their topple count (``landing_prior_rows``,
``PRIOR_POLICIES``), each against its counterpart (with ``--landing-trust U...`` over landings moved by the
landing pose's drop probability instead, and with ``--landing-direction LAMBDA...`` by the push's direction,
``landing_direction.doubted_rows``); with ``--gamma G``, ``--min-direction-z Z``,
``--choice-radius R`` and/or ``--choose-for-repeats [--repeats-then-grasp]``, value iteration, ``belief_vi``,
``smoothed_vi`` and ``aware_vi`` planned under that MDP instead of the dataset's (``VARIANT_POLICIES``: another
discount, other choosable pushes, another choice of value iteration's push), each against its counterpart, so
one run pairs the two MDPs trial by trial.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from schema import horizon, neighbourhood, retry
from schema.reader import Dataset
from schema.vocabulary import NO_OP, STATUS_NAMES, STATUS_OK

from ..build.atomic import write_text_atomic
from ..model.config import Config, MDPConfig, field_range
from ..model.landing_direction import CLASSES as DIRECTION_CLASSES
from ..model.landing_direction import checked_doubts, doubted_rows, leaving_shares
from ..model.landing_trust import BANDS as TRUST_BANDS
from ..model.landing_trust import checked_shares, trusted_rows
from ..model.mdp import IMPROVEMENT, belief_value_iteration, choice_by_means, pose_values, value_iteration_policy
from ..model.rng import stream
from .policies_physics import PURPOSE, ExperimentError, ObjectPlan, load_planned, mean_se, object_plans, open_trials, world_config
from .policy_experiment import useful_starts
from .pushsim import (
    DEFAULT_PLAYER,
    PlayerSettings,
    add_player_options,
    body_model,
    draw_noise,
    play_push,
    player_from_args,
    player_parameters,
)

ROBUST_POLICY = "smoothed_vi"
"""Name of the robust policy (a fourth ``<name>_action`` column if the contract adopts it)."""
HORIZON_POLICY = "horizon_vi"
"""Value iteration solved for the experiment's push budget (``horizon_actions``)."""
SMOOTHED_HORIZON_POLICY = "smoothed_horizon_vi"
"""``horizon_vi`` over the neighbourhood-smoothed transitions (``PoseScores.smoothed_rows``)."""
UNTRIED_POLICY = "untried_vi"
"""Value iteration that does not push again where a push failed (``untried_choice``)."""
ONCE_POLICY = "once_vi"
"""Value iteration that does not count on retrying a failed push (``mdp.retry_failed = false``,
docs/MODEL.md (12.9)), from the dataset's transitions (``once_actions``)."""
AWARE_POLICY = "aware_vi"
"""``untried_vi`` that, after a failure, ranks the untried pushes by what it now believes of them
(``aware_choice``: P(topple)^k, ``mdp.after_failure_power``), a failure worth the grasp now."""
BELIEF_POLICY = "belief_vi"
"""Value iteration that believes its own failures from the first push on (``belief_tables``,
docs/MODEL.md (12.13)): a failure is valued at the failed state's V1, and after one the untried
pushes are ranked by Q1."""
BELIEF_HORIZON_POLICY = "belief_horizon_vi"
"""``horizon_vi`` over the fresh and failed-here states of ``belief_vi`` (``belief_budget_tables``):
Q0_h in a fresh pose, Q1_h over the pushes no failure ruled out after one, h the pushes left."""
BUDGET_POLICY = "budget_vi"
"""``belief_horizon_vi``'s fresh-pose push with h pushes left, in whatever pose, for a client that sends ``/plan``
its ``pushes_left`` and not its failures: Q0_h of (12.14) after a failure too, as a fresh ask with one push fewer."""
CHOSEN_HORIZON_POLICY = "chosen_horizon_vi"
"""``horizon_vi`` whose push is chosen as value iteration's is ((12.15)): the choosable push of highest
neighbourhood-mean Q_h among those with enough neighbours (``chosen_horizon_actions``)."""
CHALLENGERS = (ROBUST_POLICY, HORIZON_POLICY, SMOOTHED_HORIZON_POLICY, UNTRIED_POLICY, ONCE_POLICY, AWARE_POLICY,
               BELIEF_POLICY, BELIEF_HORIZON_POLICY, BUDGET_POLICY, CHOSEN_HORIZON_POLICY)
"""The policies each compared with value iteration, paired."""
PRIOR_POLICY = "prior_vi"
PRIOR_BELIEF_POLICY = "prior_belief_vi"
PRIOR_BELIEF_HORIZON_POLICY = "prior_belief_horizon_vi"
PRIOR_POLICIES = {PRIOR_POLICY: "value_iteration", PRIOR_BELIEF_POLICY: BELIEF_POLICY,
                  PRIOR_BELIEF_HORIZON_POLICY: BELIEF_HORIZON_POLICY}
"""Played only with a landing prior (``--landing-prior``): each the policy it maps to, planned over
``landing_prior_rows``, and compared with that policy, paired (stop 40; measured, not served)."""
VARIANT_POLICY = "variant_vi"
VARIANT_BELIEF_POLICY = "variant_belief_vi"
VARIANT_ROBUST_POLICY = "variant_smoothed_vi"
VARIANT_AWARE_POLICY = "variant_aware_vi"
VARIANT_POLICIES = {VARIANT_POLICY: "value_iteration", VARIANT_BELIEF_POLICY: BELIEF_POLICY, VARIANT_ROBUST_POLICY: ROBUST_POLICY,
                    VARIANT_AWARE_POLICY: AWARE_POLICY}
"""Played only under another MDP (``experiment``'s ``variant``: a discount, a cut on the choosable
pushes, a choice for the client that repeats): value iteration, ``belief_vi``, ``smoothed_vi`` and
``aware_vi`` (the variant's value iteration until a push fails, then ``aware_choice`` over the variant's Q,
what ``/plan`` with ``failed_actions`` would serve from a build under it) planned under it over the
dataset's rows, each compared with the same policy under the dataset's MDP, paired (stops 44, 47)."""
VARIANT_FIELDS = ("gamma", "min_direction_z", "choice_radius", "choose_for_repeats", "repeats_then_grasp")
"""The ``mdp`` fields a variant may change."""
COUNTERPARTS = {**PRIOR_POLICIES, **VARIANT_POLICIES}
"""Every optional policy and the policy it is compared with."""
REPORTS_FAILURES = (UNTRIED_POLICY, AWARE_POLICY, BELIEF_POLICY, BELIEF_HORIZON_POLICY, PRIOR_BELIEF_POLICY,
                    PRIOR_BELIEF_HORIZON_POLICY, VARIANT_BELIEF_POLICY, VARIANT_AWARE_POLICY)
"""The policies played as a client that tells /plan its failed pushes: where a push of the trial
has failed they choose among the candidates no failure ruled out (``after_failure_choice``)."""
COMPARED = ("max_height", "value_iteration", *CHALLENGERS)
"""Policies the study plays (common random numbers: adding one changes no other's pushes, though a
trial that any played policy leaves the pose set in is dropped for all, ``trial_gains``)."""


@dataclass(frozen=True)
class Smoothing:
    """The neighbourhood of a candidate push.

    radius : m, largest distance between contact points;  max_angle : rad, largest angle
    between push directions;  min_neighbours : fewest ok candidates (itself included) a
    candidate needs to be chosen
    """

    # Chosen on corpus objects only, for the calibration of the chosen pushes (docs/VALIDATION.md,
    # "Robust push choice"); 5 and 10 mm gave the same V_s gain within its error.
    radius: float = neighbourhood.RADIUS
    max_angle: float = neighbourhood.MAX_ANGLE
    min_neighbours: int = 5

    def __post_init__(self):
        if not (self.radius >= 0 and self.max_angle >= 0 and self.min_neighbours >= 1):
            raise ValueError(f"smoothing needs radius >= 0, max_angle >= 0, min_neighbours >= 1, got {self}")


@dataclass(frozen=True)
class Exclusion:
    """What a failed push rules out for the rest of a trial (``untried_vi``): the candidates of
    the same pose within ``radius`` (m) and ``max_angle`` (rad) of it, itself included."""

    radius: float = neighbourhood.RADIUS
    max_angle: float = neighbourhood.MAX_ANGLE

    def __post_init__(self):
        if not (self.radius >= 0 and self.max_angle >= 0):
            raise ValueError(f"exclusion needs radius >= 0 and max_angle >= 0, got {self}")


def neighbour_mean(points: np.ndarray, directions: np.ndarray, values: np.ndarray, smoothing: Smoothing) -> tuple[np.ndarray, np.ndarray]:
    """``schema.neighbourhood.neighbour_mean`` of every candidate with ``smoothing``'s limits
    (the service reports the same mean beside each chosen push)."""
    return neighbourhood.neighbour_mean(points, directions, values, smoothing.radius, smoothing.max_angle)


def smoothed_choice(v_s_pose: float, smoothed_q: np.ndarray, count: np.ndarray, gamma: float, min_neighbours: int,
                    q: np.ndarray) -> int:
    """argmax of the smoothed Q among candidates with enough neighbours, or of ``q`` where none has
    them; NO_OP unless it beats V_s (``pipeline.model.mdp.choice_by_means``, the rule of the stored push).

    v_s_pose : V_s of this pose;  smoothed_q, count : (A,) from ``neighbour_mean``, NaN where the
    candidate may not be chosen;  q : (A,) float, the candidates' own Q_T
    returns : action index, or NO_OP
    """
    smoothed_q = np.asarray(smoothed_q, dtype=float)
    return choice_by_means(v_s_pose, smoothed_q, count, q, np.isfinite(smoothed_q), gamma, min_neighbours)


def untried_choice(pose: int, v_s: np.ndarray, q: np.ndarray, failed: np.ndarray, gamma: float) -> int:
    """Value iteration's push among the candidates no failed push of this pose has ruled out.

    Played pushes are nearly deterministic (a replay of the held-out log's pushes with other
    noise draws predicts them with Brier score 0.010, docs/VALIDATION.md "Physics predicting
    itself"), so a push that left the object in its pose will almost surely fail again, and so
    will its neighbours; value iteration's table treats every push as a fresh draw.
    pose : int;  v_s : (P,) float;  q : (A,) float, Q_T of this pose (NaN unless ok)
    failed : (A,) bool, candidates ruled out by this trial's failed pushes from this pose
    returns : action index, or NO_OP
    """
    return value_iteration_policy(pose, v_s, np.where(failed, np.nan, q), gamma).action


def aware_choice(pose: int, v_s: np.ndarray, q: np.ndarray, p_topple: np.ndarray, ruled_out: np.ndarray,
                 choosable: np.ndarray, gamma: float, power: float, retry_failed: bool = True, *, believes: bool = False) -> int:
    """After a failure: the untried push of most believed value, pushed if it beats grasping now
    (``schema.retry.ranking_values``, what /plan serves).

    The table's Q_T(x, u) = p T + (1 - p) V_T(x), T the mean V_T of where a topple lands.  Once
    a push from x has failed, u topples with p^k (``schema.retry.after_failure``), and a push
    that fails again is worth the grasp here, so

        Q''(x, u) = V_s(x) + p^k (T - V_s(x)) = V_s(x) + p^(k-1) (Q_T - (1 - p) V_T(x)) - p^k V_s(x)

    with the stored V_T(x) = max(V_s(x), gamma max Q_T over the choosable pushes).  From a dataset
    built believing failures (``believes``, docs/MODEL.md (12.13)) q is Q0 and the ranking is Q1.
    pose : int;  v_s : (P,) float;  q, p_topple : (A,) float, NaN unless ok
    ruled_out, choosable : (A,) bool;  power : k;  returns : action index, or NO_OP
    """
    stay = float(v_s[pose])
    mine = np.where(choosable, q, np.nan)
    v_t = max(stay, gamma * float(np.nanmax(mine))) if np.isfinite(mine).any() else stay
    believed = retry.ranking_values(q, p_topple, stay, v_t, power, retry_failed, believes=believes, gamma=gamma, choosable=choosable)
    return retry.best_untried(believed, choosable & ~ruled_out, stay, IMPROVEMENT, scale=gamma)


@dataclass
class PoseCandidates:
    """One pose's candidate pushes as read from the actions table (index = action id).

    points, directions : (A, 3) float, pose frame;  q, p_topple, mean_force : (A,) float,
    NaN unless ok
    """

    points: np.ndarray
    directions: np.ndarray
    q: np.ndarray
    p_topple: np.ndarray
    mean_force: np.ndarray


def read_candidates(dataset: Dataset, object_id: str) -> list[PoseCandidates]:
    """Every pose's candidates of one object, in pose order."""
    columns = ["pose", "action", "status", "q", "p_topple", "mean_force"] + [f"{c}_{a}" for c in ("point", "direction") for a in "xyz"]
    table = dataset.object_rows("actions", object_id, columns=columns)

    def array(name):  # nulls of float columns arrive as NaN
        return table[name].to_numpy(zero_copy_only=False).astype(float)

    pose, action = (table[name].to_numpy(zero_copy_only=False) for name in ("pose", "action"))
    ok = table["status"].to_numpy(zero_copy_only=False) == STATUS_NAMES[STATUS_OK]
    order = np.lexsort((action, pose))
    out = []
    for x in range(int(pose.max()) + 1 if len(pose) else 0):
        rows = order[pose[order] == x]
        if not np.array_equal(action[rows], np.arange(len(rows))):
            raise ExperimentError(f"{object_id}: pose {x}'s actions are not numbered 0..A-1")
        # null (not ok) entries arrive as NaN; mask by status as well, so only ok candidates count.
        masked = {name: np.where(ok[rows], array(name)[rows], np.nan) for name in ("q", "p_topple", "mean_force")}
        out.append(PoseCandidates(
            points=np.stack([array(f"point_{a}")[rows] for a in "xyz"], axis=1),
            directions=np.stack([array(f"direction_{a}")[rows] for a in "xyz"], axis=1),
            **masked,
        ))
    return out


@dataclass
class PoseScores:
    """Per-candidate scores of one pose.  q : (A,) float, the candidates' own Q_T, which a pose too
    sparse for any neighbourhood chooses by;  smoothed_q, smoothed_p : (A,) float;  count : (A,) int;
    smoothed_rows : (A, P) float, each candidate's mean next-pose row over its neighbours (NaN
    with fewer than ``min_neighbours``), when the rows were given."""

    q: np.ndarray
    smoothed_q: np.ndarray
    smoothed_p: np.ndarray
    count: np.ndarray
    smoothed_rows: np.ndarray | None = None


def pose_scores(candidates: PoseCandidates, smoothing: Smoothing, rows: np.ndarray | None = None) -> PoseScores:
    """Neighbourhood means of Q_T and of P(topple) for every candidate of a pose, and of its
    next-pose rows ``rows`` ((A, P), NaN unless ok) when given: the transitions under an extra
    contact and direction error of ``smoothing``'s size (``smoothed_horizon_vi``)."""
    # q, p_topple and the rows are finite on the same (ok) candidates, so one pass smooths them all.
    values = [candidates.q[:, None], candidates.p_topple[:, None], *([] if rows is None else [rows])]
    means, count = neighbour_mean(candidates.points, candidates.directions, np.hstack(values), smoothing)
    smoothed_rows = None
    if rows is not None:
        smoothed_rows = means[:, 2:]
        smoothed_rows[count < smoothing.min_neighbours] = np.nan
    return PoseScores(candidates.q, means[:, 0], means[:, 1], count, smoothed_rows)


def robust_actions(v_s: np.ndarray, scores: list[PoseScores], gamma: float, smoothing: Smoothing,
                   choosable: list[np.ndarray] | None = None) -> np.ndarray:
    """(P,) int, ``smoothed_vi``'s action per pose (NO_OP: no push), among each pose's
    ``choosable`` pushes ((A_x,) bool, ``schema.horizon.choosable_pushes``; default all)."""
    return np.array([smoothed_choice(float(v_s[x]), s.smoothed_q if choosable is None else np.where(choosable[x], s.smoothed_q, np.nan),
                                     s.count, gamma, smoothing.min_neighbours, s.q)
                     for x, s in enumerate(scores)], dtype=np.int64)


def next_pose_rows(dataset: Dataset, object_id: str, n_actions: list[int]) -> list[np.ndarray]:
    """Each pose's (A_x, P) matrix of P(x' | x, u) from the transitions table; NaN rows unless ok."""
    table = dataset.object_rows("transitions", object_id, columns=["pose", "action", "next_pose", "probability"])
    pose, action, next_pose, probability = (table[name].to_numpy(zero_copy_only=False)
                                            for name in ("pose", "action", "next_pose", "probability"))
    rows = []
    for x, count in enumerate(n_actions):
        matrix = np.zeros((count, len(n_actions)))
        mine = pose == x
        matrix[action[mine], next_pose[mine]] = probability[mine]
        matrix[np.bincount(action[mine], minlength=count) == 0] = np.nan  # no transitions: not ok
        rows.append(matrix)
    return rows


def value_iteration_actions(v_s: np.ndarray, rows: list[np.ndarray], mdp: MDPConfig,
                            choosable: list[np.ndarray] | None = None,
                            candidates: list[PoseCandidates] | None = None) -> np.ndarray:
    """(P,) int: value iteration's push per pose under ``mdp`` (``pipeline.model.mdp.pose_values``)
    over ``next_pose_rows`` or rows made from them; NO_OP: grasp.  choosable : as ``robust_actions``;
    candidates : each pose's pushes, which a choice by neighbourhood (``mdp.choice_radius``) needs."""
    values = pose_values(rows, v_s, [-1] * len(rows), mdp, choosable, _pushes(candidates))
    return np.array([v.policies["value_iteration"].action for v in values], dtype=np.int64)


def once_actions(v_s: np.ndarray, rows: list[np.ndarray], mdp: MDPConfig, choosable: list[np.ndarray] | None = None,
                 candidates: list[PoseCandidates] | None = None) -> np.ndarray:
    """(P,) int: value iteration's push per pose without retries (``mdp`` with
    ``retry_failed = False``, docs/MODEL.md (12.9)); NO_OP: grasp."""
    return value_iteration_actions(v_s, rows, replace(mdp, retry_failed=False, believe_failures=False), choosable, candidates)


def _pushes(candidates: list[PoseCandidates] | None) -> list[tuple[np.ndarray, np.ndarray]] | None:
    return None if candidates is None else [(c.points, c.directions) for c in candidates]


def belief_tables(v_s: np.ndarray, rows: list[np.ndarray], mdp: MDPConfig,
                  choosable: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """``belief_vi``'s push per fresh pose, (P,) int (NO_OP: grasp), and each pose's Q1, (A_x,)
    float, which ranks its pushes once one has failed (``pipeline.model.mdp.belief_value_iteration``
    with k = ``mdp.after_failure_power``, over ``next_pose_rows``)."""
    _, _, q0, q1 = belief_value_iteration(rows, v_s, mdp.gamma, mdp.after_failure_power, mdp.tolerance,
                                          mdp.max_iterations, choosable)
    first = [retry.best_untried(q, allowed, float(v_s[x]), IMPROVEMENT, scale=mdp.gamma)
             for x, (q, allowed) in enumerate(zip(q0, choosable))]
    return np.array(first, dtype=np.int64), q1


def belief_budget_tables(v_s: np.ndarray, rows: list[np.ndarray], mdp: MDPConfig, pushes: int,
                         choosable: list[np.ndarray]) -> tuple[np.ndarray, list[list[np.ndarray]]]:
    """``belief_horizon_vi``'s push per fresh pose with ``pushes - k`` pushes left (row k, as
    ``horizon_actions``), (pushes, P) int, and Q1_h per pose in the same row order, which ranks
    the pushes once one has failed: ``schema.horizon.belief_budget_choices`` and ``pose_belief_q``
    over ``next_pose_rows``, as ``/plan`` serves ``pushes_left``."""
    action_offsets, transition_offsets, next_pose, probability = csr = horizon.csr_from_rows(rows)
    actions, fresh, failed = horizon.belief_budget_choices(v_s, *csr, pushes, mdp.after_failure_power, _row_mask(choosable))
    q1s = [[horizon.budget_q(v_s, fresh, failed, h, x, slice(int(action_offsets[x]), int(action_offsets[x + 1])),
                             transition_offsets, next_pose, probability, mdp.after_failure_power, after_failure=True)
            for x in range(len(v_s))] for h in range(1, pushes + 1)]
    return actions[::-1], q1s[::-1]


def horizon_actions(v_s: np.ndarray, rows: list[np.ndarray], pushes: int, choosable: list[np.ndarray] | None = None) -> np.ndarray:
    """(pushes, P) int: ``horizon_vi``'s push per pose with ``pushes - k`` pushes left (row k).

    ``schema.horizon.budget_choices`` (finite-horizon value iteration, (12.8), as ``/plan``
    serves ``pushes_left`` in a build that does not believe failures) over ``next_pose_rows``.  The table's probabilities are float64, the
    service's float32: where two pushes' values differ by less than that rounding (~1e-8; 13
    of 2,709 pose-budgets of the default dataset's first 80 objects, 3 pushes) the two may
    pick different pushes of equal value.  choosable : per pose (A_x,) bool, as ``robust_actions``.
    """
    actions, _ = horizon.budget_choices(v_s, *horizon.csr_from_rows(rows), pushes, _row_mask(choosable))
    return actions[::-1]  # row k: pushes - k left, the order the pushes are played in


def _row_mask(choosable: list[np.ndarray] | None) -> np.ndarray | None:
    """Per-pose choosable masks as one mask over ``horizon.csr_from_rows``' action rows (None: every push)."""
    return None if choosable is None else np.concatenate([np.zeros(0, dtype=bool), *choosable])


def chosen_horizon_actions(v_s: np.ndarray, rows: list[np.ndarray], scores: list[PoseScores], pushes: int,
                           choosable: list[np.ndarray], min_neighbours: int) -> np.ndarray:
    """(pushes, P) int: ``chosen_horizon_vi``'s push per pose with ``pushes - k`` pushes left (row k).

    The values are (12.8)'s, V_{h-1} of ``horizon.budget_choices``; only the choice moves, as (12.15) moves value
    iteration's: the push of highest mean Q_h over its neighbourhood, which is its smoothed row times V_{h-1}
    (``PoseScores.smoothed_rows``, NaN with fewer than ``min_neighbours``), pushed iff that beats V_s
    (``mdp.choice_by_means`` undiscounted; a pose where no choosable push has the neighbours takes argmax Q_h).
    rows : per pose (A_x, P) (``next_pose_rows``);  scores : per pose, with ``smoothed_rows``;  choosable : per pose (A_x,) bool
    """
    _, values = horizon.budget_choices(v_s, *horizon.csr_from_rows(rows), pushes, _row_mask(choosable))
    actions = np.full((pushes, len(v_s)), NO_OP, dtype=np.int64)
    for h in range(pushes):
        before = np.asarray(v_s, dtype=float) if h == 0 else values[h - 1]
        for x, (row, score) in enumerate(zip(rows, scores)):
            if len(row):
                actions[h, x] = choice_by_means(float(v_s[x]), score.smoothed_rows @ before, score.count, row @ before,
                                                choosable[x], 1.0, min_neighbours)
    return actions[::-1]  # row k: pushes - k left, as horizon_actions


@dataclass
class Landings:
    """Where the model lands each candidate push of one pose when it topples.

    share : (A, P) float, P(x' | x, u) over the leaving part of the row, 0 at x and on rows
      where nothing leaves;  pose : (A,) int, the likeliest x' (the first of equal shares), -1
      where nothing leaves;  v_s : (A,) float, the mean V_s of x' under ``share``, NaN there"""

    share: np.ndarray
    pose: np.ndarray
    v_s: np.ndarray


def pose_landings(rows: np.ndarray, pose: int, v_s: np.ndarray) -> Landings:
    """``Landings`` of pose ``pose`` from its next-pose rows.

    rows : (A, P) float, P(x' | x, u), NaN rows unless ok (``next_pose_rows``);  v_s : (P,) float"""
    share, total = leaving_shares(rows, pose)
    leaves = total > 0
    return Landings(share, np.where(leaves, np.argmax(share, axis=1), -1),
                    np.where(leaves, share @ np.asarray(v_s, dtype=float), np.nan))


def landing_prior_rows(rows: np.ndarray, pose: int, alpha: float, choosable: np.ndarray, trials: int) -> np.ndarray:
    """``rows`` with each push's landing shrunk toward its pose's mean landing by its topple count.

    A push's landing is estimated from the trials that toppled, n = ``trials`` x its leaving mass,
    and the planners prefer the pushes whose landing reads best, so a landing from a few topples is
    chosen for its noise as much as for its mechanics (the landing's winner's curse,
    docs/VALIDATION.md stop 39).  share' = (n share + alpha m) / (n + alpha), m the mean landing of
    the pose's choosable pushes that leave; each row keeps its leaving mass and its stay.  A measured
    challenger (docs/VALIDATION.md, "A landing trusted as far as its topples"), not served.

    rows : (A, P) float, NaN rows unless ok;  alpha : pseudo-count of the pose's mean landing, >= 0;
    choosable : (A,) bool;  trials : the model's trials per push
    returns : (A, P) float; ``rows`` itself when alpha is 0 or no choosable push leaves"""
    share, total = leaving_shares(rows, pose)
    leaves = total > 0
    if alpha == 0 or not (leaves & choosable).any():
        return rows
    mean = share[leaves & choosable].mean(axis=0)
    weight = alpha / (trials * total[leaves] + alpha)
    shrunk = np.array(rows, dtype=float)
    shrunk[leaves] = total[leaves, None] * ((1 - weight)[:, None] * share[leaves] + weight[:, None] * mean)
    shrunk[leaves, pose] = np.asarray(rows, dtype=float)[leaves, pose]
    return shrunk


def believing_tables(v_s: np.ndarray, rows: list[np.ndarray], mdp: MDPConfig, choosable: list[np.ndarray], max_pushes: int,
                     names: tuple[str, str] = (BELIEF_POLICY, BELIEF_HORIZON_POLICY),
                     budget_choosable: list[np.ndarray] | None = None,
                     ) -> tuple[dict[str, np.ndarray], dict[str, list], dict[str, list]]:
    """The two policies that believe their failures, planned over ``rows``: ``belief_tables`` as
    ``names[0]`` and ``belief_budget_tables`` as ``names[1]``.  returns : their actions, and the Q1
    tables each ranks by after a failure (``after_failure_choice``), keyed by name.

    rows : per pose (A_x, P) float (``next_pose_rows``);  choosable : per pose (A_x,) bool
    budget_choosable : the budget's (``mdp.budget_min_direction_z``), default ``choosable``"""
    first, budget = names
    actions, q1, budget_q1 = {}, {}, {}
    actions[first], q1[first] = belief_tables(v_s, rows, mdp, choosable)
    actions[budget], budget_q1[budget] = belief_budget_tables(v_s, rows, mdp, max_pushes,
                                                              choosable if budget_choosable is None else budget_choosable)
    return actions, q1, budget_q1


def prior_plan(v_s: np.ndarray, prior: list[np.ndarray], mdp: MDPConfig, choosable: list[np.ndarray], max_pushes: int,
               budget_choosable: list[np.ndarray] | None = None, candidates: list[PoseCandidates] | None = None,
               ) -> tuple[dict[str, np.ndarray], dict[str, list], dict[str, list]]:
    """``believing_tables`` of the ``PRIOR_POLICIES`` over ``prior``, every pose's rows with their landings
    pulled toward a prior (``landing_prior_rows``, ``landing_trust.trusted_rows`` or
    ``landing_direction.doubted_rows``), with ``prior_vi``'s
    actions (``value_iteration_actions``; ``candidates`` as there) among the actions."""
    actions, q1, budget_q1 = believing_tables(v_s, prior, mdp, choosable, max_pushes,
                                              (PRIOR_BELIEF_POLICY, PRIOR_BELIEF_HORIZON_POLICY), budget_choosable)
    actions[PRIOR_POLICY] = value_iteration_actions(v_s, prior, mdp, choosable, candidates)
    return actions, q1, budget_q1


def variant_plan(v_s: np.ndarray, rows: list[np.ndarray], candidates: list[PoseCandidates], scores: list[PoseScores],
                 mdp: MDPConfig, choosable: list[np.ndarray], smoothing: Smoothing
                 ) -> tuple[dict[str, np.ndarray], dict[str, list], list[np.ndarray]]:
    """The ``VARIANT_POLICIES`` planned under ``mdp`` over pushes ``choosable`` under it: value iteration
    (``pose_values``; ``aware_vi`` pushes as it does until a push fails), ``belief_vi`` (``belief_tables``)
    and ``smoothed_vi`` over the neighbourhood means of that value iteration's Q_T (its V_T, hence every
    Q_T, follows the variant).  returns : their actions, the Q1 the variant ``belief_vi`` ranks by after a
    failure, keyed by name, and the variant's Q per pose, which its ``aware_vi`` ranks by."""
    values = pose_values(rows, v_s, [-1] * len(rows), mdp, choosable, _pushes(candidates))
    actions = {VARIANT_POLICY: np.array([v.policies["value_iteration"].action for v in values], dtype=np.int64)}
    actions[VARIANT_AWARE_POLICY] = actions[VARIANT_POLICY]
    smoothed = []
    for c, v, s in zip(candidates, values, scores):
        mean, count = neighbour_mean(c.points, c.directions, v.q, smoothing)
        smoothed.append(PoseScores(v.q, mean, s.smoothed_p, count))
    actions[VARIANT_ROBUST_POLICY] = robust_actions(v_s, smoothed, mdp.gamma, smoothing, choosable)
    actions[VARIANT_BELIEF_POLICY], q1 = belief_tables(v_s, rows, mdp, choosable)
    return actions, {VARIANT_BELIEF_POLICY: q1}, [v.q for v in values]


# ---------------------------------------------------------------- physics


@dataclass
class Push:
    """One push played: where, what the model said, what happened.

    after : the pose it came to rest in (-1: none of the pose set), ``after_v_s`` its V_s (NaN for -1);
    landing : the model's likeliest landing, ``landing_v_s`` the model's mean V_s of where it lands
    (``pose_landings``; -1 and NaN where nothing leaves the pose);  p_after :
    the model's probability of ``after`` given a topple (NaN unless it toppled into the pose set)"""

    trial: int
    object_id: str
    policy: str
    pose: int
    action: int
    p_topple: float
    smoothed_p: float
    count: int
    mean_force: float
    height: float
    toppled: bool
    after: int
    after_v_s: float
    landing: int
    landing_v_s: float
    p_after: float


def play_object(plan: ObjectPlan, extra: dict, trials: list[tuple[int, int]], config: Config, seed: int, max_pushes: int,
                world: Config | None, policies: tuple[str, ...] = COMPARED,
                player: PlayerSettings = DEFAULT_PLAYER) -> tuple[str, dict, list[Push]]:
    """Play ``policies`` (each one of ``plan.actions``) from each (trial, start) of one object (runs in a worker).

    The noise of push k of a trial is the k-th draw of the stream ``policies-physics`` uses,
    shared by all policies (common random numbers).  An action table of shape (pushes, P) is a
    budget's: row k is played with ``pushes - k`` pushes left.  ``player``: the push player's numerics.
    returns : (object id, {trial: {policy: visited poses}} or {"failure": reason}, pushes)
    """
    from ..model.poses import settle

    spec = plan.spec
    loaded = load_planned(plan, config)
    if isinstance(loaded, str):
        return spec.object_id, {"failure": loaded}, []
    obj, pose_set = loaded
    body = body_model(obj)
    candidates, scores = extra["candidates"], extra["scores"]
    results: dict[int, dict[str, list[int]]] = {}
    pushes: list[Push] = []
    for trial, start in trials:
        rng = stream(seed, f"{spec.object_id}/trial/{trial}", start, PURPOSE)
        noises = [draw_noise(world or config, rng, noise=True) for _ in range(max_pushes)]
        results[trial] = {}
        for policy in policies:
            poses = [start]
            pose, transform = start, plan.transforms[start]
            choice = plan.actions[policy]
            failed: dict[int, np.ndarray] = {}  # pose -> candidates ruled out this trial (the policies that report failures)
            for step in range(max_pushes):
                if policy in REPORTS_FAILURES and pose in failed:
                    action = after_failure_choice(policy, pose, step, failed[pose], plan, extra, config)
                else:
                    action = int(choice[step, pose] if choice.ndim == 2 else choice[pose])  # the budgets: per pushes left
                if action == NO_OP:
                    break
                c, s = candidates[pose], scores[pose]
                to_object = np.linalg.inv(plan.transforms[pose])
                point = to_object[:3, :3] @ c.points[action] + to_object[:3, 3]
                direction = to_object[:3, :3] @ c.directions[action]
                played = play_push(body, transform, point, direction, config, noises[step], settings=player)
                after = settle(pose_set, obj, played.final_transform[:3, :3])
                top = float(np.nanmax(c.points[:, 2]))
                landing = extra["landings"][pose]
                pushes.append(Push(trial, spec.object_id, policy, pose, action, float(c.p_topple[action]),
                                   float(s.smoothed_p[action]), int(s.count[action]), float(c.mean_force[action]),
                                   float(c.points[action, 2] / top) if top > 0 else float("nan"), bool(after != pose),
                                   int(after), float(plan.v_s[after]) if after >= 0 else float("nan"),
                                   int(landing.pose[action]), float(landing.v_s[action]),
                                   float(landing.share[action, after]) if after >= 0 and after != pose else float("nan")))
                poses.append(after)
                if after < 0:
                    break
                if policy in REPORTS_FAILURES and after == pose:
                    # What /plan's failed_actions rules out (schema.retry), the same rule.
                    ruled_out = retry.ruled_out(c.points, c.directions, [action], extra["exclusion"].radius,
                                                extra["exclusion"].max_angle)
                    failed[pose] = failed.get(pose, np.zeros(len(c.q), dtype=bool)) | ruled_out
                pose, transform = after, played.final_transform
            results[trial][policy] = poses
    return spec.object_id, results, pushes


def after_failure_choice(policy: str, pose: int, step: int, ruled_out: np.ndarray, plan: ObjectPlan, extra: dict,
                         config: Config) -> int:
    """The push of a ``REPORTS_FAILURES`` policy from a pose where a push of the trial has failed,
    among the choosable candidates not in ``ruled_out`` ((A,) bool); ``step`` counts the trial's
    pushes (the budget's row).  returns : action index, or NO_OP"""
    candidates = extra["candidates"][pose]
    # A VARIANT_POLICIES policy plans with its own discount over its own choosable pushes.
    variant = policy in VARIANT_POLICIES
    gamma = (extra["variant_mdp"] if variant else config.mdp).gamma
    choosable = extra["variant_choosable" if variant else "choosable"][pose]
    stay = float(plan.v_s[pose])
    if policy == UNTRIED_POLICY:
        return untried_choice(pose, plan.v_s, candidates.q, ruled_out | ~choosable, gamma)
    if policy in (AWARE_POLICY, VARIANT_AWARE_POLICY):
        q = extra["variant_q"][pose] if variant else candidates.q
        return aware_choice(pose, plan.v_s, q, candidates.p_topple, ruled_out, choosable, gamma,
                            config.mdp.after_failure_power, config.mdp.retry_failed, believes=config.mdp.believe_failures)
    if policy in (BELIEF_POLICY, PRIOR_BELIEF_POLICY, VARIANT_BELIEF_POLICY):
        return retry.best_untried(extra["belief_q1"][policy][pose], choosable & ~ruled_out, stay, IMPROVEMENT, scale=gamma)
    if policy in (BELIEF_HORIZON_POLICY, PRIOR_BELIEF_HORIZON_POLICY):
        return retry.best_untried(extra["belief_budget_q1"][policy][step][pose], extra["budget_choosable"][pose] & ~ruled_out,
                                  stay, horizon.IMPROVEMENT)
    raise ValueError(f"{policy} has no rule after a failure")


def experiment(root: str | Path, n_trials: int, smoothing: Smoothing = Smoothing(), *, max_pushes: int = 3, seed: int = 0,
               workers: int | None = 1, world: Config | None = None, progress: bool = False,
               exclusion: Exclusion = Exclusion(), landing_prior: float | None = None,
               landing_trust: tuple[float, ...] | None = None, landing_direction: tuple[float, ...] | None = None,
               variant: dict[str, float | bool] | None = None, per_trial: bool = False,
               player: PlayerSettings = DEFAULT_PLAYER) -> tuple[dict, list[Push]]:
    """Play the ``COMPARED`` policies (and the ``PRIOR_POLICIES`` with a landing prior, the
    ``VARIANT_POLICIES`` under another MDP); the report
    (JSON-ready) and every push played.

    world : the simulated world's noise; default the dataset's own.  The CLI passes the thesis
      preset (``policies_physics.world_config("thesis")``), as ``toppledb policies-physics`` and
      ``make logs`` do: pass it too, or the numbers are not the CLI's (a call without it played
      value iteration at +0.127 over Max-Height where the CLI's seed 0 gives +0.115)
    exclusion : what a failed push rules out for ``untried_vi``
    landing_prior : alpha of ``landing_prior_rows``; given, the ``PRIOR_POLICIES`` are played too.  A
      trial any of them leaves the pose set in is dropped for every policy, as for any played policy,
      so the others' counted trials can differ from a run without it (pushes never do).  Their
      pushes' landing records (``Push.landing``...) are the model's rows', not the shrunk ones.
    landing_trust : the untrusted share of a landing per band of its pose's drop probability
      (``landing_trust.trusted_rows``); given, the ``PRIOR_POLICIES`` are played over the trusted rows
      (stop 50), as with a landing prior (the same caveats); not with ``landing_prior``
    landing_direction : the doubted share of a landing per push direction (``landing_direction.doubted_rows``,
      candidate LD); given, the ``PRIOR_POLICIES`` are played over the doubted rows (stop 55), as with a
      landing prior (the same caveats); not with either of the two above
    variant : ``mdp`` values (``VARIANT_FIELDS``) the ``VARIANT_POLICIES`` plan under, the dataset's
      for the others; given, they are played too (the same caveat on dropped trials).
    per_trial : the report also holds ``trial_records``, every played trial's record (``trial_records``)
    player : the push player's numerics (``pushsim.PlayerSettings``; the docs' runs have the default), recorded
      in the report: the same trials under other settings measure how much the judge depends on them"""
    from ..build.fanout import map_unordered

    started = time.perf_counter()
    if landing_prior is not None and not 0 <= landing_prior < float("inf"):
        raise ValueError(f"the landing prior is a count of trials, finite and >= 0; got {landing_prior}")
    for name, value in (variant or {}).items():
        if name not in VARIANT_FIELDS:
            raise ValueError(f"a variant changes {' or '.join(VARIANT_FIELDS)}, not {name}")
        switch = isinstance(getattr(MDPConfig(), name), bool)  # a switch takes true or false, nothing else
        if switch != isinstance(value, bool):
            raise ValueError(f"{name} is {'true or false' if switch else 'a number'}; got {value!r}")
        if switch:
            continue
        accepted = field_range(MDPConfig, name)
        if not accepted.contains(value):
            raise ValueError(f"{name} must be {accepted.text()}; got {value}")
    reshaped = [given for given in (landing_prior, landing_trust, landing_direction) if given is not None]
    if len(reshaped) > 1:
        raise ValueError("a landing prior, a landing trust or a landing doubted by direction, one at most: "
                         "they play the same policies")
    if landing_trust is not None:
        landing_trust = checked_shares(landing_trust)
    if landing_direction is not None:
        landing_direction = checked_doubts(landing_direction)
    policies = COMPARED + (tuple(PRIOR_POLICIES) if reshaped else ())
    policies += tuple(VARIANT_POLICIES) if variant else ()
    dataset, config, tables, starts, by_object = open_trials(root, n_trials, seed)
    variant_mdp = replace(config.mdp, **variant) if variant else None
    plans: dict[str, ObjectPlan] = object_plans(dataset, sorted(by_object))
    tasks = []
    for object_id in sorted(by_object):
        plan = plans[object_id]
        candidates = read_candidates(dataset, object_id)
        rows = next_pose_rows(dataset, object_id, [len(c.q) for c in candidates])
        scores = [pose_scores(c, smoothing, r) for c, r in zip(candidates, rows)]
        landings = [pose_landings(r, x, plan.v_s) for x, r in enumerate(rows)]
        # The pushes the dataset's own policies could choose (mdp.min_direction_z), for every rule but the budgets.
        choosable = [horizon.choosable_pushes(c.directions[:, 2], config.mdp.min_direction_z) for c in candidates]
        # The budgets choose as /plan's pushes_left does (mdp.budget_min_direction_z).
        budget_choosable = [horizon.choosable_pushes(c.directions[:, 2], config.mdp.budget_min_direction_z) for c in candidates]
        plan.actions[ROBUST_POLICY] = robust_actions(plan.v_s, scores, config.mdp.gamma, smoothing, choosable)
        plan.actions[HORIZON_POLICY] = horizon_actions(plan.v_s, rows, max_pushes, budget_choosable)
        plan.actions[SMOOTHED_HORIZON_POLICY] = horizon_actions(plan.v_s, [s.smoothed_rows for s in scores], max_pushes,
                                                                budget_choosable)
        plan.actions[UNTRIED_POLICY] = plan.actions["value_iteration"]  # until a push fails
        plan.actions[AWARE_POLICY] = plan.actions["value_iteration"]
        plan.actions[ONCE_POLICY] = once_actions(plan.v_s, rows, config.mdp, choosable, candidates)
        actions, belief_q1, belief_budget_q1 = believing_tables(plan.v_s, rows, config.mdp, choosable, max_pushes,
                                                                budget_choosable=budget_choosable)
        plan.actions.update(actions)
        plan.actions[BUDGET_POLICY] = plan.actions[BELIEF_HORIZON_POLICY]  # never told of a failure
        plan.actions[CHOSEN_HORIZON_POLICY] = chosen_horizon_actions(plan.v_s, rows, scores, max_pushes, budget_choosable,
                                                                     smoothing.min_neighbours)
        if reshaped:
            if landing_prior is not None:
                prior = [landing_prior_rows(r, x, landing_prior, choosable[x], config.topple.trials) for x, r in enumerate(rows)]
            elif landing_trust is not None:
                prior = [trusted_rows(r, x, plan.drop_probabilities, landing_trust) for x, r in enumerate(rows)]
            else:
                prior = [doubted_rows(r, x, c.directions[:, 2], landing_direction) for x, (r, c) in enumerate(zip(rows, candidates))]
            actions, q1, budget_q1 = prior_plan(plan.v_s, prior, config.mdp, choosable, max_pushes, budget_choosable,
                                                candidates)
            plan.actions.update(actions)
            belief_q1.update(q1)
            belief_budget_q1.update(budget_q1)
        variant_choosable, variant_q = None, None
        if variant_mdp is not None:
            variant_choosable = [horizon.choosable_pushes(c.directions[:, 2], variant_mdp.min_direction_z) for c in candidates]
            actions, q1, variant_q = variant_plan(plan.v_s, rows, candidates, scores, variant_mdp, variant_choosable, smoothing)
            plan.actions.update(actions)
            belief_q1.update(q1)
        tasks.append((plan, {"candidates": candidates, "scores": scores, "exclusion": exclusion, "choosable": choosable,
                             "budget_choosable": budget_choosable, "variant_mdp": variant_mdp,
                             "variant_choosable": variant_choosable, "variant_q": variant_q,
                                  "landings": landings, "belief_q1": belief_q1, "belief_budget_q1": belief_budget_q1}, by_object[object_id],
                      config, seed, max_pushes, world, policies, player))

    runs: dict[int, dict[str, list[int]]] = {}
    pushes: list[Push] = []
    failures = {}
    for object_id, results, object_pushes in map_unordered(play_object, tasks, workers, description="objects", progress=progress):
        if "failure" in results:
            failures[object_id] = results["failure"]
            continue
        runs.update(results)
        pushes.extend(object_pushes)
    report = summarise(tables, starts, runs, pushes, policies)
    report.update({"landing_prior": landing_prior, "landing_trust": None if landing_trust is None else landing_trust.tolist(),
                   "landing_direction": None if landing_direction is None else landing_direction.tolist(),
                   "variant": variant or None, "dataset": str(Path(root).resolve()), "trials": n_trials, "objects": len(by_object),
                   "failed_objects": failures, "seed": seed, "max_pushes": max_pushes,
                   "smoothing": vars(smoothing), "exclusion": vars(exclusion), "player": player_parameters(player),
                   "wall_s": round(time.perf_counter() - started, 1)})
    if per_trial:
        report["trial_records"] = trial_records(tables, starts, runs, policies)
    return report, pushes


def trial_gains(tables, starts: np.ndarray, runs: dict, policies: tuple[str, ...]) -> tuple[np.ndarray, dict, np.ndarray, int]:
    """Each policy's V_s gain per trial, over the trials no policy left outside the pose set.

    runs : {trial: {policy: visited poses}}
    returns : kept trials (T,) int;  gains : policy -> (T,) float, V_s at the end minus at the
      start;  useful : (T,) bool, the start is not its object's best pose and greedy would push;
      how many trials were left out
    """
    played = np.array(sorted(runs), dtype=np.int64)
    outside = np.array([any(r[-1] < 0 for r in runs[t].values()) for t in played], dtype=bool)
    kept = played[~outside]
    rows = starts[kept]
    first = tables.first_pose[np.searchsorted(tables.first_pose, rows, side="right") - 1]
    useful = useful_starts(tables, rows)
    gains = {p: tables.v_s[first + np.array([runs[t][p][-1] for t in kept], dtype=np.int64)] - tables.v_s[rows] for p in policies}
    return kept, gains, useful, int(outside.sum())


def trial_records(tables, starts: np.ndarray, runs: dict, policies: tuple[str, ...]) -> list[dict]:
    """Every played trial as a record, to pair two runs trial by trial (``paired_trials``).

    runs : {trial: {policy: visited poses}}
    returns : per trial, in order: ``trial``; ``start``, its start row in the dataset's pose order
      (object by object, pose by pose); ``object``, its object's index; ``object_id``; ``outside``, whether a played
      policy left the pose set; ``useful``, as ``useful_starts``; ``gains``, policy -> V_s at the
      end minus at the start (None where outside)
    """
    kept, gains, _, _ = trial_gains(tables, starts, runs, policies)
    gain_of = {int(t): {p: float(gains[p][i]) for p in policies} for i, t in enumerate(kept)}
    played = np.array(sorted(runs), dtype=np.int64)
    rows = starts[played]
    objects = np.searchsorted(tables.first_pose, rows, side="right") - 1
    return [{"trial": int(t), "start": int(row), "object": int(obj), "object_id": tables.object_ids[obj],
             "outside": int(t) not in gain_of, "useful": bool(useful), "gains": gain_of.get(int(t))}
            for t, row, obj, useful in zip(played, rows, objects, useful_starts(tables, rows))]


def landing_summary(pushes: list[Push]) -> dict:
    """Where a policy's pushes that toppled into the pose set came to rest, against the model: how
    many, and of those how many the model lands nowhere (its row never leaves the pose, or the push
    has no row); the share that rested in the model's likeliest landing and in a pose it gives no
    probability (those included); over the rest, the model's mean V_s of their landings and the V_s
    they rested at."""
    landed = [p for p in pushes if p.toppled and p.after >= 0]
    foreseen = [p for p in landed if p.landing >= 0]
    return {
        "toppled": len(landed),
        "no_landing": len(landed) - len(foreseen),
        "likeliest_share": mean_se([p.after == p.landing for p in landed])[0],
        "unforeseen_share": mean_se([p.p_after == 0 for p in landed])[0],
        "expected_v_s": mean_se([p.landing_v_s for p in foreseen])[0],
        "landed_v_s": mean_se([p.after_v_s for p in foreseen])[0],
    }


def summarise(tables, starts: np.ndarray, runs: dict, pushes: list[Push], policies: tuple[str, ...] = COMPARED) -> dict:
    """Per policy: V_s gain on useful trials, paired gain over max_height (and never push), topple rates;
    the ``CHALLENGERS`` against value iteration and the ``COUNTERPARTS`` played against theirs, paired."""
    kept, gains, useful, outside = trial_gains(tables, starts, runs, policies)
    gains["never_push"] = np.zeros(len(kept))
    report = {"played_trials": len(runs), "outside_trials": outside, "useful_trials": int(useful.sum()), "policies": {}}
    kept_trials = set(kept.tolist())
    for policy, gain in gains.items():
        mine = [p for p in pushes if p.policy == policy and p.trial in kept_trials]
        gain_mean, gain_se = mean_se(gain[useful])
        over, over_se = mean_se(gain[useful] - gains["max_height"][useful])
        report["policies"][policy] = {
            "physical_gain_useful": gain_mean, "physical_gain_useful_se": gain_se,
            "gain_over_max_height": over, "gain_over_max_height_se": over_se,
            "physical_gain_all": mean_se(gain)[0],
            "pushes": len(mine),
            "predicted_topple_rate": mean_se([p.p_topple for p in mine])[0],
            "smoothed_topple_rate": mean_se([p.smoothed_p for p in mine])[0],
            "physical_topple_rate": mean_se([p.toppled for p in mine])[0],
            "physical_topple_rate_se": mean_se([p.toppled for p in mine])[1],
            "landings": landing_summary(mine),
        }
    for policy in CHALLENGERS:
        mean, error = mean_se(gains[policy][useful] - gains["value_iteration"][useful])
        report["policies"][policy].update({"gain_over_value_iteration": mean, "gain_over_value_iteration_se": error})
    # The budget believing failures against the budget that does not (the same pushes left).
    mean, error = mean_se(gains[BELIEF_HORIZON_POLICY][useful] - gains[HORIZON_POLICY][useful])
    report["policies"][BELIEF_HORIZON_POLICY].update({"gain_over_horizon_vi": mean, "gain_over_horizon_vi_se": error})
    for policy, counterpart in COUNTERPARTS.items():
        if policy in gains:
            mean, error = mean_se(gains[policy][useful] - gains[counterpart][useful])
            report["policies"][policy].update({"counterpart": counterpart, "gain_over_counterpart": mean,
                                               "gain_over_counterpart_se": error})
    return report


def cell(value: float | None, signed: bool = True) -> str:
    """A report's number in a text table: three decimals, signed unless a rate, '-' for none."""
    return "    -" if value is None else (f"{value:+.3f}" if signed else f"{value:.3f}")


def study_parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """The arguments every physics study of the policies shares: the dataset, its trials and
    their seed, the push budget, workers, the simulated world, and the JSON report."""
    from ..cli import positive_int

    parser = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--trials", type=positive_int, default=600)
    parser.add_argument("--max-pushes", type=positive_int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=positive_int, default=1)
    parser.add_argument("--world", default="thesis")
    parser.add_argument("--json", type=Path, help="write the report here")
    return parser


def text(report: dict) -> str:
    lines = [(f"{report['played_trials']} trials on {report['objects']} objects, {report['useful_trials']} useful, "
              f"{report['outside_trials']} outside; smoothing {report['smoothing']}; {report['wall_s']} s"),
             f"{'policy':<20} {'gain useful':>12} {'over max_height':>18} {'pushes':>7} {'P raw':>6} {'P smooth':>8} {'physics':>8}"]
    for policy, r in report["policies"].items():
        se = r["gain_over_max_height_se"]
        lines.append(f"{policy:<20} {cell(r['physical_gain_useful']):>12} "
                     f"{cell(r['gain_over_max_height']) + ('' if se is None else f' +/- {se:.3f}'):>18} {r['pushes']:>7} "
                     f"{cell(r['predicted_topple_rate'], False):>6} {cell(r['smoothed_topple_rate'], False):>8} "
                     f"{cell(r['physical_topple_rate'], False):>8}")
    for policy in CHALLENGERS:
        r = report["policies"][policy]
        lines.append(f"{policy} - value_iteration on useful trials: {cell(r['gain_over_value_iteration'])} +/- "
                     f"{r['gain_over_value_iteration_se'] or 0:.3f}")
    for policy in COUNTERPARTS:
        if policy in report["policies"]:
            r = report["policies"][policy]
            lines.append(f"{policy} - {r['counterpart']} on useful trials: {cell(r['gain_over_counterpart'])} +/- "
                         f"{r['gain_over_counterpart_se'] or 0:.3f}")
    lines.append(f"{'toppled into the set':<20} {'pushes':>7} {'at likeliest':>12} {'unforeseen':>10} {'V_s model':>9} {'V_s got':>8}")
    for policy, r in report["policies"].items():
        land = r["landings"]
        lines.append(f"{policy:<20} {land['toppled']:>7} {cell(land['likeliest_share'], False):>12} "
                     f"{cell(land['unforeseen_share'], False):>10} {cell(land['expected_v_s'], False):>9} "
                     f"{cell(land['landed_v_s'], False):>8}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import positive_int, print_and_record, refused_outputs

    parser = study_parser("python -m pipeline.studies.robust_policy", __doc__)
    parser.add_argument("--radius", type=float, default=Smoothing.radius, help="m (default: %(default)s)")
    parser.add_argument("--max-angle", type=float, default=Smoothing.max_angle, help="rad (default: %(default)s)")
    parser.add_argument("--min-neighbours", type=positive_int, default=Smoothing.min_neighbours)
    parser.add_argument("--exclude-radius", type=float, default=Exclusion.radius,
                        help="m, what a failed push rules out for untried_vi (default: %(default)s)")
    parser.add_argument("--exclude-angle", type=float, default=Exclusion.max_angle, help="rad (default: %(default)s)")
    parser.add_argument("--pushes", type=Path, help="write every push played (diagnostics) here, JSON lines")
    parser.add_argument("--trials-out", type=Path, metavar="FILE.jsonl",
                        help=("write every trial's start and each policy's gain here, JSON lines: two runs of one seed on "
                              "datasets of the same objects pair trial by trial (python -m pipeline.studies.paired_trials)"))
    parser.add_argument("--landing-prior", type=float, metavar="ALPHA",
                        help="also play value iteration, belief_vi and belief_horizon_vi over rows whose landings are "
                             "shrunk toward the pose's mean landing with this pseudo-count (landing_prior_rows)")
    parser.add_argument("--landing-trust", type=float, nargs=len(TRUST_BANDS) + 1, metavar="U",
                        help="also play them over rows whose landing on a pose keeps 1 - U of its share, U per band of the "
                             "pose's drop probability (edges " + ", ".join(map(str, TRUST_BANDS)) + "), the rest spread "
                             "by drop probability (landing_trust.trusted_rows); not with --landing-prior")
    parser.add_argument("--landing-direction", type=float, nargs=len(DIRECTION_CLASSES), metavar="LAMBDA",
                        help="also play them over rows whose landing moves LAMBDA of its share to the pose's mean "
                             "landing, LAMBDA per push direction (" + ", ".join(DIRECTION_CLASSES) + "; candidate LD, "
                             "landing_direction.doubted_rows); not with --landing-prior or --landing-trust")
    parser.add_argument("--gamma", type=float, metavar="G",
                        help="also play value iteration, belief_vi and smoothed_vi planned with this discount in (0, 1] "
                             "(variant_vi, variant_belief_vi, variant_smoothed_vi), each against its counterpart")
    parser.add_argument("--min-direction-z", type=float, metavar="Z",
                        help="also play them choosing among the pushes with u_z >= Z (the dataset's mdp.min_direction_z "
                             "for the others); with --gamma, one variant of both")
    parser.add_argument("--choice-radius", type=float, metavar="R",
                        help="also play them with value iteration choosing by its neighbourhood within R m (mdp.choice_radius; "
                             "0: the argmax of Q_T); with the others, one variant of all")
    parser.add_argument("--choose-for-repeats", action="store_const", const=True,
                        help="also play them with value iteration's push chosen for a client that repeats it "
                             "(mdp.choose_for_repeats, docs/MODEL.md (12.16)); with the others, one variant of all")
    parser.add_argument("--repeats-then-grasp", action="store_const", const=True,
                        help="with --choose-for-repeats: a client that grasps once repeating is worth less "
                             "(mdp.repeats_then_grasp, docs/MODEL.md (12.17))")
    add_player_options(parser)
    args = parser.parse_args(argv)
    if refused_outputs(args.json, args.trials_out, args.pushes):
        return 2
    try:
        player = player_from_args(args)
        smoothing = Smoothing(args.radius, args.max_angle, args.min_neighbours)
        report, pushes = experiment(args.dataset, args.trials, smoothing, max_pushes=args.max_pushes, seed=args.seed,
                                    workers=args.workers, world=world_config(args.world),
                                    exclusion=Exclusion(args.exclude_radius, args.exclude_angle),
                                    landing_prior=args.landing_prior, landing_trust=args.landing_trust,
                                    landing_direction=args.landing_direction,
                                    variant={name: getattr(args, name) for name in VARIANT_FIELDS if getattr(args, name) is not None},
                                    per_trial=args.trials_out is not None, player=player)
    except (ExperimentError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    trials = report.pop("trial_records", None)
    if print_and_record(text(report), report, args.json):
        return 2
    if trials is not None:
        write_text_atomic(args.trials_out, "".join(json.dumps(t) + "\n" for t in trials))
    if args.pushes:
        write_text_atomic(args.pushes, "".join(json.dumps(vars(p)) + "\n" for p in pushes))
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
