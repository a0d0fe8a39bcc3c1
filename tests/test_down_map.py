"""The map of P(topple) for pushes that press down (docs/MODEL.md C.15)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pipeline.model.config import Config, ContactConfig
from pipeline.model.feature_map import (
    DOWN_FEATURES,
    FeatureMapError,
    check_down_weights,
    down_features,
    fit_weights,
    landing_rows,
    map_down_rows,
    mapped_probability,
)
from pipeline.model.recalibration import fit
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.frames import transform_points
from schema.vocabulary import STATUS_OK
from tests.test_smoothing import pose_and_candidates  # noqa: F401 (fixture: random_object(3), pose 2, 80 contacts)
from tests.test_validation import model_logs  # noqa: F401 (fixture)

IDENTITY = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
"""q = sigmoid(logit P): P itself wherever P is inside the logit's clip."""
WEIGHTS = (-0.5, 0.6, 0.4, 1.5, -0.3, -0.8, -1.2, 0.2)

# A standing 5 x 8 x 15 cm box, pose frame: base [-2.5, 2.5] x [-4, 4] cm, centre of mass 7.5 cm up.
BOX_CORNERS = np.array([[0.025, -0.04, 0], [0.025, 0.04, 0], [-0.025, 0.04, 0], [-0.025, -0.04, 0]])  # counter-clockwise
BOX_EDGES = np.stack([BOX_CORNERS, np.roll(BOX_CORNERS, -1, axis=0)], axis=1)  # (4, 2, 3)
BOX_COM = np.array([0.0, 0.0, 0.075])


def test_features_of_a_standing_box_follow_their_definitions():
    points = np.array([[0.0, 0.0, 0.15], [0.025, 0.01, 0.06], [0.045, 0.0, 0.1]])
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0.6, 0, 0.8]])
    down = np.array([0.0, -0.6, -0.8])
    directions = np.array([[0, 0, -1.0], [-0.8, 0, -0.6], down])
    f = down_features(np.array([0.2, 0.5, np.nan]), points, normals, directions, BOX_EDGES, BOX_COM)
    column = {name: f[:, i] for i, name in enumerate(DOWN_FEATURES)}
    assert np.allclose(column["bias"][:2], 1.0) and np.allclose(column["logit_p"][:2], np.log([0.25, 1.0]))
    assert np.allclose(column["direction_z"][:2], [-1.0, -0.6])
    # The top's centre is 2.5 cm inside the nearest edge, the side face's point on the edge line.
    assert column["overhang"][:2] == pytest.approx([-0.025 / 0.075, 0.0])
    assert column["height"][:2] == pytest.approx([2.0, 0.8])
    assert column["normal_z"][:2] == pytest.approx([1.0, 0.0])
    assert column["stability"][:2] == pytest.approx([0.025 / 0.075] * 2), "the centre of mass is 2.5 cm inside the near edges"
    assert column["offset"][:2] == pytest.approx([0.0, np.hypot(0.025, 0.01) / 0.075])
    assert np.all(np.isnan(f[2])), "a push that is not ok (P NaN) has no features"
    # A point 2 cm beyond the edge overhangs by 2 cm, whatever its height.
    beyond = down_features(np.array([0.3]), points[2:], normals[2:], directions[2:], BOX_EDGES, BOX_COM)
    assert beyond[0, DOWN_FEATURES.index("overhang")] == pytest.approx(0.02 / 0.075)


def _rows(p_leave, n_poses=3, start=0):
    rows = np.zeros((len(p_leave), n_poses))
    rows[:, start] = 1.0 - np.asarray(p_leave)
    rows[:, 1] = p_leave
    return rows


def _pushes(n):
    """n pushes along the box's +x face, alternately from above (u_z -0.9) and from the side."""
    points = np.column_stack([np.full(n, 0.025), np.linspace(-0.03, 0.03, n), np.full(n, 0.1)])
    normals = np.tile([1.0, 0, 0], (n, 1))
    side, above = np.array([-1.0, 0, 0]), np.array([-np.sqrt(1 - 0.81), 0, -0.9])
    directions = np.array([above if i % 2 == 0 else side for i in range(n)])
    return points, normals, directions


def test_only_pushes_below_the_cut_are_mapped_and_rows_stay_distributions():
    points, normals, directions = _pushes(6)
    counted = _rows([0.1, 0.2, 0.3, 0.4, 0.0, 0.6])
    mapped_before = _rows([0.15, 0.25, 0.35, 0.45, 0.05, 0.65])  # a C.7 map of the counts, say
    out, p = map_down_rows(mapped_before, counted, 0, points, normals, directions, BOX_EDGES, BOX_COM, WEIGHTS, -0.3)
    side = directions[:, 2] >= -0.3
    assert np.array_equal(out[side], mapped_before[side]), "a push the policies may choose keeps its row exactly"
    q = mapped_probability(down_features(1 - counted[:, 0], points, normals, directions, BOX_EDGES, BOX_COM), WEIGHTS)
    assert np.allclose(p[~side], q[~side]), "read from the counted P, not from the row C.7 mapped"
    assert np.allclose(out.sum(axis=1), 1.0) and np.allclose(out[~side, 2], 0.0), "a down push lands where the pose's pushes land"
    same, _ = map_down_rows(mapped_before, counted, 0, points, normals, directions, BOX_EDGES, BOX_COM, (), -0.3)
    assert np.array_equal(same, mapped_before), "no weights, no map"
    identity, p_identity = map_down_rows(counted, counted, 0, points, normals, directions, BOX_EDGES, BOX_COM, IDENTITY, -0.3)
    assert np.allclose(p_identity[[0, 2]], [0.1, 0.3]) and np.allclose(identity[[0, 2]], counted[[0, 2]])
    # The push from above that never toppled (index 4) borrows its neighbours' landing, pose 1.
    assert p[4] > 0 and out[4, 1] == pytest.approx(p[4])
    everything, _ = map_down_rows(mapped_before, counted, 0, points, normals, directions, BOX_EDGES, BOX_COM, WEIGHTS, 1.0)
    assert not np.allclose(everything[side], mapped_before[side]), "a cut above every push maps every push"


