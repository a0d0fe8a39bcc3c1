"""The map of P(topple) for pushes that press down (docs/MODEL.md C.15)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pipeline.model.config import PRESETS, Config, ContactConfig
from pipeline.model.edges import edge_geometry
from pipeline.model.feature_map import (
    DOWN_FEATURES,
    FeatureMapError,
    check_down_weights,
    down_features,
    fit_weights,
    landing_rows,
    map_down_rows,
    mapped_probability,
    pressed_down,
)
from pipeline.model.outcomes import Actions
from pipeline.model.recalibration import fit, predict
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.frames import transform_points
from schema.horizon import choosable_pushes
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
BOX = edge_geometry(BOX_EDGES, BOX_COM)
ABOVE = np.array([-np.sqrt(1 - 0.81), 0, -0.9])
SIDE = np.array([-1.0, 0, 0])


def _actions(points, normals, directions):
    n = len(points)
    return Actions(points=np.asarray(points, dtype=float), normals=np.asarray(normals, dtype=float),
                   directions=np.asarray(directions, dtype=float), status=np.full(n, STATUS_OK, dtype=np.int8))


def _rows(p_leave, landing_pose=1, n_poses=3, start=0):
    rows = np.zeros((len(p_leave), n_poses))
    rows[:, start] = 1.0 - np.asarray(p_leave)
    rows[:, landing_pose] = p_leave
    return rows


def _pushes(n):
    """n pushes on the box's +x face, 1.2 cm apart, alternately from above (u_z -0.9) and from the side."""
    points = np.column_stack([np.full(n, 0.025), np.linspace(-0.03, 0.03, n), np.full(n, 0.1)])
    normals = np.tile([1.0, 0, 0], (n, 1))
    return _actions(points, normals, [ABOVE if i % 2 == 0 else SIDE for i in range(n)])


def _map(next_pose, unmapped, actions, weights=WEIGHTS, cut_z=-0.3, pool=None):
    return map_down_rows(next_pose, unmapped, 0, actions, BOX, BOX_COM, weights, cut_z, pool=pool)


def test_features_of_a_standing_box_follow_their_definitions():
    points = np.array([[0.0, 0.0, 0.15], [0.025, 0.01, 0.06], [0.045, 0.0, 0.1]])
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0.6, 0, 0.8]])
    directions = np.array([[0, 0, -1.0], [-0.8, 0, -0.6], [0.0, -0.6, -0.8]])
    f = down_features(np.array([0.2, 0.5, np.nan]), points, normals, directions, BOX, BOX_COM)
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
    beyond = down_features(np.array([0.3]), points[2:], normals[2:], directions[2:], BOX, BOX_COM)
    assert beyond[0, DOWN_FEATURES.index("overhang")] == pytest.approx(0.02 / 0.075)


def test_features_do_not_move_with_the_object_across_the_table_and_only_lengths_scale():
    points = np.array([[0.03, 0.01, 0.12], [0.0, -0.02, 0.15], [0.05, 0.03, 0.05]])
    normals = np.array([[0.6, 0, 0.8], [0, 0, 1.0], [1.0, 0, 0]])
    directions = np.array([[-0.6, 0, -0.8], [0.3, 0, -0.954], [-0.8, 0.0, -0.6]])
    com = BOX_COM + [0.004, -0.007, 0.0]  # off the base's centre, so the offset's sign matters
    p = np.array([0.2, 0.4, 0.6])
    f = down_features(p, points, normals, directions, edge_geometry(BOX_EDGES, com), com)
    shift = np.array([0.31, -0.17, 0.0])  # the same object elsewhere on the table
    moved = down_features(p, points + shift, normals, directions, edge_geometry(BOX_EDGES + shift, com + shift), com + shift)
    assert np.allclose(moved, f)
    column = DOWN_FEATURES.index("offset")
    assert np.allclose(f[:, column], np.linalg.norm(points[:, :2] - com[:2], axis=1) / com[2])
    assert f[0, DOWN_FEATURES.index("stability")] == pytest.approx((0.025 - 0.004) / 0.075), "the nearest edge sets it"
    # Twice the size: every length over the centre of mass's height is the same number.
    doubled = down_features(p, 2 * points, normals, directions, edge_geometry(2 * BOX_EDGES, 2 * com), 2 * com)
    assert np.allclose(doubled, f)


