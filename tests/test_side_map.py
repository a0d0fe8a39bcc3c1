"""The map of P(topple) for pushes from the side the model is unsure of (docs/MODEL.md C.16)."""

from __future__ import annotations

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from pipeline.model.config import PRESETS, Config
from pipeline.model.edges import edge_geometry
from pipeline.model.feature_map import (
    SIDE_BAND,
    FeatureMapError,
    check_side_band,
    check_side_weights,
    fit_weights,
    map_side_rows,
    mapped_probability,
    needed_force_ratio,
    side_features,
    side_rows,
)
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.frames import transform_points
from schema.vocabulary import STATUS_OK
from tests.test_down_map import BOX, BOX_COM, BOX_EDGES, SIDE, _actions
from tests.test_smoothing import pose_and_candidates  # noqa: F401 (fixture: random_object(3), pose 2, 80 contacts)
from tests.test_validation import model_logs  # noqa: F401 (fixture)

IDENTITY = (0.0, 1.0, 0.0)
"""q = sigmoid(logit P): P itself wherever P is inside the logit's clip."""
NARROW = (0.2, 0.8)
"""A band inside the default one."""
WEIGHTS = (-3.0, 0.9, -2.0)
"""The fitted map's shape: a push that needs less force topples more at the same P."""


def test_a_standing_box_needs_its_half_width_over_the_push_height():
    # Pushed along -x on its +x face at height h, the 5 cm wide box turns about the far edge
    # (x = -2.5 cm): F* h = m g 2.5 cm.  Pressing down as well shortens the lever by the vertical
    # part times the 5 cm to that edge; a push straight down has no lever about any base edge.
    heights = np.array([0.03, 0.06, 0.12])
    points = np.column_stack([np.full(3, 0.025), np.zeros(3), heights])
    assert needed_force_ratio(points, np.tile(SIDE, (3, 1)), BOX) == pytest.approx(0.025 / heights)
    pressing = np.array([[-0.8, 0.0, -0.6]])
    assert needed_force_ratio(points[[2]], pressing, BOX)[0] == pytest.approx(0.025 / (0.8 * 0.12 - 0.6 * 0.05))
    assert needed_force_ratio(np.array([[0.0, 0.0, 0.15]]), np.array([[0.0, 0.0, -1.0]]), BOX)[0] == np.inf
    # Along y, the long side: the lever is the same, the centre of mass 4 cm from the far edge.
    assert needed_force_ratio(np.array([[0.0, 0.04, 0.1]]), np.array([[0.0, -1.0, 0.0]]), BOX)[0] == pytest.approx(0.04 / 0.1)
    # The same object elsewhere on the table, or twice the size, needs the same force ratio.
    shift = np.array([0.31, -0.17, 0.0])
    moved = edge_geometry(BOX_EDGES + shift, BOX_COM + shift)
    assert needed_force_ratio(points + shift, np.tile(SIDE, (3, 1)), moved) == pytest.approx(0.025 / heights)
    doubled = edge_geometry(2 * BOX_EDGES, 2 * BOX_COM)
    assert needed_force_ratio(2 * points, np.tile(SIDE, (3, 1)), doubled) == pytest.approx(0.025 / heights)
    f = side_features(np.array([0.3, np.nan]), points[:2], np.tile(SIDE, (2, 1)), BOX)
    assert f[0] == pytest.approx([1.0, np.log(0.3 / 0.7), np.log(0.025 / 0.03)]) and np.all(np.isnan(f[1]))
    # No lever about any edge: an infinite force, clipped so the feature stays finite.
    stuck = side_features(np.array([0.3]), np.array([[0.0, 0.0, 0.15]]), np.array([[0.0, 0.0, -1.0]]), BOX)
    assert stuck[0, 2] == pytest.approx(np.log(1e3))


def _pushes_and_rows():
    """Seven pushes on the box's +x face: side pushes at P 0.03, 0.3, 0.5, 0.97 and 0.3 (lower,
    so needing more force), one from above and one from below at P 0.4; each row leaves pose 0
    for poses 1 and 2 in the ratio 3 : 1."""
    directions = [SIDE, SIDE, SIDE, SIDE, SIDE, [-0.3, 0.0, -0.954], [-0.6, 0.0, 0.8]]
    heights = [0.1, 0.1, 0.1, 0.1, 0.04, 0.1, 0.1]
    points = np.column_stack([np.full(7, 0.025), np.linspace(-0.03, 0.03, 7), heights])
    actions = _actions(points, np.tile([1.0, 0, 0], (7, 1)), np.array(directions, dtype=float))
    p = np.array([0.03, 0.3, 0.5, 0.97, 0.3, 0.4, 0.4])
    rows = np.column_stack([1.0 - p, 0.75 * p, 0.25 * p])
    return actions, rows


