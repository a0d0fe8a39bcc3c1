"""Marginal landings carried on one fall further (docs/MODEL.md C.18): the landing moves, P(topple) never."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from shapes import box_object, candidate_pushes, pose_with_down, random_object

from pipeline.model.config import PRESETS, Config
from pipeline.model.landing_onward import onward_shares
from pipeline.model.mesh import model_from_mesh
from pipeline.model.poses import settle, stable_poses
from pipeline.model.reference import landed_masses
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from schema.vocabulary import STATUS_OK
from tests.test_momentum import QUADRILATERAL, pivot_edge, planar_roll_on, prism, quad, side_down  # noqa: F401 (fixture)

DROP = np.array([0.3, 0.05, 0.1, 0.4, 0.15])


@pytest.fixture(scope="module")
def marginal_pose():
    """random_object(4), 14 poses, 12 of drop probability <= 0.1, and its pose 0: of the edges that
    leave it, some land (by C.8) in marginal poses, some in the two probable ones, and five roll on."""
    obj = random_object(4)
    pose_set = stable_poses(obj)
    return obj, pose_set, pose_set.poses[0], candidate_pushes(obj, pose_set.poses[0], 80, 4)


def _table(setup, topple, seed=4):
    """``evaluate_pose`` of a (object, pose set, pose, actions) setup on its (seed, object, pose) stream."""
    obj, pose_set, pose, actions = setup
    return evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(seed, obj.name, pose.index, "trials"))


def test_a_box_s_onward_pose_is_the_face_opposite_its_start():
    """A box's cross-section about any base edge is a rectangle: toppled onto the next face, the
    edge ahead of its travel is that face's far edge, and over it lies the face opposite the start.
    The box never rolls on (Housner), so that is one fall beyond every landing."""
    obj = box_object(size=(0.05, 0.08, 0.15))
    pose_set = stable_poses(obj, merge_symmetric=False)
    for pose in pose_set.poses:
        opposite = pose_with_down(pose_set, -pose.down, atol=1e-6)
        np.testing.assert_array_equal(pose.edge_momentum_pose, pose.edge_final_pose)
        np.testing.assert_array_equal(pose.edge_onward_pose, np.full(len(pose.base_edges), opposite))


def test_the_prism_s_onward_pose_is_the_side_its_fall_stops_short_of(quad):  # noqa: F811
    """Where the planar closed form clearly keeps too little energy to roll on over the far end of
    the landing side, the onward pose is the side beyond it; where it rolls on, the onward pose is
    one beyond wherever the chain ends, never the landing side."""
    _, pose_set = quad
    n = len(QUADRILATERAL)
    poses = [pose_with_down(pose_set, side_down(QUADRILATERAL, side), atol=1e-6) for side in range(n)]
    stops_short = 0
    for side in range(n):
        kept, needed = planar_roll_on(QUADRILATERAL, side)
        pose = pose_set.poses[poses[side]]
        edge = pivot_edge(pose, np.array([QUADRILATERAL[(side + 1) % n][0], 0.0, QUADRILATERAL[(side + 1) % n][1]]))
        if kept < needed / 1.5:
            assert pose.edge_momentum_pose[edge] == poses[(side + 1) % n], side
            assert pose.edge_onward_pose[edge] == poses[(side + 2) % n], side
            stops_short += 1
        elif kept > needed * 1.5:
            assert pose.edge_onward_pose[edge] != poses[(side + 1) % n], side
    assert stops_short >= 1


def test_only_marginal_landings_with_somewhere_to_go_are_carried_on():
    landed = np.array([1, 2, 3, 4, 1, 1, 0])
    onward = np.array([3, 0, 4, 2, 1, 0, 1])
    # Edge 0: marginal (0.05) onto 3; 1: marginal at the bound (0.1) onto 0; 2: landing 3 is not
    # marginal; 3: nor is 4; 4: nothing ahead; 5: back into the start pose 0; 6: never left it.
    shares = onward_shares(landed, onward, 0, DROP, 0.4, 0.1)
    np.testing.assert_array_equal(shares, [0.4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    # Starting from 3: edges 1 and 5 may now go on to 0, and edge 0's onward pose is the start.
    shares = onward_shares(landed, onward, 3, DROP, 0.4, 0.1)
    np.testing.assert_array_equal(shares, [0.0, 0.4, 0.0, 0.0, 0.0, 0.4, 0.0])
    np.testing.assert_array_equal(onward_shares(landed, onward, 3, DROP, 0.4, 0.2)[[2, 3]], [0.0, 0.4])
    # A chain that rolled back into the start pose (marginal, with somewhere onward) is no topple.
    assert not onward_shares(np.array([1]), np.array([3]), 1, DROP, 0.4, 0.1).any()
    assert not onward_shares(landed, onward, 3, DROP, 0.0, 0.1).any()


@pytest.mark.parametrize("corrections", [None, "finger_friction,force_limit,momentum,rolling,stability_margin,stuck_finger,tip_path"])
def test_the_engine_carries_marginal_landings_on_trial_by_trial(marginal_pose, corrections):
    """Each counted row is the reference's per-trial masses (``landed_masses``) over the engine's
    own edges; P(topple) and the outcomes are those without the correction.  tau is one pose's
    drop probability exactly, which is marginal (at most tau)."""
    _, pose_set, pose, _ = marginal_pose
    drop = pose_set.probabilities
    below = float(drop[4])  # the pose most of its marginal landings go to
    counted = replace(Config().topple.counted(), n_trials=40)
    if corrections:  # blocked topples roll on (C.6), marginal start poses fall over (C.3)
        counted = replace(counted, corrections=corrections)
    onward = replace(counted, landing_onward=0.4, landing_onward_below=below)
    plain, carried = _table(marginal_pose, counted), _table(marginal_pose, onward)
    np.testing.assert_array_equal(plain.outcomes, carried.outcomes)
    np.testing.assert_array_equal(plain.p_topple, carried.p_topple)
    kinds = {"carried": 0, "kept": 0, "rolled": 0, "at tau": 0}
    for action in np.flatnonzero(~np.isnan(plain.next_pose[:, 0])):
        expected = np.zeros(len(drop))
        for edge in carried.outcomes[action]:
            masses = landed_masses(pose, int(edge), onward.applied_corrections, drop, 0.4, below)
            for landed, mass in masses.items():
                expected[landed] += mass / onward.trials
            if edge >= 0 and not pose.edge_blocked[edge]:
                landed = int(pose.edge_momentum_pose[edge])
                kinds["carried" if len(masses) == 2 else "kept"] += landed != pose.index
                kinds["rolled"] += landed != pose.edge_final_pose[edge]
                kinds["at tau"] += len(masses) == 2 and drop[landed] == below
        np.testing.assert_allclose(carried.next_pose[action], expected, atol=1e-12)
    assert min(kinds.values()) >= 3, f"the test needs trials of every kind: {kinds}"


def test_the_table_s_edge_landings_count_its_rows_from_its_outcomes(marginal_pose):
    """The table's per-edge landings (stored in the HDF5 file beside the outcomes) turn a pose's
    trials into its counted rows: a trial over edge k counts 1 - share in the landing, share onward.
    The thesis's variants land on ``edge_final_pose`` and carry nothing."""
    _, pose_set, pose, actions = marginal_pose
    below = float(pose_set.probabilities[4])
    counted = replace(Config().topple.counted(), n_trials=40, landing_onward=0.4, landing_onward_below=below)
    thesis = replace(Config.from_toml(PRESETS / "thesis.toml").topple, n_trials=40)
    for topple in (counted, thesis):
        table = _table(marginal_pose, topple)
        ok = np.flatnonzero(actions.status == STATUS_OK)
        recounted = np.zeros((len(ok), len(pose_set.poses)))
        for row, action in enumerate(ok):
            for edge in table.outcomes[action]:
                if edge < 0:
                    recounted[row, pose.index] += 1
                    continue
                recounted[row, table.edge_landed_pose[edge]] += 1 - table.edge_onward_share[edge]
                recounted[row, table.edge_onward_pose[edge]] += table.edge_onward_share[edge]
        np.testing.assert_allclose(table.next_pose[ok], recounted / topple.n_trials, atol=1e-12)
        stays = table.edge_onward_share == 0  # nothing goes on: the onward pose is the landing, not C.18's pose
        np.testing.assert_array_equal(table.edge_onward_pose[stays], table.edge_landed_pose[stays])
        if topple is thesis:
            np.testing.assert_array_equal(table.edge_landed_pose, pose.edge_final_pose)
            assert not table.edge_onward_share.any()
        else:
            # The case holds both kinds: C.8's landings that are not the thesis's, and shares carried on.
            assert (table.edge_landed_pose != pose.edge_final_pose).any() and table.edge_onward_share.any()
            assert set(np.unique(table.edge_onward_share)) <= {0.0, 0.4}