def test_only_pushes_below_the_cut_are_mapped_and_rows_stay_distributions():
    actions = _pushes(6)
    unmapped = _rows([0.1, 0.2, 0.3, 0.4, 0.0, 0.6])
    mapped_before = _rows([0.15, 0.25, 0.35, 0.45, 0.05, 0.65])  # a C.7 map of the counts, say
    out, p = _map(mapped_before, unmapped, actions)
    side = actions.directions[:, 2] >= -0.3
    assert np.array_equal(out[side], mapped_before[side]), "a push the policies may choose keeps its row exactly"
    q = mapped_probability(down_features(1 - unmapped[:, 0], actions.points, actions.normals, actions.directions, BOX, BOX_COM),
                           WEIGHTS)
    assert np.allclose(p[~side], q[~side]), "read from the unmapped P, not from the row C.7 mapped"
    assert np.allclose(out[~side, 1], q[~side]) and np.allclose(out.sum(axis=1), 1.0)
    same, p_same = _map(mapped_before, unmapped, actions, weights=())
    assert np.array_equal(same, mapped_before) and np.allclose(p_same, 1 - mapped_before[:, 0]), "no weights, no map"
    identity, p_identity = _map(unmapped, unmapped, actions, weights=IDENTITY)
    assert np.allclose(p_identity[[0, 2]], [0.1, 0.3]) and np.allclose(identity[[0, 2]], unmapped[[0, 2]])
    everything, _ = _map(mapped_before, unmapped, actions, cut_z=1.0)
    assert np.allclose(everything[side, 1], q[side]), "a cut above every push maps every push"


def test_a_push_that_never_toppled_lands_where_its_neighbours_do_not_where_the_pose_does():
    # Push 0 (from above) never toppled; push 1, 1.2 cm away with the same direction, lands in
    # pose 2; push 2, 7 cm away, lands in pose 1 with more mass than push 1 has.
    points = np.array([[0.025, -0.03, 0.1], [0.025, -0.018, 0.1], [0.025, 0.04, 0.1]])
    actions = _actions(points, np.tile([1.0, 0, 0], (3, 1)), [ABOVE, ABOVE, ABOVE])
    unmapped = np.array([[1.0, 0.0, 0.0], [0.7, 0.0, 0.3], [0.1, 0.9, 0.0]])
    out, p = _map(unmapped, unmapped, actions)
    assert p[0] > 0 and out[0, 2] == pytest.approx(p[0]) and out[0, 1] == 0.0
    alone = _actions(points[[0, 2]], actions.normals[[0, 2]], actions.directions[[0, 2]])
    out_alone, p_alone = _map(unmapped[[0, 2]], unmapped[[0, 2]], alone)
    assert p_alone[0] > 0 and out_alone[0, 1] == pytest.approx(p_alone[0]), "with no neighbour, where the pose's pushes land"


def test_a_pose_nothing_leaves_keeps_its_rows_and_rows_that_are_not_ok_stay_nan():
    actions = _pushes(4)
    unmapped = _rows([0.0, 0.0, 0.0, 0.0])
    unmapped[2] = np.nan
    out, p = _map(unmapped, unmapped, actions)
    assert np.array_equal(out, unmapped, equal_nan=True) and np.allclose(p[[0, 1, 3]], 0.0), "nowhere to land: no topple"


def test_a_probe_lends_no_landing_to_the_pose():
    # Row 0: a candidate from above that never toppled, alone; row 1 a side candidate that never
    # toppled; row 2 a probe (past the pool of 2) far from both, which topples to pose 1.
    points = np.array([[0.025, -0.03, 0.1], [0.025, 0.03, 0.1], [-0.025, 0.0, 0.14]])
    actions = _actions(points, [[1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0]], [ABOVE, SIDE, [1.0, 0, 0]])
    unmapped = _rows([0.0, 0.0, 0.8])
    alone, p_alone = _map(unmapped, unmapped, actions, pool=2)
    assert p_alone[0] == 0.0 and np.array_equal(alone[0], unmapped[0]), "the pose's candidates never topple: nowhere to land"
    _, p_all = _map(unmapped, unmapped, actions)
    assert p_all[0] > 0.0, "counted as a candidate, the probe's topple would give it a landing"


