"""After a failed push: the candidates it rules out, and the best push among the rest.

A push's outcome is nearly fixed by the push.  Replayed in pybullet with fresh noise, the
held-out log's pushes predict themselves with informative sup-TV 0.08, and value
iteration's repeats of a push that had just left the object in its pose toppled 12 % of the
time where its table said 31 % (docs/VALIDATION.md, "Do not push again where a push
failed").  The dataset's tables treat every push as a fresh draw, so a client that reports
its failed pushes gets a push that has not failed, chosen by the policy's own rule among
the candidates no failed push rules out: the failed push and its neighbourhood (contacts
within ``neighbourhood.RADIUS``, directions within ``neighbourhood.MAX_ANGLE``), whose
outcomes the failure has made unlikely too.

numpy only: the service and the pipeline's studies share it.
"""

from __future__ import annotations

import numpy as np

from . import neighbourhood
from .vocabulary import NO_OP

POLICY_IMPROVEMENT = 1e-12
"""The margin by which the dataset's greedy and value iteration push only when a push beats
grasping now (``pipeline.model.mdp.IMPROVEMENT``, held equal by a test): with it the service's
choice over every candidate is the stored policy's."""


def ruled_out(
    points: np.ndarray,
    directions: np.ndarray,
    failed: np.ndarray,
    radius: float = neighbourhood.RADIUS,
    max_angle: float = neighbourhood.MAX_ANGLE,
) -> np.ndarray:
    """The candidates of one pose in the neighbourhood of any failed push, the failed ones included.

    points : (A, 3) float, m, the pose's candidate contacts;  directions : (A, 3) float, unit
    failed : (F,) int, indices of the failed pushes among the A candidates (F may be 0)
    returns : (A,) bool
    """
    points, directions = np.asarray(points, dtype=float), np.asarray(directions, dtype=float)
    failed = np.unique(np.asarray(failed, dtype=np.int64))
    if len(failed) == 0:
        return np.zeros(len(points), dtype=bool)
    return neighbourhood._near(points, directions, failed, radius, max_angle).any(axis=0)


def impossible_failure(failed, ok: np.ndarray) -> tuple[int, int, bool] | None:
    """The first reported failure that cannot be one: an index the pose does not have, or a push
    that is not ok (no policy serves it, and it would rule out the ok pushes around it).

    failed : (F,) int, as reported;  ok : (A,) bool, the pose's ok candidates
    returns : (position in ``failed``, the index, whether the pose has it at all), or None
    """
    for position, action in enumerate(failed):
        if not 0 <= action < len(ok):
            return position, int(action), False
        if not ok[action]:
            return position, int(action), True
    return None


def best_untried(values: np.ndarray, allowed: np.ndarray, stay: float, improvement: float, scale: float = 1.0) -> int:
    """The allowed candidate of largest value, pushed only if ``scale`` times its value beats
    grasping now.

    The rule of the dataset's policies (``pipeline.model.mdp``: greedy with the expected V_s
    after the push, value iteration with Q_T and scale gamma) and of the budgets
    (``schema.horizon``, Q_h), over the candidates ``allowed``; the first of equal values
    wins, as there.
    values : (A,) float, NaN for candidates that cannot be pushed;  allowed : (A,) bool
    stay : V_s of the pose (grasping now);  improvement : the margin a push must beat it by
    returns : the candidate's index, or NO_OP
    """
    values = np.where(np.asarray(allowed, dtype=bool), np.asarray(values, dtype=float), np.nan)
    if values.size == 0 or np.isnan(values).all():
        return NO_OP
    action = int(np.nanargmax(values))
    return action if scale * values[action] > stay + improvement else NO_OP


def choose_untried(values: np.ndarray, points: np.ndarray, directions: np.ndarray, failed, choosable: np.ndarray,
                   stay: float, improvement: float, scale: float = 1.0) -> tuple[int, int]:
    """The policy's push once ``failed`` pushes of a pose have failed: ``best_untried`` over its
    choosable candidates that no failed push rules out (``ruled_out``), and how many choosable
    candidates they ruled out (what /plan and the Python API's plan report as ``ruled_out``).

    values : (A,) float, the policy's ranking;  points, directions, failed : as ``ruled_out``
    choosable : (A,) bool;  stay, improvement, scale : as ``best_untried``
    returns : (action index or NO_OP, ruled-out count)
    """
    excluded = ruled_out(points, directions, failed)
    choosable = np.asarray(choosable, dtype=bool)
    return best_untried(values, choosable & ~excluded, stay, improvement, scale), int((excluded & choosable).sum())


def after_failure(p_topple: float, power: float) -> float:
    """A push's P(topple) once a push from the same pose has failed: p^k, k = ``power``
    (``mdp.after_failure_power``, fitted on corpus objects in pybullet).

    A failure is evidence about the pose, not only about the failed push: in physics, value
    iteration's next pushes after one toppled half as often as their P(topple) (0.122 against
    0.244 on corpus objects), least so for the pushes the table is sure of.  Greedy and the
    budgets only report it; value iteration also ranks its pushes by it (``believed_values``).
    p_topple : float, clipped to [0, 1] (``clip_probability``);  returns : float
    """
    return float(clip_probability(p_topple)) ** power


def clip_probability(p_topple) -> np.ndarray:
    """P(topple) held to [0, 1], NaN kept: 1 - P(x | x, u) can round a hair outside, and every
    belief here raises p to a power, which a negative base would make complex.
    p_topple : float or (N,) float;  returns : float array of the same shape"""
    return np.clip(np.asarray(p_topple, dtype=float), 0.0, 1.0)