def test_the_maps_keep_the_carried_landing_and_the_thesis_ignores_it(marginal_pose):
    """The default's maps move P(topple) and keep the landing in proportion: rows are linear in
    the share, and P(topple) is the default's.  The thesis's variants apply nothing."""
    base = replace(Config().topple, n_trials=40)
    none, half, whole = (_table(marginal_pose, replace(base, landing_onward=a, landing_onward_below=0.2)) for a in (0.0, 0.5, 1.0))
    np.testing.assert_array_equal(none.p_topple, half.p_topple)
    np.testing.assert_allclose(half.next_pose, (none.next_pose + whole.next_pose) / 2, atol=1e-12)
    assert not np.allclose(none.next_pose, whole.next_pose, equal_nan=True)
    thesis = replace(Config.from_toml(PRESETS / "thesis.toml").topple, n_trials=40, landing_onward=0.5)
    assert thesis.applied_landing_onward == 0.0
    np.testing.assert_array_equal(_table(marginal_pose, thesis).next_pose,
                                  _table(marginal_pose, replace(thesis, landing_onward=0.0)).next_pose)


def test_the_setting_is_checked_and_kept_out_of_what_maps_are_fitted_on():
    configured = Config().with_overrides({"topple.landing_onward": 0.3, "topple.landing_onward_below": 0.2})
    assert configured.topple.applied_landing_onward == 0.3
    assert configured.topple.without_recalibration().landing_onward == 0.0
    assert Config.from_dict(configured.to_dict()).topple == configured.topple
    for key, value in (("topple.landing_onward", 1.5), ("topple.landing_onward_below", -0.1)):
        with pytest.raises(ValueError, match=key.split(".")[1]):
            Config().with_overrides({key: value})
    # It carries on C.8's landings: without momentum there are none to carry.
    assert not Config().with_overrides({"topple.corrections": "finger_friction,force_limit"}).topple.applied_landing_onward