def test_only_unsure_side_pushes_are_mapped_and_keep_where_they_land():
    actions, rows = _pushes_and_rows()
    out, p = map_side_rows(rows, 0, actions, BOX, WEIGHTS)
    taken = side_rows(1.0 - rows[:, 0], actions.directions[:, 2])
    assert taken.tolist() == [False, True, True, False, True, False, False]
    assert np.array_equal(out[~taken], rows[~taken]), "P outside the band, from above or below: the row as it was"
    q = mapped_probability(side_features(1.0 - rows[:, 0], actions.points, actions.directions, BOX), WEIGHTS)
    assert np.allclose(p[taken], q[taken]) and np.allclose(out[taken, 0], 1.0 - q[taken])
    assert np.allclose(out[taken, 1], 3.0 * out[taken, 2]), "the landing keeps its proportions"
    assert np.allclose(out.sum(axis=1), 1.0)
    # The same P, a push lower down needs more force: the map says it topples less.
    assert p[4] < p[1]
    identity, p_identity = map_side_rows(rows, 0, actions, BOX, IDENTITY)
    assert np.allclose(identity, rows) and np.allclose(p_identity, 1.0 - rows[:, 0])
    same, _ = map_side_rows(rows, 0, actions, BOX, ())
    assert np.array_equal(same, rows), "no weights, no map"
    one = [0, 1, 3]  # a single push the map takes is mapped too
    alone, p_alone = map_side_rows(rows[one], 0, _actions(actions.points[one], actions.normals[one], actions.directions[one]), BOX, WEIGHTS)
    assert p_alone[1] == pytest.approx(q[1]) and np.array_equal(alone[[0, 2]], rows[[0, 3]])
    nan_rows = rows.copy()
    nan_rows[1] = np.nan  # a push that is not ok
    out, p = map_side_rows(nan_rows, 0, actions, BOX, WEIGHTS)
    assert np.all(np.isnan(out[1])) and np.isnan(p[1])


def test_the_band_and_the_side_class_are_where_the_map_was_fitted():
    z = np.array([-0.3, -0.30001, 0.29999, 0.3, 0.0, 0.0, 0.0])
    p = np.array([0.5, 0.5, 0.5, 0.5, SIDE_BAND[0], SIDE_BAND[1], np.nan])
    assert side_rows(p, z).tolist() == [True, False, True, False, False, False, False]
    # The whole open interval: every side push that leaves and is not certain; P = 0 never (no landing).
    z, p = np.zeros(5), np.array([0.0, 1e-6, 0.97, 1.0 - 1e-9, 1.0])
    assert side_rows(p, z, (0.0, 1.0)).tolist() == [False, True, True, True, False]
    assert side_rows(p, z, (0.9, 0.98)).tolist() == [False, False, True, False, False]


def test_the_band_is_configured_and_a_wider_band_maps_the_sure_pushes_too():
    actions, rows = _pushes_and_rows()
    wide, p_wide = map_side_rows(rows, 0, actions, BOX, WEIGHTS, (0.0, 1.0))
    narrow, _ = map_side_rows(rows, 0, actions, BOX, WEIGHTS)
    taken = side_rows(1.0 - rows[:, 0], actions.directions[:, 2], (0.0, 1.0))
    assert taken.tolist() == [True, True, True, True, True, False, False]
    q = mapped_probability(side_features(1.0 - rows[:, 0], actions.points, actions.directions, BOX), WEIGHTS)
    assert np.allclose(p_wide[taken], q[taken]) and np.allclose(wide[taken, 1], 3.0 * wide[taken, 2])
    assert np.array_equal(wide[[1, 2, 4]], narrow[[1, 2, 4]]) and not np.allclose(wide[[0, 3]], narrow[[0, 3]])
    assert Config().topple.side_map_band == SIDE_BAND
    assert Config().with_overrides({"topple.side_map_band": "0,1"}).topple.side_map_band == (0.0, 1.0)
    for bad in ("0.5,0.5", "0.9,0.1", "0.1", "0.1,0.5,0.9", "-0.1,0.5", "0.5,1.1"):
        with pytest.raises(ValueError, match="side_map_band"):
            Config().with_overrides({"topple.side_map_band": bad})
    for bad in ((0.5, 1.1), (-0.1, 0.5), (0.5,), (0.4, 0.4)):
        with pytest.raises(ValueError, match="0 <= lo < hi <= 1"):
            check_side_band(bad)
    check_side_band((0.0, 1.0))
    with pytest.raises(ValueError, match="side_map_band"):
        side_rows(np.array([0.0, 0.5]), np.zeros(2), (-0.1, 1.0))  # P = 0 would be taken, with nothing leaving