def test_the_cut_is_the_policies_own_in_float32_so_no_push_is_on_both_sides():
    direction_z = np.array([-0.31, np.nextafter(-0.3, -1.0), -0.3, -0.29, 0.0])
    down = pressed_down(direction_z, -0.3)
    assert down.tolist() == [True, False, False, False, False]
    assert np.array_equal(down, ~choosable_pushes(direction_z, -0.3))
    actions = _pushes(2)
    actions.directions[0] = [-np.sqrt(1 - 0.09), 0.0, np.nextafter(-0.3, -1.0)]  # the policies may choose it
    unmapped = _rows([0.2, 0.3])
    out, p = _map(unmapped, unmapped, actions)
    assert np.array_equal(out, unmapped) and np.allclose(p, [0.2, 0.3])


def test_bad_weights_and_a_cut_above_the_policies_are_refused():
    check_down_weights(())
    check_down_weights(WEIGHTS)
    for bad in [(1.0, 2.0), WEIGHTS[:-1] + (np.nan,)]:
        with pytest.raises(FeatureMapError, match="topple.down_map needs 8"):
            check_down_weights(bad)
    with pytest.raises(ValueError, match="down_map"):
        Config().with_overrides({"topple.down_map": "1,2,3"})
    with pytest.raises(ValueError, match="down_map_z"):
        Config().with_overrides({"topple.down_map_z": -2.0})
    # Choosing from every push with the down map on maps chosen pushes: the default does, by the
    # neighbourhood over the boosted map (C.19); the argmax, or no boosted map, is refused.
    assert Config().mdp.min_direction_z == -1.0 and Config().topple.applied_down_map and Config().topple.down_map_z > -1.0
    for unjudged in ({"mdp.choice_radius": 0.0}, {"topple.boosted_map": ""}):
        with pytest.raises(ValueError, match="would map pushes the policies may choose"):
            Config().with_overrides(unjudged)
        assert Config().with_overrides({**unjudged, "mdp.min_direction_z": -0.3}).topple.applied_down_map
    assert Config().with_overrides({"mdp.min_direction_z": -1.0, "topple.down_map": ""}).topple.applied_down_map == ()
    assert Config().with_overrides({"mdp.min_direction_z": 0.0}).topple.applied_down_map == Config().topple.down_map
    with pytest.raises(ValueError, match="would map pushes the policies may choose"):
        Config.from_toml(PRESETS / "thesis.toml").with_overrides({"topple.variant": "corrected"})
    assert Config.from_toml(PRESETS / "thesis.toml").topple.applied_down_map == (), "the thesis's variants apply no map"
    topple = replace(Config().topple, down_map=WEIGHTS)
    assert topple.applied_down_map == WEIGHTS and topple.needs_candidates
    assert replace(topple, variant="robust").applied_down_map == ()
    assert topple.without_recalibration().down_map == () and topple.counted().down_map == ()


def test_a_file_with_a_map_of_its_own_comes_without_the_default_down_map(tmp_path):
    path = tmp_path / "map.toml"
    path.write_text("[topple]\nrecalibration_x = [0.0, 1.0]\nrecalibration_y = [0.1, 0.9]\n")
    assert Config.from_toml(path).topple.down_map == ()
    path.write_text("[topple]\nfeature_map = []\n")  # restating the default's (no feature map) is no map of its own
    assert Config.from_toml(path).topple.down_map == Config().topple.down_map
    path.write_text(f"[topple]\nrecalibration_x = [0.0, 1.0]\nrecalibration_y = [0.1, 0.9]\ndown_map = {list(WEIGHTS)}\n")
    assert Config.from_toml(path).topple.down_map == WEIGHTS
    # --set changes one key of a whole configuration, down map included.
    overridden = Config().with_overrides({"topple.recalibration_x": "0,1", "topple.recalibration_y": "0.1,0.9"})
    assert overridden.topple.down_map == Config().topple.down_map
    assert Config.from_dict(Config().to_dict()) == Config(), "a manifest reads back with its down map"


