"""Value iteration over an object's stable poses and the three toppling policies
(Correa 2019, section 4.3), as pure numpy functions over per-pose tables.

States are the object's stable poses x; the actions of a pose are its candidate
pushes (only ``ok`` ones have transition rows) plus the no-op, which ends the
episode with a suction grasp worth V_s(x):

    Q_T(x, u) = sum_x' P(x' | x, u) V_T(x')
    V_T(x)    = max(V_s(x), gamma * max_u Q_T(x, u))

or, with ``retry_failed`` false (opt-in; docs/MODEL.md section 12, (12.9)), a push that
leaves the object where it was is worth grasping there, V_s(x), not V_T(x):

    Q_T(x, u) = sum_{x' != x} P(x' | x, u) V_T(x') + P(x | x, u) V_s(x)

or, with ``believe_failures`` (the default, docs/MODEL.md (12.13)), over a fresh and a failed
state per pose, where a push topples with P^k once one from the pose has failed
(``belief_value_iteration``).

Inputs, for an object with P poses:

next_pose : list of P arrays, next_pose[x] is (A_x, P) float, P(x' | x, u) for the
  actions of pose x; rows of actions that are not ``ok`` are NaN (any NaN marks the
  row) and are ignored; the other rows sum to 1
v_s : (P,) float in [0, 1], suction grasp quality of each pose
choosable : list of P arrays, choosable[x] is (A_x,) bool, the pushes the policies may
  choose (``schema.horizon.choosable_pushes``); the others keep their Q_T and greedy values

No geometry here: the service and planners can import it without the mesh stack.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schema import neighbourhood, retry
from schema.vocabulary import NO_OP

from .config import MDPConfig
from .outcomes import PolicyChoice, PoseValues

IMPROVEMENT = retry.POLICY_IMPROVEMENT
"""An action must beat the no-op by more than this to be chosen: rows summing to 1
only up to rounding must not turn "stay in this pose" into a spurious improvement.  The
rule itself is ``schema.retry.best_untried``, which the service and the Python API's plan
apply after failed pushes too."""


def _stack(next_pose: list[np.ndarray], n_poses: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All ``ok`` rows of all poses in one matrix, in pose order.

    returns : rows (N, P) float; owner (N,) int, the pose of each row (non-decreasing);
      ok (sum A_x,) bool, which of the concatenated actions are ``ok``
    """
    blocks = [np.asarray(t, dtype=float).reshape(-1, n_poses) for t in next_pose]
    stacked = np.concatenate(blocks) if blocks else np.zeros((0, n_poses))
    owner = np.repeat(np.arange(len(blocks)), [len(b) for b in blocks])
    ok = ~np.isnan(stacked).any(axis=1)
    return stacked[ok], owner[ok], ok


def _split(values: np.ndarray, next_pose: list[np.ndarray]) -> list[np.ndarray]:
    """Cut a stacked (sum A_x,) array back into one (A_x,) array per pose."""
    if not next_pose:
        return []
    return np.split(values, np.cumsum([len(t) for t in next_pose])[:-1])


def _greedy_step(
    q: np.ndarray, starts: np.ndarray, ends: np.ndarray, poses: np.ndarray, n_poses: int
) -> tuple[np.ndarray, np.ndarray]:
    """Best Q and the row achieving it for every pose; -inf and -1 for poses without rows."""
    best = np.full(n_poses, -np.inf)
    row = np.full(n_poses, -1)
    for x, a, b in zip(poses, starts, ends):
        i = a + int(np.argmax(q[a:b]))
        best[x], row[x] = q[i], i
    return best, row


