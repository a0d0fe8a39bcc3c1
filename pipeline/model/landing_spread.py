"""Landings spread onto the most stable poses (docs/MODEL.md C.17).

The model's landing is sharp: 77 % of the corpus pushes that topple in the model land in one
pose, yet 22 % of the toppled repeats of the corpus logs land in a pose the model gives that
push no probability (the object rolls on, turns over another edge, or the finger carries it).
Where it lands then is not random: the poses with the largest drop probability, the widest
basins, take most of it.  So a share ``eps`` of every toppling row's landing is moved to the
start pose's ``k`` most probable other stable poses, in proportion to their drop probability:

    L(x')          = pi(x') / sum_{y in K} pi(y)    for x' in K, else 0                (C.17.1)
    P'(x' | x, u)  = (1 - eps) P(x' | x, u) + eps p L(x')    for x' != x                 (C.17.2)
    P'(x | x, u)   = P(x | x, u) = 1 - p                                                 (C.17.3)

with pi the pose set's drop probabilities, K the k poses other than x with the largest pi
(ties broken by pose index), and p = 1 - P(x | x, u) the row's P(topple), which is unchanged:
the spread moves landing mass only, never the topple's probability, so a row that never
topples (p = 0) and a pose with no other pose are left as they are.  numpy only.
"""

from __future__ import annotations

import numpy as np


def landing_prior(drop_probabilities: np.ndarray, start: int, poses: int) -> np.ndarray:
    """(C.17.1): where an unforeseen landing goes from pose ``start``.

    drop_probabilities : (P,) float, the pose set's drop probability of each pose
    start : the pose the object leaves;  poses : k, how many other poses share the landing
    returns : (P,) float, summing to 1 over at most k poses other than ``start`` (0 at
      ``start``), or all zeros when no other pose has a positive drop probability
    """
    pi = np.asarray(drop_probabilities, dtype=float)
    others = np.flatnonzero((np.arange(len(pi)) != start) & (pi > 0))
    # Largest first; the stable sort keeps the lower index first among equal probabilities.
    kept = others[np.argsort(-pi[others], kind="stable")][:poses]
    prior = np.zeros(len(pi))
    if len(kept):
        prior[kept] = pi[kept] / pi[kept].sum()
    return prior


def spread_landings(next_pose: np.ndarray, start: int, prior: np.ndarray, share: float) -> np.ndarray:
    """(C.17.2)-(C.17.3): each row's toppled mass, ``share`` of it moved to ``prior``.

    next_pose : (A, P) float, next-pose rows leaving pose ``start`` (NaN rows: not ok)
    prior : (P,) float, ``landing_prior``'s;  share : eps in [0, 1]
    returns : (A, P) float, every row's P(topple) and sum kept; rows that never topple, NaN
      rows, and every row when ``prior`` is all zeros or ``share`` is 0 are returned as they are
    """
    next_pose = np.array(next_pose, dtype=float)
    if share == 0 or not prior.any():
        return next_pose
    p = 1.0 - next_pose[:, start]  # (A,), NaN for rows that are not ok
    rows = np.flatnonzero(p > 0)
    leaving = next_pose[rows].copy()
    leaving[:, start] = 0.0
    spread = (1.0 - share) * leaving + share * p[rows, None] * prior[None]
    spread[:, start] = next_pose[rows, start]
    next_pose[rows] = spread
    return next_pose