def test_the_engine_maps_the_down_pushes_from_their_unmapped_rows_and_no_other(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    base = replace(Config().topple, n_trials=40, down_map=(), boosted_map="")  # C.19 maps every row after it

    def table(t):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"))

    plain, mapped, unmapped = table(base), table(replace(base, down_map=WEIGHTS)), table(base.without_recalibration())
    ok = actions.status == STATUS_OK
    down = ok & (actions.directions[:, 2] < base.down_map_z)
    assert down.sum() >= 5 and (ok & ~down).sum() >= 5, "the test needs pushes of both kinds"
    assert np.array_equal(mapped.next_pose[~down], plain.next_pose[~down], equal_nan=True)
    com = transform_points(pose.transform, obj.center_mass[None])[0]
    f = down_features(unmapped.p_topple, actions.points, actions.normals, actions.directions,
                      edge_geometry(pose.base_edges, com), com)
    landing = landing_rows(unmapped.next_pose, pose.index, actions.points, actions.directions)
    q = np.where(landing.sum(axis=1) > 0, mapped_probability(f, WEIGHTS), 0.0)
    assert np.allclose(mapped.p_topple[down], q[down])
    rows = q[:, None] * landing
    rows[:, pose.index] = 1.0 - q
    assert np.allclose(mapped.next_pose[down], rows[down]) and np.array_equal(mapped.outcomes, plain.outcomes)


def test_the_scorer_reads_what_the_engine_maps(model_logs):  # noqa: F811
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    log = read_log([model_logs / "reported.parquet"])
    scorer = Scorer(log, seed=2, contacts=ContactConfig(n_contacts=CANDIDATES_PER_POSE))
    topple = Config().topple
    features, p, lands = scorer.down_map_inputs(topple)
    assert np.allclose(p, scorer.score(topple.without_recalibration()).p_topple), "features come from the model with no map"
    for group in scorer.groups:
        obj = log.objects[group.object_id].model
        pool = scorer.pose_candidates(group)
        table = evaluate_pose(obj, group.pose, group.drop_probabilities, pool.actions, topple.without_recalibration(),
                              stream(2, obj.name, group.pose.index, "trials"), candidates=pool.candidates)
        com = transform_points(group.pose.transform, obj.center_mass[None])[0]  # the pose frame's, not the mesh's
        expected = down_features(table.p_topple, pool.actions.points, pool.actions.normals, pool.actions.directions,
                                 edge_geometry(group.pose.base_edges, com), com)[pool.index]
        assert np.allclose(features[group.rows], expected, equal_nan=True)
        landing = landing_rows(table.next_pose, group.pose.index, pool.actions.points, pool.actions.directions,
                               pool=pool.candidates)
        assert np.array_equal(lands[group.rows], landing[pool.index].sum(axis=1) > 0)


def test_recalibrate_down_fits_the_centred_map_on_all_pushes_and_the_down_map_on_its_own(model_logs, tmp_path):  # noqa: F811
    from pipeline.studies.recalibrate import down_recalibrate, main, metrics, push_folds, recalibrate
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    # The boxes' pushes are from the side (u_z = 0) or from above (u_z = -1): a cut at -0.5 splits them.
    config = Config().with_overrides({"topple.down_map_z": -0.5, "seed": 2, "contacts.n_contacts": CANDIDATES_PER_POSE})
    scorer = Scorer(log, seed=2, contacts=config.contacts)
    features, p, lands = scorer.down_map_inputs(config.topple)
    down = features[:, DOWN_FEATURES.index("direction_z")] < -0.5
    assert 8 <= down.sum() < len(p) - 8, "the test needs pushes on both sides of the cut"
    result = down_recalibrate(log, config, folds=3, seed=2)
    observed, repeats, objects = scorer.empirical_topple, scorer.repeats.astype(float), scorer.object_index
    assert np.allclose(result["weights"], fit_weights(features[down], observed[down], repeats[down])), "fitted below the cut only"
    assert result["other_pushes"]["down_map"] == result["other_pushes"]["centred"], "the others keep the centred map"
    assert result["pushes_without_landing"] == int(np.sum(down & ~lands))
    plain = recalibrate(log, config, folds=3, seed=2, methods=("centred",))
    assert result["cross_validated"]["centred"] == plain["cross_validated"]["methods"]["centred"], "the same folds as plain recalibrate"
    knots = fit("centred", p, observed, repeats)
    assert result["knots"] == {"x": list(knots.x), "y": list(knots.y)}
    # Held out means held out: each fold's pushes predicted from the other folds' alone.
    _, fold_of = push_folds([scorer.object_ids[i] for i in objects], 3, 2)
    held_out = np.empty(len(p))
    for f in range(3):
        train, test = fold_of != f, fold_of == f
        centred = predict(p[test], fit("centred", p[train], observed[train], repeats[train]))
        q = mapped_probability(features[test], fit_weights(features[train & down], observed[train & down], repeats[train & down]))
        held_out[test] = np.where(down[test], np.where(lands[test], q, 0.0), centred)
    assert result["cross_validated"]["down_map"] == metrics(held_out, observed, repeats, objects)

    out, record = tmp_path / "down.toml", tmp_path / "down.json"
    common = ["--corpus", "none", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}", "--seed", "2",
              "--set", "seed=2", "--out", str(out), "--json", str(record)]
    assert main([str(path), "--down", "--set", "topple.down_map_z=-0.5", *common]) == 0
    written = Config.from_toml(out).topple
    assert np.allclose(written.down_map, result["weights"]) and written.down_map_z == -0.5, "the cut travels with the weights"
    assert not written.applied_boosted_map and Config.from_toml(out).mdp.min_direction_z == -0.5, \
        "without the boosted map over it, value iteration chooses no push the down map maps"
    # The file's other sections are the defaults', whatever the base model's: a base that chose from the side says so too.
    assert main([str(path), "--down", "--set", "topple.down_map_z=-0.5", "--set", "mdp.min_direction_z=-0.3", *common]) == 0
    assert Config.from_toml(out).mdp.min_direction_z == -0.5
    assert json.loads(record.read_text())["weights"] == result["weights"]
    # A cut below every push leaves nothing to fit: a clear error, nothing written.
    out.unlink()
    assert main([str(path), "--down", "--set", "topple.down_map_z=-1.0", *common]) == 2 and not out.exists()
    assert main([str(path), "--down", "--features", *common]) == 2


