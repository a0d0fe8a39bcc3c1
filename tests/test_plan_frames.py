# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
"""Frames of POST /plan when the observed object is not on the table plane z = 0.

The observed pose is ``lift(dz) @ planar @ T_p``: a stable pose p, moved in the plane,
then raised by dz (a depth sensor's offset, a tray, a stacked object).  Matching must
not depend on dz, and /plan must report it as ``match.z_offset``: the stored pushes
assume the object rests on z = 0, so the height is what tells a client (or the
service) that it does not.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

from schema.frames import match_pose
from service import create_app
from tests.test_service import dataset, planar_transform  # noqa: F401 (fixture)

OBJECT = "random_001"
LIFTS = [0.0, 0.012, -0.004, 0.25]  # m
PLAN_LIFTS = [0.0, 0.003, -0.002]  # m, small enough to count as resting on the table (a few mm of sensor error)


def lift(dz: float) -> np.ndarray:
    up = np.eye(4)
    up[2, 3] = dz
    return up


@pytest.fixture(scope="module")
def poses(dataset) -> dict[int, dict]:
    return {r["pose"]: r for r in pq.read_table(dataset / "poses.parquet").to_pylist() if r["object_id"] == OBJECT}


def _downs_and_transforms(poses):
    order = sorted(poses)
    downs = np.array([[poses[p][f"down_{a}"] for a in "xyz"] for p in order], dtype=float)
    transforms = np.array([np.reshape(poses[p]["transform"], (4, 4)) for p in order], dtype=float)
    return downs, transforms


@pytest.mark.parametrize("dz", LIFTS)
def test_match_pose_ignores_height_and_keeps_it_out_of_the_planar_transform(poses, dz):
    downs, transforms = _downs_and_transforms(poses)
    rng = np.random.default_rng(11)
    for pose in sorted(poses):
        planar = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.4, 0.4, 2))
        observed = lift(dz) @ planar @ transforms[pose]
        match = match_pose(observed, downs, transforms, tolerance=0.01)
        assert match.pose == pose
        np.testing.assert_allclose(match.planar, planar, atol=1e-12)  # no z in the planar transform
        # What is left over once the planar part and the stable pose are undone is the lift alone.
        np.testing.assert_allclose(np.linalg.inv(match.planar) @ observed @ np.linalg.inv(transforms[pose]), lift(dz), atol=1e-12)


def test_plan_reports_the_observed_height_as_z_offset(dataset, poses):
    _, transforms = _downs_and_transforms(poses)
    rng = np.random.default_rng(12)
    with TestClient(create_app(dataset)) as client:
        for pose in sorted(poses):
            planar = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.4, 0.4, 2))
            for dz in PLAN_LIFTS:
                observed = lift(dz) @ planar @ transforms[pose]
                response = client.post("/plan", json={"object_id": OBJECT, "pose": observed.tolist()})
                assert response.status_code == 200, response.text
                match = response.json()["match"]
                assert match["pose"] == pose and match["angle_error"] < 1e-6
                assert match["z_offset"] == pytest.approx(dz, abs=1e-12)
                np.testing.assert_allclose(match["planar"], planar, atol=1e-12)
                np.testing.assert_allclose(match["translation"], planar[:2, 3], atol=1e-12)