def test_bad_weights_are_refused_and_only_the_corrected_variant_maps():
    check_side_weights(())
    check_side_weights(WEIGHTS)
    for bad in [(1.0, 2.0), (1.0, np.nan, 0.0)]:
        with pytest.raises(FeatureMapError, match=r"topple.side_map needs 3 finite weights \(bias, logit_p, log_force_ratio\)"):
            check_side_weights(bad)
    with pytest.raises(ValueError, match="side_map"):
        Config().with_overrides({"topple.side_map": "1,2"})
    topple = replace(Config().topple, side_map=WEIGHTS)
    assert topple.applied_side_map == WEIGHTS and replace(topple, variant="robust").applied_side_map == ()
    assert topple.without_recalibration().side_map == ()
    assert Config.from_toml(PRESETS / "thesis.toml").topple.applied_side_map == (), "the thesis's variants apply no map"


def test_a_file_with_a_map_of_its_own_comes_without_the_default_side_map(tmp_path):
    path = tmp_path / "map.toml"
    path.write_text("[topple]\nrecalibration_x = [0.0, 1.0]\nrecalibration_y = [0.1, 0.9]\n")
    assert Config.from_toml(path).topple.side_map == ()
    path.write_text(f"[topple]\nrecalibration_x = [0.0, 1.0]\nrecalibration_y = [0.1, 0.9]\nside_map = {list(WEIGHTS)}\n")
    assert Config.from_toml(path).topple.side_map == WEIGHTS
    path.write_text("[topple]\nn_trials = 50\n")  # no map of its own: the default's
    assert Config.from_toml(path).topple.side_map == Config().topple.side_map
    configured = Config().with_overrides({"topple.side_map": ",".join(map(str, WEIGHTS))})
    assert Config.from_dict(configured.to_dict()) == configured, "a manifest reads back with its side map"