def test_the_engine_keeps_the_probes_out_of_the_down_maps_neighbourhoods(pose_and_candidates, monkeypatch):  # noqa: F811
    """The down map's landings are neighbourhood means (C.15): over the pose's candidates, never over
    other probes evaluated beside them, as the other maps (found by mutation testing: the pool was
    never checked for this map)."""
    import pipeline.model.topple as topple_module

    obj, pose_set, pose, actions = pose_and_candidates
    seen = {}
    real = topple_module.map_down_rows

    def recorded(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(topple_module, "map_down_rows", recorded)
    k = len(actions.status) - 5
    topple = replace(Config().topple, n_trials=20, boosted_map="")
    assert topple.applied_down_map
    evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(3, obj.name, pose.index, "trials"), candidates=k)
    assert seen["pool"] == k
    seen.clear()
    evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(3, obj.name, pose.index, "trials"))
    assert seen["pool"] == len(actions.status), "with no probes every push is a candidate"


def test_a_down_candidate_with_nowhere_to_land_keeps_its_row_beside_a_probe_that_lands():
    # Pushes 0 and 2 press down; candidates 0 and 1 never topple, probe 2 (3 cm away, past the pool) does.
    actions = _pushes(3)
    rows = np.array([[1.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0.5]])
    mapped, p = _map(rows, rows, actions, pool=2)
    assert np.array_equal(mapped[:2], rows[:2]) and np.array_equal(p[:2], [0.0, 0.0]), "no landing known: no topple"
    assert np.allclose(mapped.sum(axis=1), 1.0) and p[2] > 0 and mapped[2, 1] == 0.0
