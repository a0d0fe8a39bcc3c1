"""Marginal landings carried on one fall further (docs/MODEL.md C.18).

Where the model lands a topple in a pose of low drop probability, physics often does not leave it
there: the object enters such a pose shallowly, and the finger, still advancing along its stroke,
takes it over the next edge.  So a share ``alpha`` of each trial's landing in a pose of drop
probability at most ``tau`` goes on to the edge's onward pose (``StablePose.edge_onward_pose``,
the pose C.8's chain stopped short of):

    1 - a_e  in q,   a_e  in q',    a_e = alpha  if pi(q) <= tau, q' != q, q' != s, q != s;  else 0     (C.18.1)

with q the edge's landing, q' its onward pose and s the start pose.  Mass never moves into or out
of s, so P(topple) is unchanged.  numpy only.
"""

from __future__ import annotations

import numpy as np


def onward_shares(landed: np.ndarray, onward: np.ndarray, start: int, drop_probabilities: np.ndarray, share: float,
                  below: float) -> np.ndarray:
    """(C.18.1): share of each edge's topples carried on to its onward pose.

    Landings in poses of drop probability above ``below`` keep their mass, as do edges whose
    onward pose is their landing (nothing lies ahead), whose landing is the start pose (the chain
    rolled back into it) or whose onward pose is (two falls back into it, on a symmetric object
    whose poses were merged): so P(topple) never changes.

    landed, onward : (E,) int, each edge's landing and onward pose (indices into the pose set;
      an entry equal to ``start`` is a trial that stays)
    start : the pose the object leaves
    drop_probabilities : (P,) float, the pose set's;  share : alpha in [0, 1];  below : tau
    returns : (E,) float in [0, share]
    """
    marginal = np.asarray(drop_probabilities, dtype=float)[landed] <= below
    return np.where(marginal & (onward != landed) & (onward != start) & (landed != start), float(share), 0.0)