def test_a_build_that_carries_nothing_on_keeps_the_shard_identity_it_had_before_the_setting():
    """Off (0, no momentum, or a thesis variant), the correction changes no shard: a dataset built
    before the setting existed keeps its shards.  On (the default), both settings are its identity."""
    from pipeline.build.corpus import ObjectSpec
    from pipeline.build.shards import fingerprint, shard_inputs

    spec = ObjectSpec("box", "/nowhere/box.stl", 1.0, 0.2, "list:x", "0" * 64)
    off = shard_inputs(spec, Config().with_overrides({"topple.landing_onward": 0.0}))
    assert not {"landing_onward", "landing_onward_below"} & set(off["config"]["topple"])
    assert shard_inputs(spec, Config().with_overrides({"topple.landing_onward": 0.0, "topple.landing_onward_below": 0.3})) == off
    default = shard_inputs(spec, Config())
    assert default["config"]["topple"]["landing_onward"] == 0.4 and fingerprint(default) != fingerprint(off)
    assert fingerprint(shard_inputs(spec, Config().with_overrides({"topple.landing_onward_below": 0.3}))) != fingerprint(default)
    assert "landing_spread" not in default["config"]["topple"], "the spread, still off, stays out"
    both = shard_inputs(spec, Config().with_overrides({"topple.landing_spread": 0.25}))
    assert {"landing_onward", "landing_spread", "landing_spread_poses"} <= set(both["config"]["topple"])
    thesis = Config.from_toml(PRESETS / "thesis.toml")
    assert "landing_onward" not in shard_inputs(spec, thesis)["config"]["topple"]


def test_a_chain_back_into_the_start_pose_leaves_p_topple_alone():
    """random_object(44), pose 6: its edge 4's C.8 chain rolls back into the start pose, a marginal
    one with an onward pose elsewhere.  Such trials stay, so nothing of theirs is carried."""
    obj = random_object(44)
    pose_set = stable_poses(obj)
    pose = pose_set.poses[6]
    back = np.flatnonzero(~pose.edge_blocked & (pose.edge_momentum_pose == pose.index) & (pose.edge_final_pose != pose.index))
    assert len(back) and (pose.edge_onward_pose[back] != pose.index).any() and pose_set.probabilities[6] <= 0.1
    setup = obj, pose_set, pose, candidate_pushes(obj, pose, 200, 44)  # such topples are rare: 3 trials of these pushes
    tables = [_table(setup, replace(Config().topple, n_trials=40, landing_onward=a), seed=44) for a in (0.0, 0.4)]
    assert np.isin(tables[0].outcomes, back).any(), "the test needs trials over those edges"
    np.testing.assert_array_equal(tables[0].p_topple, tables[1].p_topple)
    np.testing.assert_array_equal(tables[0].next_pose[:, pose.index], tables[1].next_pose[:, pose.index])


def test_merged_symmetric_poses_carry_on_to_the_representative_of_the_unmerged_onward_pose():
    """An extruded trapezoid is mirror-symmetric: its turned copies merge.  Each merged pose's onward
    table is, edge by edge, its unmerged twin's, read as the merged pose that orientation rests in."""
    obj = model_from_mesh(prism(np.array([[0.0, 0.0], [0.09, 0.0], [0.06, 0.04], [0.03, 0.04]]), depth=0.05),
                          mass=0.2, name="trapezoid")
    merged, unmerged = stable_poses(obj), stable_poses(obj, merge_symmetric=False)
    assert len(merged.poses) < len(unmerged.poses)
    moved = 0
    for pose in merged.poses:
        twin = next(u for u in unmerged.poses if np.allclose(u.transform, pose.transform))
        expected = [settle(merged, obj, unmerged.poses[q].transform[:3, :3]) for q in twin.edge_onward_pose]
        np.testing.assert_array_equal(pose.edge_onward_pose, expected)
        moved += int((pose.edge_onward_pose != pose.edge_momentum_pose).sum())
    assert moved >= 1