def failed_ratios(p_topple: np.ndarray, power: float) -> tuple[np.ndarray, np.ndarray]:
    """A push's two factors in docs/MODEL.md (12.13)-(12.14) once a push from its pose has failed:
    b = p^(k-1), the ratio of its believed topple chance to its P, and p^k, that chance (0^0 is 1,
    harmless: a push that never topples leaves nothing).

    p_topple : (N,) float, clipped to [0, 1] (``clip_probability``);  power : k
    returns : b, p^k, (N,) float each"""
    p = clip_probability(p_topple)
    ratio = np.power(p, power - 1.0)
    return ratio, p * ratio


def believed_values(q: np.ndarray, p_topple: np.ndarray, stay: float, v_t: float, power: float) -> np.ndarray:
    """Value iteration's Q of a pose's pushes once a push from it has failed (docs/MODEL.md (12.12)).

    The table's Q_T(x, u) = p T + (1 - p) F, T the mean V_T of where a topple lands and F what the
    table counted a failure at: V_T(x) (the thesis's retries) or V_s(x) (``mdp.retry_failed``
    false, (12.9)); ``v_t`` is that F, so the caller passes V_s(x) for such a build.  After
    a failure u topples with p^k (``after_failure``), and a push that fails again is worth the
    grasp here, so Q'' = V_s(x) + p^k (T - V_s(x)): the believed chance of a topple times what
    it gains.  A long shot that the table values for its retries loses to a likelier push, and
    a pose whose pushes are all unlikely now is grasped.
    q, p_topple : (A,) float, NaN unless ok, p clipped to [0, 1];  stay : V_s(x);  v_t : F, V_T(x) (the pose's stored value)
      or V_s(x) without retries
    power : k;  returns : (A,) float, Q'' (NaN where q is)
    """
    q, p = np.asarray(q, dtype=float), clip_probability(p_topple)
    return stay + np.power(p, power - 1.0) * (q - (1.0 - p) * v_t) - np.power(p, power) * stay


def failed_state_values(q0: np.ndarray, p_topple: np.ndarray, stay: float, gamma: float, power: float,
                        choosable: np.ndarray) -> np.ndarray:
    """Q1 of a pose's pushes once a push from it has failed, from a build that believes failures
    (docs/MODEL.md (12.13)), read off its stored Q0 alone.

    With b = p^(k-1), Q1(x, u) = b Q0(x, u) + (1 - b) V1(x): Q0 = S + (1 - p) V1 and
    Q1 = b S + (1 - p^k) V1 share S, the value of where a topple lands.  Each push's Q1 is affine
    in V1 with slope below 1, so V1 = max(V_s, gamma max_u Q1) is the largest of V_s and each
    push's own fixed point gamma b Q0 / (1 - gamma + gamma b), over the choosable pushes.
    q0, p_topple : (A,) float, NaN unless ok;  stay : V_s(x);  gamma : discount;  power : k
    choosable : (A,) bool, the pushes value iteration plans over
    returns : (A,) float, Q1 (NaN where q0 is)
    """
    q0 = np.asarray(q0, dtype=float)
    believed, _ = failed_ratios(p_topple, power)
    loop = 1.0 - gamma + gamma * believed
    # A push that never topples again has no fixed point above the grasp (0 / 0 when gamma = 1).
    own = np.divide(gamma * believed * q0, loop, out=np.zeros_like(loop), where=loop > 0)
    own = np.where(np.asarray(choosable, dtype=bool), own, np.nan)
    failed = max(stay, float(np.nanmax(own))) if np.isfinite(own).any() else stay
    return believed * q0 + (1.0 - believed) * failed


def has_map(power: float | None) -> bool:
    """Whether a build's ``mdp.after_failure_power`` is a map: None (a build from before it)
    and 1 (the thesis preset) leave P(topple) and value iteration's ranking as the table's."""
    return power is not None and power != 1.0


def given_failures(p_topple: float, power: float | None) -> float | None:
    """``p_topple_given_failures``: ``after_failure`` when the build has a map, else None."""
    return after_failure(p_topple, power) if has_map(power) else None


def ranking_values(q: np.ndarray, p_topple: np.ndarray, stay: float, v_t: float, power: float | None,
                   retry_failed: bool, *, believes: bool = False, gamma: float | None = None,
                   choosable: np.ndarray | None = None) -> np.ndarray:
    """What value iteration ranks a pose's untried pushes by after a failure: with a map, Q1 of a
    build that believes failures (``failed_state_values``, ``believes``, then ``gamma`` and
    ``choosable`` are the build's), else ``believed_values`` (the failure counted at V_T(x), or at
    V_s(x) when the build's Q_T does not retry, ``mdp.retry_failed`` false); without a map the
    table's Q.  The service, the Python API's ``plan`` and the robust-choice study all rank by it.

    q, p_topple : (A,) float;  stay : V_s(x);  v_t : V_T(x);  choosable : (A,) bool
    returns : (A,) float
    """
    if not has_map(power):
        return np.asarray(q, dtype=float)
    if believes:
        if gamma is None or choosable is None:
            raise ValueError("a build that believes failures ranks by Q1, which needs its gamma and choosable pushes")
        return failed_state_values(q, p_topple, stay, gamma, power, choosable)
    return believed_values(q, p_topple, stay, v_t if retry_failed else stay, power)
