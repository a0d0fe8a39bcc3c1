"""A push's landing trusted by how rare its landing pose is (candidate LT, stop 50).

Where a push's row lands a topple in a pose of low drop probability, physics often brings the object
to rest elsewhere (docs/VALIDATION.md, stops 34 and 39), and the planners, which choose pushes for
where the row lands them, pick those over-valued landings.  So before a pose's pushes are valued, a
share u_b of the landing on each pose y moves to the drop-probability prior over the poses other
than the start pose x, b the band of y's drop probability d_y (``BANDS``):

    s'_y = (1 - u_b(y)) s_y + pi_y / (sum_{z != x} pi_z) * sum_z u_b(z) s_z,    y != x            (LT.1)

with s the leaving part of the row (sums to P(topple)) and pi the drop probabilities (the prior is
``landing_spread.landing_prior`` over every other pose; with none of positive pi, nothing moves).  The stay
s_x, hence P(topple), is unchanged.  The rows are linear in u, so the shares are fitted by least
squares (``trust_terms``).  numpy only.
"""

from __future__ import annotations

import numpy as np

from .landing_spread import landing_prior

BANDS = (0.05, 0.1, 0.2)
"""Upper edges of the drop-probability bands of a landing pose: (0, 0.05], (0.05, 0.1], (0.1, 0.2],
above 0.2 (the bands of reports/landing_drawn_s34.md, where a topple misses the row's landing in 67,
33, 15 and 4 % of the corpus's drawn pushes)."""


def landing_bands(drop_probabilities: np.ndarray) -> np.ndarray:
    """Band of each pose's drop probability.

    drop_probabilities : (P,) float
    returns : (P,) int in [0, len(BANDS)]
    """
    return np.searchsorted(np.asarray(BANDS, dtype=float), np.asarray(drop_probabilities, dtype=float), side="left")


def trust_terms(rows: np.ndarray, pose: int, drop_probabilities: np.ndarray) -> np.ndarray:
    """How each band's untrusted share moves each row: (LT.1) is ``rows + terms @ u``.

    rows : (A, P) float, P(x' | x, u) (NaN rows are not ok and get no terms);  pose : x
    drop_probabilities : (P,) float
    returns : (A, P, len(BANDS) + 1) float; term b is -s_y on the landings in band b, and their
      sum spread over the prior (LT.1); each term sums to 0 over x', so P(topple) never moves;
      all 0 when no other pose has a drop probability
    """
    leaving = np.nan_to_num(np.asarray(rows, dtype=float), nan=0.0)
    leaving[:, pose] = 0.0
    band = landing_bands(drop_probabilities)
    # Every other pose with a drop probability (C.17.1 with k unbounded); none: nothing moves.
    prior = landing_prior(drop_probabilities, pose, len(leaving[0]))
    terms = np.zeros(leaving.shape + (len(BANDS) + 1,))
    for b in range(len(BANDS) + 1):
        moved = np.where(band == b, leaving, 0.0) if prior.any() else np.zeros_like(leaving)
        terms[:, :, b] = moved.sum(axis=1, keepdims=True) * prior - moved
    return terms


def checked_shares(untrusted) -> np.ndarray:
    """The untrusted shares u_b as an array, or ValueError saying what they must be.

    untrusted : (len(BANDS) + 1,) numbers in [0, 1]"""
    shares = np.asarray(untrusted, dtype=float)
    if shares.shape != (len(BANDS) + 1,) or not np.all((shares >= 0) & (shares <= 1)):
        raise ValueError(f"the untrusted shares are {len(BANDS) + 1} numbers in [0, 1], one per band of drop probability "
                         f"(edges {', '.join(map(str, BANDS))}); got {shares.tolist()}")
    return shares


def trusted_rows(rows: np.ndarray, pose: int, drop_probabilities: np.ndarray, untrusted: np.ndarray) -> np.ndarray:
    """(LT.1): ``rows`` with each band's untrusted share of its landings moved to the prior.

    rows : (A, P) float, NaN rows unless ok (kept NaN);  pose : x;  drop_probabilities : (P,) float
    untrusted : (len(BANDS) + 1,) float in [0, 1], u_b per band
    returns : (A, P) float; ``rows`` itself when every share is 0
    """
    untrusted = checked_shares(untrusted)
    if not untrusted.any():
        return rows
    rows = np.asarray(rows, dtype=float)
    return rows + trust_terms(rows, pose, drop_probabilities) @ untrusted