def _self_mass(rows: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(N,) float, each row's probability of leaving the object in its own pose."""
    return rows[np.arange(len(rows)), owner]


def _q_values(rows: np.ndarray, owner: np.ndarray, value: np.ndarray, v_s: np.ndarray, retry_failed: bool) -> np.ndarray:
    """(N,) float, Q_T of every row under ``value``: (12.1), or (12.9) when a failed push is not retried."""
    q = rows @ value
    if not retry_failed:
        q -= _self_mass(rows, owner) * (value[owner] - v_s[owner])
    return q


def _policy_value(rows: np.ndarray, row: np.ndarray, acting: np.ndarray, v_s: np.ndarray, gamma: float,
                  retry_failed: bool) -> np.ndarray:
    """Exact value of the stationary policy "push ``row[x]`` where ``acting``, else grasp".

    Solves V_A = gamma (T_AA V_A + T_AS V_s(S)), V_S = V_s(S); without retries (12.9) the
    mass a push leaves in its own pose goes to V_s there instead.  Any policy's value is a
    lower bound on V_T, which is what lets value iteration jump to it.
    """
    value = v_s.copy()
    act = np.flatnonzero(acting)
    if len(act):
        t = rows[row[act]]
        stay = np.flatnonzero(~acting)
        constant = gamma * t[:, stay] @ v_s[stay]
        if not retry_failed:
            own = np.arange(len(act)), act
            constant = constant + gamma * t[own] * v_s[act]
            t = t.copy()
            t[own] = 0.0
        system = np.eye(len(act)) - gamma * t[:, act]
        try:
            value[act] = np.linalg.solve(system, constant)
        except np.linalg.LinAlgError:
            # Only possible without discount (gamma = 1) and a closed loop of pushes;
            # V_s is still a valid lower bound, and plain sweeps do the rest.
            return v_s.copy()
    return value


def value_iteration(
    next_pose: list[np.ndarray],
    v_s: np.ndarray,
    gamma: float,
    tolerance: float,
    max_iterations: int,
    choosable: list[np.ndarray] | None = None,
    retry_failed: bool = True,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """V_T and Q_T by value iteration from V_T = V_s, accelerated by policy evaluation.

    Each sweep applies the Bellman update V <- max(V_s, gamma * max_u T_u V) (without retries,
    T_u's own-pose entry takes V_s there, (12.9)) and also
    evaluates exactly (one P x P linear solve) the greedy policy of the current V,
    keeping the larger of the two.  Both are lower bounds on the fixed point, so the
    iterates rise monotonically from V_s to it (V_T >= V_s everywhere) -- in a handful
    of sweeps instead of the hundreds plain value iteration needs when pushes rarely
    topple.  Stops, returning the last Bellman update, when it changes no value by
    more than ``tolerance``; V_T is then within ``tolerance * gamma / (1 - gamma)`` of
    the fixed point.  At most ``max_iterations`` sweeps (0 returns V_s).

    next_pose : list of P (A_x, P) float, see the module docstring
    v_s : (P,) float
    gamma : discount in [0, 1)
    tolerance : float, largest change of any V_T(x) in the last sweep
    max_iterations : int, upper bound on sweeps
    choosable : list of P (A_x,) bool (0/1 reads as bool), the pushes the max over u may take
      (default all); the others' Q_T is still their value under the plan, (12.7).  ValueError
      unless one mask per pose, one entry per push
    retry_failed : whether a push that leaves the object in its pose may be pushed again
      (the thesis, (12.1)) or the object is then grasped there ((12.9))
    returns : V_T (P,) float; Q_T list of (A_x,) float, NaN where the row is NaN
    """
    v_s = np.asarray(v_s, dtype=float)
    n_poses = len(v_s)
    rows, owner, ok = _stack(next_pose, n_poses)
    planned = slice(None) if choosable is None else _choosable_rows(choosable, next_pose, ok)
    plan_rows, plan_owner = rows[planned], owner[planned]
    poses, starts = np.unique(plan_owner, return_index=True)
    ends = np.r_[starts[1:], len(plan_owner)].astype(int)

    value = v_s.copy()
    for _ in range(max_iterations):
        best, row = _greedy_step(_q_values(plan_rows, plan_owner, value, v_s, retry_failed), starts, ends, poses, n_poses)
        bellman = np.maximum(v_s, gamma * best)
        change = float(np.max(bellman - value)) if n_poses else 0.0  # iterates only rise
        if change <= tolerance:
            value = bellman
            break
        value = np.maximum(bellman, _policy_value(plan_rows, row, gamma * best > v_s, v_s, gamma, retry_failed))

    q = np.full(len(ok), np.nan)
    q[ok] = _q_values(rows, owner, value, v_s, retry_failed)
    return value, _split(q, next_pose)


@dataclass(frozen=True)
class _BeliefRows:
    """An object's ``ok`` rows as (12.13) reads them: owner (N,) int, ok as ``_stack``; planned
    (N,) bool, the choosable rows; stay (N,) float, P(x | x, u); leave (N, P), the rows with their
    own pose's entry zeroed; failed_ratio, failed_topple (N,) float, p^(k-1)
    and p^k (``schema.retry.failed_ratios``)."""

    owner: np.ndarray
    ok: np.ndarray
    planned: np.ndarray
    stay: np.ndarray
    leave: np.ndarray
    failed_ratio: np.ndarray
    failed_topple: np.ndarray

    def best(self, values: np.ndarray, n_poses: int) -> np.ndarray:
        """(P,) float, per pose the largest of ``values`` over its planned rows; -inf without any."""
        out = np.full(n_poses, -np.inf)
        np.maximum.at(out, self.owner[self.planned], values[self.planned])
        return out

    def failed_loop(self, gamma: float) -> np.ndarray:
        """(N,) float, what pushing a row again and again from its failed state is worth per unit of
        S, its loop summed: gamma p^(k-1) / (1 - gamma + gamma p^k); 0 for a push that never topples
        (0 / 0 when gamma = 1)."""
        loop = 1.0 - gamma + gamma * self.failed_topple
        return np.divide(gamma * self.failed_ratio, loop, out=np.zeros_like(loop), where=loop > 0)


def _sweep(step, v_s: np.ndarray, tolerance: float, max_iterations: int) -> np.ndarray:
    """Iterate ``value = step(value)`` from V_s until no value moves by more than ``tolerance``
    (at most ``max_iterations`` sweeps); the last value, (P,) float."""
    value = v_s.copy()
    for _ in range(max_iterations):
        update = step(value)
        change = float(np.max(np.abs(update - value))) if len(value) else 0.0
        value = update
        if change <= tolerance:
            break
    return value


def _choosable_rows(choosable: list, next_pose: list[np.ndarray], ok: np.ndarray) -> np.ndarray:
    """Which of the stacked ok rows (``_stack``) the plan may choose.

    choosable : list of P (A_x,) masks, read as bool (a 0/1 integer mask is a mask, as ``pose_values``
      reads it for its choices, and not a list of row numbers);  next_pose : the P tables
    ok : (sum A_x,) bool from ``_stack``;  returns : (N,) bool over the stacked ok rows
    ValueError unless there is one mask per pose, one entry per push
    """
    masks = [np.asarray(c, dtype=bool) for c in choosable]
    if len(masks) != len(next_pose):
        raise ValueError(f"choosable has {len(masks)} masks for {len(next_pose)} poses: one per pose")
    for x, (mask, table) in enumerate(zip(masks, next_pose)):
        if mask.shape != (len(table),):
            raise ValueError(f"choosable[{x}] has shape {mask.shape}, pose {x} has {len(table)} pushes: one entry per push")
    return np.concatenate([np.zeros(0, dtype=bool), *masks])[ok]


def _belief_rows(next_pose: list[np.ndarray], n_poses: int, power: float, choosable: list[np.ndarray] | None,
                 name: str) -> _BeliefRows:
    if not power >= 1.0:
        raise ValueError(f"{name} needs power >= 1, got {power}")
    rows, owner, ok = _stack(next_pose, n_poses)
    planned = np.ones(len(rows), dtype=bool) if choosable is None else _choosable_rows(choosable, next_pose, ok)
    stay = _self_mass(rows, owner)
    leave = rows.copy()
    leave[np.arange(len(rows)), owner] = 0.0
    return _BeliefRows(owner, ok, planned, stay, leave, *retry.failed_ratios(1.0 - stay, power))


def belief_value_iteration(
    next_pose: list[np.ndarray],
    v_s: np.ndarray,
    gamma: float,
    power: float,
    tolerance: float,
    max_iterations: int,
    choosable: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Value iteration that believes its own failures (docs/MODEL.md (12.13)).

    Two states per pose: fresh (x, 0), and (x, 1) once a push from x has left the object in x.
    A failure is news about the pose (docs/VALIDATION.md "After a failed push"): there a push
    of P(topple) p topples with p^k (``schema.retry.after_failure``, k = ``power``) and lands
    where its row's topples land; a topple leaves the object fresh in its new pose.

        Q0(x, u) = S(x, u) + (1 - p) V1(x),            S(x, u) = sum_{x' != x} P(x' | x, u) V0(x')
        Q1(x, u) = p^(k-1) S(x, u) + (1 - p^k) V1(x)
        V_i(x)   = max(V_s(x), gamma max_u Q_i(x, u))  over the choosable pushes

    k = 1 is the thesis's value iteration (V0 = V1 = V_T); k -> infinity values a failure at
    the grasp, (12.9).  For a fixed push the failed state's loop has the closed form
    gamma p^(k-1) S / (1 - gamma + gamma p^k), so V1(x) follows from V0 at once and each sweep
    only iterates V0 over the topples between poses; sweeps stop when no V0 moves by more than
    ``tolerance`` (at most ``max_iterations``).

    next_pose, v_s, choosable : as ``value_iteration``;  gamma : discount in [0, 1);  power : k >= 1
    returns : V0, V1 (P,) float; Q0, Q1 lists of (A_x,) float, NaN where the row is NaN
    """
    v_s = np.asarray(v_s, dtype=float)
    n_poses = len(v_s)
    rows = _belief_rows(next_pose, n_poses, power, choosable, "belief_value_iteration")
    failed_loop = rows.failed_loop(gamma)

    def failed_values(s: np.ndarray) -> np.ndarray:
        return np.maximum(v_s, rows.best(failed_loop * s, n_poses))

    def step(value: np.ndarray) -> np.ndarray:
        s = rows.leave @ value
        return np.maximum(v_s, gamma * rows.best(s + rows.stay * failed_values(s)[rows.owner], n_poses))

    value = _sweep(step, v_s, tolerance, max_iterations)
    s = rows.leave @ value
    failed_value = failed_values(s)
    q0, q1 = np.full(len(rows.ok), np.nan), np.full(len(rows.ok), np.nan)
    q0[rows.ok] = s + rows.stay * failed_value[rows.owner]
    q1[rows.ok] = rows.failed_ratio * s + (1.0 - rows.failed_topple) * failed_value[rows.owner]
    return value, failed_value, _split(q0, next_pose), _split(q1, next_pose)


def repeat_value_iteration(
    next_pose: list[np.ndarray],
    v_s: np.ndarray,
    gamma: float,
    power: float,
    tolerance: float,
    max_iterations: int,
    choosable: list[np.ndarray] | None = None,
    then_grasp: bool = False,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Value iteration for a client that pushes its pose's stored push again after it fails
    (docs/MODEL.md (12.16)).

    A client that sends /plan only its pose is served the same push after a failure, and (12.13)'s
    failed state, which switches to the best untried push, is not where it goes.  Its pushes keep
    (12.13)'s belief: after a failure the same push topples with p^k (k = ``power``) and lands where
    its row's topples land, so a push is worth its topples plus its own loop of repeats:

        Q_R(x, u) = S(x, u) (1 + (1 - p) gamma p^(k-1) / (1 - gamma + gamma p^k)),  S(x, u) = sum_{x' != x} P(x' | x, u) V_R(x')
        V_R(x)    = max(V_s(x), gamma max_u Q_R(x, u))  over the choosable pushes

    the value of the best stationary pose -> push map under that belief.  A push unlikely to topple
    loses more here than in Q0, where its failure is worth the best other push.  With ``then_grasp``
    (12.17) the client grasps where it failed once its repeats are worth less than that, as a robot
    whose budget runs out does: the failed state is (12.13)'s with the same push or the grasp,

        Q_G(x, u) = S(x, u) + (1 - p) max(V_s(x), gamma p^(k-1) S(x, u) / (1 - gamma + gamma p^k))

    (``pose_values`` ranks the stored push by either; the grasp after a failure is not stored or served.)

    next_pose, v_s, choosable : as ``value_iteration``;  gamma : discount in [0, 1);  power : k >= 1
    returns : V_R (P,) float; Q_R (or Q_G) list of (A_x,) float, NaN where the row is NaN
    """
    v_s = np.asarray(v_s, dtype=float)
    n_poses = len(v_s)
    rows = _belief_rows(next_pose, n_poses, power, choosable, "repeat_value_iteration")
    failed_loop = rows.failed_loop(gamma)
    grasp = v_s[rows.owner]

    def push_values(s: np.ndarray) -> np.ndarray:
        # Q_R is S times a factor fixed by the push alone: (12.16) is value iteration with rescaled rows.
        if then_grasp:
            return s + rows.stay * np.maximum(grasp, failed_loop * s)
        return s * (1.0 + rows.stay * failed_loop)

    value = _sweep(lambda value: np.maximum(v_s, gamma * rows.best(push_values(rows.leave @ value), n_poses)),
                   v_s, tolerance, max_iterations)
    q = np.full(len(rows.ok), np.nan)
    q[rows.ok] = push_values(rows.leave @ value)
    return value, _split(q, next_pose)


def greedy_values(next_pose: list[np.ndarray], v_s: np.ndarray) -> list[np.ndarray]:
    """E[V_s(x')] of every action: the suction quality expected right after the push.

    returns : list of (A_x,) float, NaN where the row is NaN
    """
    v_s = np.asarray(v_s, dtype=float)
    return [np.asarray(t, dtype=float).reshape(-1, len(v_s)) @ v_s for t in next_pose]


def max_height_policy(pose: int, v_s: np.ndarray, max_height_action: int, greedy: np.ndarray) -> PolicyChoice:
    """Max-Height baseline (thesis 4.3.1): push the highest near-horizontal-normal point.

    No-op when the object already rests in a pose of the highest V_s, when the pose
    has no Max-Height action (-1), or when that action is not ``ok`` (NaN greedy
    value: the push cannot be executed, e.g. the finger collides).

    pose : int;  v_s : (P,) float;  max_height_action : int, ``Actions.max_height``
    greedy : (A_x,) float, ``greedy_values`` of this pose
    returns : PolicyChoice; value = E[V_s(x')] of the push, or V_s(x) for the no-op
    """
    v_s = np.asarray(v_s, dtype=float)
    stay = PolicyChoice(NO_OP, float(v_s[pose]))
    if v_s[pose] >= v_s.max() or max_height_action < 0 or max_height_action >= len(greedy):
        return stay
    value = float(greedy[max_height_action])
    if np.isnan(value):
        return stay
    return PolicyChoice(int(max_height_action), value)


def greedy_policy(pose: int, v_s: np.ndarray, greedy: np.ndarray) -> PolicyChoice:
    """Greedy baseline (thesis 4.3.2): argmax_u E[V_s(x')], no-op unless it beats V_s(x).

    pose : int;  v_s : (P,) float;  greedy : (A_x,) float, ``greedy_values`` of this pose
    returns : PolicyChoice; value = E[V_s(x')] of the push, or V_s(x) for the no-op
    """
    stay = float(np.asarray(v_s, dtype=float)[pose])
    greedy = np.asarray(greedy, dtype=float)
    action = retry.best_untried(greedy, np.ones(len(greedy), dtype=bool), stay, IMPROVEMENT)
    return PolicyChoice(NO_OP, stay) if action == NO_OP else PolicyChoice(action, float(greedy[action]))


def value_iteration_policy(pose: int, v_s: np.ndarray, q: np.ndarray, gamma: float) -> PolicyChoice:
    """Value Iteration policy (thesis 4.3.3): argmax_u Q_T(x, u), no-op when
    V_s(x) >= gamma max_u Q_T(x, u).

    pose : int;  v_s : (P,) float;  q : (A_x,) float, Q_T of this pose;  gamma : discount
    returns : PolicyChoice; value = Q_T(x, u) of the push (the expected V_T of the next
      pose, or (12.9) without retries, before this step's discount; V_T(x) = gamma Q_T), or
      V_s(x) for the no-op
    """
    stay = float(np.asarray(v_s, dtype=float)[pose])
    q = np.asarray(q, dtype=float)
    action = retry.best_untried(q, np.ones(len(q), dtype=bool), stay, IMPROVEMENT, scale=gamma)
    return PolicyChoice(NO_OP, stay) if action == NO_OP else PolicyChoice(action, float(q[action]))


def neighbourhood_choice(pose: int, v_s: np.ndarray, q: np.ndarray, points: np.ndarray, directions: np.ndarray,
                         choosable: np.ndarray, config: MDPConfig) -> PolicyChoice:
    """Value iteration's push chosen by its neighbourhood (docs/MODEL.md (12.15)):
    the choosable push of highest mean Q_T over the ok pushes within ``config.choice_radius`` of its
    contact and ``config.choice_angle`` of its direction (itself included), among those with at least
    ``config.choice_neighbours`` of them (``choice_by_means``: the argmax of Q_T where no push has
    them); no-op unless gamma times that mean beats V_s(x).  An argmax
    over ~1,000 Monte Carlo estimates picks the most over-stated one; the mean of ~30 neighbours does
    not (docs/VALIDATION.md, "Tuning the planners out of fold").

    pose : int;  v_s : (P,) float;  q : (A,) float, Q_T (NaN unless ok)
    points, directions : (A, 3) float, the pushes' contacts (m) and unit directions, pose frame
    choosable : (A,) bool;  returns : PolicyChoice; value = the push's own Q_T, or V_s(x) for the no-op
    """
    stay = float(np.asarray(v_s, dtype=float)[pose])
    q = np.asarray(q, dtype=float)
    # Over the ok pushes alone (about half): a push that is not ok is nobody's neighbour, and the
    # pairwise search costs the square of the pushes searched.
    ok = np.flatnonzero(np.isfinite(q))
    mean, count = np.full(len(q), np.nan), np.zeros(len(q), dtype=np.int64)
    mean[ok], count[ok] = neighbourhood.neighbour_mean(np.asarray(points, dtype=float)[ok], np.asarray(directions, dtype=float)[ok],
                                                       q[ok], config.choice_radius, config.choice_angle)
    action = choice_by_means(stay, mean, count, q, choosable, config.gamma, config.choice_neighbours)
    return PolicyChoice(NO_OP, stay) if action == NO_OP else PolicyChoice(action, float(q[action]))


def choice_by_means(stay: float, mean: np.ndarray, count: np.ndarray, q: np.ndarray, choosable: np.ndarray, gamma: float,
                    neighbours: int) -> int:
    """(12.15) from the neighbourhood means: the choosable push of highest ``mean`` among those with
    at least ``neighbours`` ok pushes in their neighbourhood, pushed iff gamma times that mean beats
    ``stay``.  A pose where no choosable push has that many (pushes sampled too thinly for the mean,
    as in a build with a hundred contacts) takes the thesis's argmax of ``q`` instead: no neighbourhood
    can temper the estimates there, and grasping where a push is worth far more would throw V_T away.

    stay : V_s of the pose;  mean, count, q : (A,) float, float, int (NaN unless ok);  choosable : (A,) bool
    returns : action index, or NO_OP
    """
    choosable = np.asarray(choosable, dtype=bool)
    eligible = choosable & (np.asarray(count) >= neighbours)
    if not eligible.any():
        return retry.best_untried(np.asarray(q, dtype=float), choosable, stay, IMPROVEMENT, scale=gamma)
    return retry.best_untried(mean, eligible, stay, IMPROVEMENT, scale=gamma)


def pose_values(
    next_pose: list[np.ndarray],
    v_s: np.ndarray,
    max_height_actions: list[int] | np.ndarray,
    config: MDPConfig = MDPConfig(),
    choosable: list[np.ndarray] | None = None,
    pushes: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[PoseValues]:
    """Value iteration, greedy values and all three policies' choices for every pose.

    next_pose : list of P (A_x, P) float;  v_s : (P,) float
    max_height_actions : (P,) int, ``Actions.max_height`` of each pose (-1: none)
    choosable : list of P (A_x,) bool, the pushes greedy and value iteration may choose
      (default all).  Value iteration plans over these alone; every push's Q_T is then its
      value under that plan (push it, then follow the plan's argmax), choosable or not.  Max-Height
      pushes its own push, as the thesis defines it.
    pushes : per pose (points (A_x, 3), directions (A_x, 3)), pose frame: what value iteration's
      choice by neighbourhood (``config.choice_radius`` > 0, ``neighbourhood_choice``) needs
    returns : list of P PoseValues (q = Q_T, greedy = E[V_s(x')], value = V_T(x), and
      policies ``max_height``, ``greedy``, ``value_iteration``); when ``config`` believes failures
      (``believe_failures`` with k > 1), q = Q0, value = V0 and failed_value = V1 of ``belief_value_iteration``
    """
    v_s = np.asarray(v_s, dtype=float)
    if config.choice_radius > 0 and pushes is None and len(next_pose):
        raise ValueError("mdp.choice_radius > 0 chooses value iteration's push by its neighbourhood: give each pose's pushes")
    if config.plans_with_failures:
        v_t, failed, q, _ = belief_value_iteration(next_pose, v_s, config.gamma, config.after_failure_power, config.tolerance,
                                                   config.max_iterations, choosable)
    else:
        v_t, q = value_iteration(next_pose, v_s, config.gamma, config.tolerance, config.max_iterations, choosable,
                                 config.retry_failed)
        failed = v_t if config.retry_failed else v_s
    ranked = q
    if config.choose_for_repeats:
        _, ranked = repeat_value_iteration(next_pose, v_s, config.gamma, config.after_failure_power, config.tolerance,
                                           config.max_iterations, choosable, config.repeats_then_grasp)
    greedy = greedy_values(next_pose, v_s)
    out = []
    for x in range(len(v_s)):
        mine = True if choosable is None else np.asarray(choosable[x], dtype=bool)
        choice = (value_iteration_policy(x, v_s, np.where(mine, ranked[x], np.nan), config.gamma)
                  if config.choice_radius == 0 else neighbourhood_choice(x, v_s, ranked[x], *pushes[x], mine, config))
        if choice.action != NO_OP:
            choice = PolicyChoice(choice.action, float(q[x][choice.action]))  # the stored Q of the push, whatever ranked it
        policies = {
            "max_height": max_height_policy(x, v_s, int(max_height_actions[x]), greedy[x]),
            "greedy": greedy_policy(x, v_s, np.where(mine, greedy[x], np.nan)),
            "value_iteration": choice,
        }
        out.append(PoseValues(q=q[x], greedy=greedy[x], value=float(v_t[x]), policies=policies, failed_value=float(failed[x])))
    return out


def is_selected(v_s: np.ndarray, com_heights: np.ndarray, high: float = 0.5, low: float = 0.25) -> bool:
    """Object selection rule of thesis 4.4.1: keep an object that has a pose with
    V_s > ``high`` and a pose with V_s < ``low`` whose centre of mass is lower than
    that of the high-quality pose (toppling it up is then the interesting problem).

    v_s : (P,) float;  com_heights : (P,) float, m, centre of mass above the table
    """
    v_s = np.asarray(v_s, dtype=float)
    com = np.asarray(com_heights, dtype=float)
    good, bad = v_s > high, v_s < low
    return bool(np.any(good[:, None] & bad[None, :] & (com[None, :] < com[:, None])))