def test_the_engine_maps_the_unsure_side_pushes_and_no_other(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    base = replace(Config().topple, n_trials=40, side_map=(), boosted_map="")  # C.19 maps every row after it

    def table(t):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"))

    plain, mapped = table(base), table(replace(base, side_map=WEIGHTS))
    taken = side_rows(plain.p_topple, actions.directions[:, 2])
    ok = actions.status == STATUS_OK
    assert taken.sum() >= 3 and (ok & ~taken).sum() >= 3, "the test needs pushes of both kinds"
    assert np.array_equal(mapped.next_pose[~taken], plain.next_pose[~taken], equal_nan=True)
    com = transform_points(pose.transform, obj.center_mass[None])[0]
    q = mapped_probability(side_features(plain.p_topple, actions.points, actions.directions, edge_geometry(pose.base_edges, com)),
                           WEIGHTS)
    assert np.allclose(mapped.p_topple[taken], q[taken]) and np.array_equal(mapped.outcomes, plain.outcomes)
    # The engine reads the configured band: a narrower one maps fewer rows, the rest as they were.
    narrow = table(replace(base, side_map=WEIGHTS, side_map_band=NARROW))
    inside = side_rows(plain.p_topple, actions.directions[:, 2], NARROW)
    assert 1 <= inside.sum() < taken.sum()
    assert np.allclose(narrow.p_topple[inside], q[inside])
    assert np.array_equal(narrow.next_pose[~inside], plain.next_pose[~inside], equal_nan=True)


def test_the_scorer_reads_what_the_engine_maps_and_recalibrate_side_fits_it(model_logs, tmp_path):  # noqa: F811
    from pipeline.studies.recalibrate import RecalibrationError, main, metrics, push_folds, side_recalibrate
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    config = Config().with_overrides({"seed": 2, "contacts.n_contacts": CANDIDATES_PER_POSE, "topple.side_map": "1,2,3"})
    scorer = Scorer(log, seed=2, contacts=config.contacts)
    features, p, taken = scorer.side_map_inputs(config.topple)
    _, _, taken_narrow = scorer.side_map_inputs(replace(config.topple, side_map_band=NARROW))  # the configured band is read
    assert 6 <= taken_narrow.sum() < taken.sum() and not np.any(taken_narrow & ~taken)
    before = replace(config.topple, side_map=(), boosted_map="")  # the boosted map (C.19) comes after it
    assert np.allclose(p, scorer.score(before).p_topple, equal_nan=True), \
        "read from the model without the side map, the maps before it applied"
    for group in scorer.groups:
        obj = log.objects[group.object_id].model
        pool = scorer.pose_candidates(group)
        table = evaluate_pose(obj, group.pose, group.drop_probabilities, pool.actions, before,
                              stream(2, obj.name, group.pose.index, "trials"), candidates=pool.candidates)
        com = transform_points(group.pose.transform, obj.center_mass[None])[0]
        expected = side_features(table.p_topple, pool.actions.points, pool.actions.directions, edge_geometry(group.pose.base_edges, com))
        assert np.allclose(features[group.rows], expected[pool.index], equal_nan=True)
        assert np.array_equal(taken[group.rows], side_rows(table.p_topple, pool.actions.directions[:, 2])[pool.index])
    assert 8 <= taken.sum(), "the test needs side pushes the map takes"

    result = side_recalibrate(log, config, folds=3, seed=2)
    observed, repeats, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    assert np.allclose(result["weights"], fit_weights(features[taken], observed[taken], repeats[taken])), "fitted on the taken pushes only"
    # Held out means held out: each fold's pushes predicted from the other folds' alone; the rest keep P.
    _, fold_of = push_folds([scorer.object_ids[i] for i in objects], 3, 2)
    held_out = p.copy()
    for f in range(3):
        train, test = (fold_of != f) & taken, (fold_of == f) & taken
        held_out[test] = mapped_probability(features[test], fit_weights(features[train], observed[train], repeats[train]))
    finite = np.isfinite(p)
    assert result["cross_validated"]["side_map"] == metrics(held_out[finite], observed[finite], repeats[finite], objects[finite])
    assert result["side_pushes"]["pushes"] == int(taken.sum())

    out, record = tmp_path / "side.toml", tmp_path / "side.json"
    common = ["--corpus", "none", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}", "--seed", "2",
              "--set", "seed=2", "--out", str(out), "--json", str(record)]
    assert main([str(path), "--side", *common]) == 0
    written = Config.from_toml(out).topple
    assert np.allclose(written.side_map, result["weights"]) and json.loads(record.read_text())["weights"] == result["weights"]
    default = Config().topple
    assert (written.recalibration_x, written.down_map) == (default.recalibration_x, default.down_map), "the other maps are kept"
    assert written.side_map_band == SIDE_BAND, "the band travels with the weights fitted inside it"
    assert tomllib.loads(out.read_text())["topple"]["side_map_band"] == list(SIDE_BAND), "written, not defaulted"
    assert main([str(path), "--side", *common, "--set", "topple.side_map_band=" + ",".join(map(str, NARROW))]) == 0
    assert Config.from_toml(out).topple.side_map_band == NARROW
    # A fit of another map clears the side map, and its band with it.
    plain = tmp_path / "plain.toml"
    assert main([str(path), *common[:-4], "--out", str(plain), "--json", str(tmp_path / "plain.json"),
                 "--set", "topple.side_map_band=" + ",".join(map(str, NARROW))]) == 0
    assert "side_map_band" not in tomllib.loads(plain.read_text())["topple"]
    assert json.loads(record.read_text())["side_pushes"]["pushes"] == int(taken_narrow.sum())
    assert main([str(path), "--side", "--down", *common]) == 2
    out.unlink()
    assert main([str(path), "--side", "--set", "topple.variant=robust", *common]) == 2 and not out.exists()
    with pytest.raises(RecalibrationError, match="too few"):  # a band nothing is inside
        side_recalibrate(log, replace(config, topple=replace(config.topple, side_map_band=(0.0, 1e-12))), folds=3, seed=2)


def test_the_side_map_and_a_down_map_never_take_the_same_push():
    with pytest.raises(ValueError, match="would both map"):
        Config().with_overrides({"topple.down_map_z": -0.2, "mdp.min_direction_z": 0.0})
    assert Config().with_overrides({"topple.down_map_z": -0.2, "mdp.min_direction_z": 0.0,
                                    "topple.side_map": ""}).topple.applied_down_map


def test_a_file_with_only_a_feature_map_of_its_own_comes_without_the_side_map(tmp_path):
    path = tmp_path / "features.toml"
    path.write_text("[topple]\nrecalibration_x = []\nrecalibration_y = []\nfeature_map = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]\n")
    assert Config.from_toml(path).topple.side_map == ()


def test_the_side_class_compares_directions_in_float32_as_the_served_tables():
    # A direction a hair below -0.3 in float64 is -0.3 in float32: the served tables' push is a side push.
    z = np.array([-0.3 - 1e-9, -0.3 - 1e-6])
    assert side_rows(np.array([0.5, 0.5]), z).tolist() == [True, False]