def test_a_pose_nothing_leaves_keeps_its_rows_and_rows_that_are_not_ok_stay_nan():
    points, normals, directions = _pushes(4)
    counted = _rows([0.0, 0.0, 0.0, 0.0])
    counted[2] = np.nan
    out, p = map_down_rows(counted, counted, 0, points, normals, directions, BOX_EDGES, BOX_COM, WEIGHTS, -0.3)
    assert np.array_equal(out, counted, equal_nan=True) and np.allclose(p[[0, 1, 3]], 0.0), "nowhere to land: no topple"


def test_bad_weights_are_refused_and_the_map_belongs_to_the_corrected_variant():
    check_down_weights(())
    check_down_weights(WEIGHTS)
    for bad in [(1.0, 2.0), WEIGHTS[:-1] + (np.nan,)]:
        with pytest.raises(FeatureMapError, match="topple.down_map needs 8"):
            check_down_weights(bad)
    with pytest.raises(ValueError, match="down_map"):
        Config().with_overrides({"topple.down_map": "1,2,3"})
    with pytest.raises(ValueError, match="down_map_z"):
        Config().with_overrides({"topple.down_map_z": -2.0})
    topple = replace(Config().topple, down_map=WEIGHTS)
    assert topple.applied_down_map == WEIGHTS and topple.needs_candidates
    assert replace(topple, variant="robust").applied_down_map == ()
    assert topple.without_recalibration().down_map == () and topple.counted().down_map == ()
    assert Config().topple.down_map_z == Config().mdp.min_direction_z, "no push the policies choose is mapped"


def test_the_engine_maps_the_down_pushes_from_their_counted_rows_and_no_other(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    base = replace(Config().topple, n_trials=40, down_map=())
    weights = WEIGHTS

    def table(t):
        return evaluate_pose(obj, pose, len(pose_set.poses), actions, t, stream(3, obj.name, pose.index, "trials"))

    plain, mapped, counted = table(base), table(replace(base, down_map=weights)), table(base.without_recalibration())
    ok = actions.status == STATUS_OK
    down = ok & (actions.directions[:, 2] < base.down_map_z)
    assert down.sum() >= 5 and (ok & ~down).sum() >= 5, "the test needs pushes of both kinds"
    assert np.array_equal(mapped.next_pose[~down], plain.next_pose[~down], equal_nan=True)
    com = transform_points(pose.transform, obj.center_mass[None])[0]
    f = down_features(counted.p_topple, actions.points, actions.normals, actions.directions, pose.base_edges, com)
    q = mapped_probability(f, weights)
    lands = landing_rows(counted.next_pose, pose.index, actions.points, actions.directions).sum(axis=1) > 0
    assert np.allclose(mapped.p_topple[down], np.where(lands, q, 0.0)[down])
    assert np.allclose(mapped.next_pose[ok].sum(axis=1), 1.0) and np.array_equal(mapped.outcomes, plain.outcomes)


def test_recalibrate_down_fits_the_centred_map_on_all_pushes_and_the_down_map_on_its_own(model_logs, tmp_path):  # noqa: F811
    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    contacts = ContactConfig(n_contacts=CANDIDATES_PER_POSE)
    # A cut above every push maps them all, which a few boxes' logged pushes can fit.
    topple = replace(Config().topple, down_map_z=1.0)
    scorer = Scorer(log, seed=2, contacts=contacts)
    features, p = scorer.down_features(topple)
    assert np.allclose(p, scorer.score(topple.without_recalibration()).p_topple), "features come from the model with no map"
    assert np.all(np.isfinite(features))
    out, record = tmp_path / "down.toml", tmp_path / "down.json"
    common = ["--corpus", "none", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}", "--seed", "2",
              "--set", "seed=2", "--out", str(out), "--json", str(record)]
    assert main([str(path), "--down", "--set", "topple.down_map_z=1.0", *common]) == 0
    result = json.loads(record.read_text())
    written = Config.from_toml(out).topple
    observed, repeats = scorer.empirical_topple, scorer.repeats
    assert np.allclose(written.down_map, fit_weights(features, observed, repeats)) and written.down_map_z == 1.0
    knots = fit("centred", p, observed, repeats.astype(float))
    assert np.allclose(written.recalibration_x, knots.x) and np.allclose(written.recalibration_y, knots.y)
    assert result["down_pushes"]["pushes"] == len(p) and result["other_pushes"]["pushes"] == 0
    # Every push mapped: held out, the down map's predictions are the fold-fitted logistic's, not the centred map's.
    assert result["cross_validated"]["down_map"] == result["down_pushes"]["down_map"]
    assert result["cross_validated"]["centred"]["brier"] != result["cross_validated"]["down_map"]["brier"]
    # A cut below every push leaves nothing to fit: a clear error, nothing written.
    out.unlink()
    assert main([str(path), "--down", "--set", "topple.down_map_z=-1.0", *common]) == 2 and not out.exists()
    assert main([str(path), "--down", "--features", *common]) == 2

