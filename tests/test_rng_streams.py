"""Seeded random streams (pipeline/model/rng.py): one independent stream per
(seed, object, pose, purpose), and each stage of an object's evaluation drawing
from its own purpose's stream, so that e.g. changing the suction sampling never
changes a topple trial and one pose can be recomputed alone."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pytest
from shapes import DATA

from pipeline.api import evaluate
from pipeline.model.config import Config
from pipeline.model.contacts import object_contacts, surface_points
from pipeline.model.evaluation import load_object, process_object
from pipeline.model.poses import stable_poses
from pipeline.model.rng import PURPOSES, stream
from pipeline.model.suction import suction_quality
from schema.frames import transform_points

DRAWS = 8


def _draws(seed, object_id, pose, purpose):
    return stream(seed, object_id, pose, purpose).random(DRAWS)


@pytest.mark.parametrize("pose", [-1, 0, 3])
def test_each_purpose_has_its_own_stream(pose):
    draws = {purpose: _draws(7, "random_001", pose, purpose) for purpose in PURPOSES}
    assert {"contacts", "trials", "suction"} <= set(draws)
    for a, b in combinations(PURPOSES, 2):
        assert not np.array_equal(draws[a], draws[b]), f"purposes {a!r} and {b!r} share a stream"


def test_streams_are_reproducible_and_keyed_by_seed_object_and_pose():
    first = _draws(7, "random_001", 2, "trials")
    np.testing.assert_array_equal(first, _draws(7, "random_001", 2, "trials"))
    for other in [(8, "random_001", 2), (7, "random_002", 2), (7, "random_001", 3), (7, "random_001", -1)]:
        assert not np.array_equal(first, _draws(*other, "trials")), other


def test_unknown_purpose_is_rejected():
    with pytest.raises(ValueError, match="unknown random stream purpose 'noise'"):
        stream(0, "random_001", 0, "noise")


@dataclass
class _Spec:
    object_id: str
    path: str
    scale: float
    mass: float


@pytest.fixture(scope="module")
def processed():
    config = Config().with_overrides(
        {"seed": 3, "contacts.n_contacts": 20, "topple.n_trials": 6, "suction.n_candidates": 12, "suction.n_samples": 4}
    )
    spec = _Spec("random_001", f"{DATA}/random_urdfs/001/001.obj", 0.015, 0.1)
    return spec, config, load_object(spec, config), process_object(spec, config)


def test_contacts_come_from_the_contacts_stream(processed):
    _, config, obj, _ = processed
    c = config.contacts
    points, normals = object_contacts(obj, c, config.seed)
    expected = surface_points(obj.mesh, c.n_contacts, stream(config.seed, obj.name, -1, "contacts"), c.oversample)
    np.testing.assert_array_equal(points, expected[0])
    np.testing.assert_array_equal(normals, expected[1])


def test_each_pose_is_recomputed_alone_from_its_own_streams(processed):
    # What the dataset job stores for pose p equals evaluating pose p by itself from the
    # (seed, object, p, "trials") and (seed, object, p, "suction") streams.
    _, config, obj, result = processed
    assert len(result.poses) >= 2
    pose_set = stable_poses(obj, config.poses)
    found_grasp = False
    for pose in result.poses:
        alone = evaluate(obj, pose_set, pose.index, seed=config.seed, config=config)
        np.testing.assert_array_equal(alone.actions.points, result.actions[pose.index].points)
        np.testing.assert_array_equal(alone.table.outcomes, result.topple[pose.index].outcomes)

        mesh = obj.mesh.copy()
        mesh.apply_transform(pose.transform)
        center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
        rng = stream(config.seed, obj.name, pose.index, "suction")
        suction = suction_quality(mesh, center_mass, obj.mass, config.suction, rng, config.topple.gravity)
        stored = result.suction[pose.index]
        assert stored.quality == suction.quality
        np.testing.assert_array_equal(stored.point, suction.point)  # NaN (no grasp) compares equal
        found_grasp |= bool(np.isfinite(stored.point).all())
    assert found_grasp, "some pose should have a grasp, whose point pins the suction draws"
