"""Area-uniform points on a triangle mesh's surface.

Two steps, each a pure function: choose faces with probability proportional to
their area, then place each point in its face from two uniform numbers (folding
the unit square onto the triangle).  The caller draws the uniforms, so each
random stream keeps its own draw order.
"""

from __future__ import annotations

import numpy as np


def area_weighted_faces(areas: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``count`` faces drawn with probability proportional to area.

    areas : (F,) float, m^2, at least one positive
    returns : (count,) int, into ``areas``
    """
    return rng.choice(len(areas), size=count, p=areas / areas.sum())


def points_in_triangles(triangles: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """One uniformly distributed point in each triangle.

    triangles : (n, 3, 3) float, m, corners
    uniforms : (n, 2) float in [0, 1); (u, v) past the diagonal u + v > 1 fold back
      to (1 - u, 1 - v), so the point is uniform over the triangle
    returns : (n, 3) float, m
    """
    fold = uniforms.sum(axis=1) > 1.0
    u = np.where(fold, 1.0 - uniforms[:, 0], uniforms[:, 0])[:, None]
    v = np.where(fold, 1.0 - uniforms[:, 1], uniforms[:, 1])[:, None]
    origin = triangles[:, 0]
    return origin + u * (triangles[:, 1] - origin) + v * (triangles[:, 2] - origin)
