"""A push's landing doubted by the direction it pushes from (candidate LD, stop 55: judged as a planner and not
adopted, docs/MODEL.md C.21; ``robust_policy --landing-direction`` plays it).

Traced in pybullet (docs/VALIDATION.md, stop 53), value iteration's pushes topple at least as often as
their rows say in every direction, but a topple from above lands in poses worth 0.117 V_s less than the
rows expect, from the side 0.043 and from below nothing: a finger that presses down carries the object
on through falls the model's chain of poses does not derive.  The planners choose pushes for where
their rows land them, so they over-value the pushes from above most.  Until the model derives where
those falls go, a share lambda_c of each push's landing, c its direction class (``CLASSES``), is
replaced by what the pose's pushes land in on average:

    s'_y = (1 - lambda_c) s_y + lambda_c P_u(topple) m_y,    y != x                      (LD.1)

with s the leaving part of push u's row (it sums to P_u(topple)), and m the mean over the pose's
pushes that leave of their landing given a topple (s / P(topple)), which sums to 1.  The stay s_x,
hence P(topple), is unchanged; rows that are not ok, or where nothing leaves, are kept as they are.
The shares are fitted per class by maximum likelihood of where traced plays of corpus objects
landed (``pipeline.studies.landing_direction``).  numpy only.
"""

from __future__ import annotations

import numpy as np

from schema.horizon import choosable_pushes

from .config import FROM_ABOVE_U_Z

CLASSES = ("above", "side", "below")
"""Push directions by u_z in the pose frame, as ``candidate_choice`` and the validation report split
them: from above u_z < -0.3, from the side -0.3 <= u_z < 0.3, from below u_z >= 0.3."""
SIDE_FLOOR, BELOW_FLOOR = FROM_ABOVE_U_Z, 0.3
"""The lowest u_z of the side and from-below classes."""


def direction_classes(direction_z: np.ndarray) -> np.ndarray:
    """Index into ``CLASSES`` of each push.

    direction_z : (A,) float, u_z of the push direction, pose frame (z up), compared in float32 as
      ``schema.horizon.choosable_pushes`` compares it, so the classes split what the policies choose
    returns : (A,) int in {0, 1, 2}
    """
    side_or_below = choosable_pushes(direction_z, SIDE_FLOOR)
    below = choosable_pushes(direction_z, BELOW_FLOOR)
    return side_or_below.astype(int) + below.astype(int)


def checked_doubts(doubts) -> np.ndarray:
    """The shares lambda_c as an array, or ValueError saying what they must be.

    doubts : (len(CLASSES),) numbers in [0, 1]"""
    shares = np.asarray(doubts, dtype=float)
    if shares.shape != (len(CLASSES),) or not np.all((shares >= 0) & (shares <= 1)):
        raise ValueError(f"the doubted shares are {len(CLASSES)} numbers in [0, 1], one per push direction "
                         f"({', '.join(CLASSES)}); got {np.ravel(shares).tolist()}")
    return shares


def leaving_shares(rows: np.ndarray, pose: int) -> tuple[np.ndarray, np.ndarray]:
    """Each push's landing and how likely it leaves: (A, P) float, P(x' | x, u) over the leaving
    part of the row (0 at x and on rows where nothing leaves), and (A,) float, the leaving mass
    (P(topple); 0 on rows that are not ok).  The planners' studies read landings through it too.

    rows : (A, P) float, P(x' | x, u), NaN rows unless ok;  pose : x"""
    leaving = np.nan_to_num(np.asarray(rows, dtype=float), nan=0.0)
    leaving[:, pose] = 0.0
    total = leaving.sum(axis=1)
    return np.divide(leaving, total[:, None], out=np.zeros_like(leaving), where=total[:, None] > 0), total


def mean_landing(rows: np.ndarray, pose: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each push's landing given a topple, how likely it leaves (``leaving_shares``), and the pose's mean
    landing m of (LD.1).

    rows : (A, P) float, P(x' | x, u), NaN rows unless ok;  pose : x
    returns : landing (A, P) float (rows of zeros where nothing leaves), leaving (A,) float
      (P(topple), 0 on rows that are not ok), mean (P,) float (zeros when no push leaves)
    """
    landing, total = leaving_shares(rows, pose)
    leaves = total > 0
    mean = landing[leaves].mean(axis=0) if leaves.any() else np.zeros(landing.shape[1])
    return landing, total, mean


def doubted_rows(rows: np.ndarray, pose: int, direction_z: np.ndarray, doubts) -> np.ndarray:
    """(LD.1): ``rows`` with a share of each push's landing, by its direction class, moved to the pose's mean landing.

    rows : (A, P) float, P(x' | x, u), NaN rows unless ok (kept as they are);  pose : x
    direction_z : (A,) float, each push's u_z, pose frame;  doubts : (len(CLASSES),) float in [0, 1]
    returns : (A, P) float; ``rows`` itself when every share is 0
    """
    doubts = checked_doubts(doubts)
    if not doubts.any():
        return rows
    rows = np.asarray(rows, dtype=float)
    landing, total, mean = mean_landing(rows, pose)
    share = doubts[direction_classes(direction_z)][:, None]  # (A, 1)
    doubted = total[:, None] * ((1.0 - share) * landing + share * mean)  # (A, P), 0 at x
    out = rows.copy()
    leaves = total > 0
    out[leaves] = doubted[leaves]
    out[leaves, pose] = rows[leaves, pose]
    return out
