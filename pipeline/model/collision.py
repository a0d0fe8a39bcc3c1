"""Collision checks with python-fcl: a mesh against many placed copies of one
primitive (the finger's capsule, the suction gripper's cylinder).

fcl has no batched query, so ``collides_each`` loops over placements; callers
first drop the placements that an analytic test (the table plane) already decides.
"""

from __future__ import annotations

import fcl
import numpy as np
import trimesh

from schema.frames import z_to_axes


def collision_object(mesh: trimesh.Trimesh) -> fcl.CollisionObject:
    """An fcl BVH of the mesh in its own frame (built once per object)."""
    model = fcl.BVHModel()
    model.beginModel(len(mesh.vertices), len(mesh.faces))
    model.addSubModel(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int32))
    model.endModel()
    return fcl.CollisionObject(model, fcl.Transform())


def collides_each(shape: fcl.CollisionGeometry, centers: np.ndarray, axes: np.ndarray, target: fcl.CollisionObject) -> np.ndarray:
    """Whether ``shape`` (a capsule or cylinder along its own z), placed at each
    centre with its z along each axis, intersects ``target``.

    centers : (n, 3) float, m, in the target's frame
    axes : (n, 3) float, unit, in the target's frame
    returns : (n,) bool
    """
    hits = np.zeros(len(centers), dtype=bool)
    if len(centers) == 0:
        return hits
    request, rotations = fcl.CollisionRequest(), z_to_axes(axes)
    for i in range(len(centers)):
        placed = fcl.CollisionObject(shape, fcl.Transform(rotations[i], centers[i]))
        hits[i] = fcl.collide(placed, target, request, fcl.CollisionResult()) > 0
    return hits
