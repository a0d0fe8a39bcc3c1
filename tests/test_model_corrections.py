"""The corrected variant (docs/MODEL.md "Corrections beyond the thesis") against closed forms.

The standing 0.05 x 0.08 x 0.15 m box, pushed horizontally on a side face, topples over the
far bottom edge from the height (C.2.3)

    h* = d / mu_T + k mu_f (w - d)

(d: the centre of mass's horizontal distance to that edge, w: the pushed face's), with a
finger force |f| = F_n sqrt(1 + (k mu_f)^2), F_n = m g d / (h - k mu_f w).
"""

import warnings
from dataclasses import fields, replace

import numpy as np
import pytest
from shapes import THESIS, noise_free, overhanging_frustum, random_object, standing_box, stroke_to_apex

from pipeline.model.config import CORRECTIONS, Config
from pipeline.model.contacts import explicit_actions
from pipeline.model.edges import EdgeGeometry, edge_geometry
from pipeline.model.rng import stream
from pipeline.model.topple import (
    Trials,
    _least_passing,
    evaluate_pose,
    finger_travel,
    holds_along_tip,
    landed_poses,
    sliding_contact,
    trial_outcomes,
)
from schema.frames import axis_angle_matrices, transform_points
from schema.vocabulary import OUTCOME_NO_EDGE

MU_TABLE = THESIS.topple.mu_table_mean
MU_FINGER = THESIS.topple.mu_finger_mean
"""The thesis's friction means (0.43, 0.98), ``noise_free``'s: the analytic cases below are worked out for them."""
STEP = 1e-3
"""m, pushes are placed this far below and above the closed-form threshold."""


@pytest.fixture(scope="module")
def box():
    return standing_box()


def _push(box, points, direction, topple):
    obj, pose_set, index = box
    pose = pose_set.poses[index]
    actions = explicit_actions(obj, pose.transform, np.asarray(points, float), np.tile(direction, (len(points), 1)))
    return evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(0, "box", index, "trials"))


def _box_far_edge(box):
    """The standing box's base edges and the one at y = +4 cm, across the 8 cm side from a push
    on the -y face (edges of the pose frame)."""
    obj, pose_set, index = box
    pose = pose_set.poses[index]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edges = edge_geometry(pose.base_edges, center_mass)
    far = next(e for e in range(len(edges.start)) if abs(edges.direction[e, 0]) > 0.9 and edges.start[e, 1] > 0)  # y = +4 cm
    return edges, far


@pytest.mark.parametrize("mu_finger", [0.0, 0.98])
@pytest.mark.parametrize("scale", [1.0, 0.25])
@pytest.mark.parametrize("axis, width", [(0, 0.05), (1, 0.08)])  # push across the 5 cm side, then the 8 cm side
def test_standing_box_threshold_and_force_match_the_closed_form(box, mu_finger, scale, axis, width):
    obj, pose_set, index = box
    topple = noise_free(corrections="finger_friction", mu_finger_mean=mu_finger, finger_friction_scale=scale)
    mu = scale * mu_finger
    d = width / 2
    threshold = d / MU_TABLE + mu * (width - d)
    heights = np.array([threshold - STEP, threshold + STEP, threshold + 10 * STEP])
    points = np.zeros((3, 3))
    points[:, axis] = -d  # on the face at -d along the push axis; the far edge is at +d
    points[:, 2] = heights
    direction = np.eye(3)[axis]
    table = _push(box, points, direction, topple)
    assert table.p_topple.tolist() == [0.0, 1.0, 1.0]
    weight = obj.mass * topple.gravity
    expected = weight * d / (heights[1:] - mu * width) * np.hypot(1.0, mu)
    np.testing.assert_allclose(table.mean_force[1:], expected, rtol=1e-9)


@pytest.mark.parametrize("mu_finger", [0.0, 0.98])
def test_an_off_centre_push_tips_the_box_at_the_centred_threshold_with_edge_spin(box, mu_finger):
    """Pushed y = 3 cm off the face's centre line, the moment about the vertical |tau_z| = y N
    enters (C.2.5): N c <= mu_T (m g + mu N), c = sqrt(1 + (y / h_e)^2) with h_e the far edge's
    half-length, so h* = d c / mu_T + mu (w - d).  With ``edge_spin`` (C.9) that moment turns
    the box without stopping the topple: the centred threshold (C.2.3) holds at any offset."""
    d, w, y, half_span = 0.025, 0.05, 0.03, 0.04
    c = np.hypot(1.0, y / half_span)
    for corrections, threshold in (("finger_friction", d * c / MU_TABLE + mu_finger * (w - d)),
                                   ("finger_friction,edge_spin", d / MU_TABLE + mu_finger * (w - d))):
        points = [[-d, y, threshold - STEP], [-d, y, threshold + STEP]]
        table = _push(box, points, [1.0, 0.0, 0.0], noise_free(corrections=corrections, mu_finger_mean=mu_finger))
        assert table.p_topple.tolist() == [0.0, 1.0], corrections


@pytest.mark.parametrize("height", [0.135, 0.145])
def test_a_topple_needs_the_stroke_to_reach_the_apex(box, height):
    """Across its 8 cm side the box topples from 13.2 cm (C.2.3 at mu_f 0.98) but needs 6.1-6.7 cm
    of finger travel to reach the apex: with ``stroke`` (C.10) a shorter stroke leaves it standing."""
    travel = stroke_to_apex(height)
    point, direction = [[0.0, -0.04, height]], [0.0, 1.0, 0.0]
    for stroke, toppled in ((travel - STEP, 0.0), (travel + STEP, 1.0)):
        table = _push(box, point, direction, noise_free(corrections="finger_friction,stroke", stroke=stroke))
        assert table.p_topple.tolist() == [toppled], stroke
    endless = _push(box, point, direction, noise_free(corrections="finger_friction", stroke=travel - STEP))
    assert endless.p_topple.tolist() == [1.0]  # the stroke is only read by the correction


def test_finger_travel_is_the_closed_form_and_infinite_once_the_face_turns_away(box):
    edges, far = _box_far_edge(box)
    heights = np.array([0.05, 0.1, 0.135])
    contact = np.column_stack([np.zeros(3), np.full(3, -0.04), heights])
    normal = np.tile([0.0, -1.0, 0.0], (3, 1))
    trials = Trials(contact, normal, np.tile([0.0, 1.0, 0.0], (3, 1)), np.ones(3), np.ones(3), np.ones(3, bool), np.zeros(3))
    np.testing.assert_allclose(finger_travel(trials, edges, np.full(3, far)), stroke_to_apex(heights), rtol=1e-12)
    # Pushed steeply upward, the face (its normal turning up by 28 degrees on the way to the apex)
    # comes to face along the push before the apex: the finger cannot carry it there.
    steep = Trials(contact, normal, np.tile([0.0, 0.3, 0.95], (3, 1)) / np.hypot(0.3, 0.95), np.ones(3), np.ones(3),
                   np.ones(3, bool), np.zeros(3))
    assert np.isinf(finger_travel(steep, edges, np.full(3, far))).all()


def test_stroke_must_equal_the_executed_push_depth():
    with pytest.raises(ValueError, match="push_depth"):
        Config().with_overrides({"topple.stroke": 0.06})
    with pytest.raises(ValueError, match="push_depth"):
        Config().with_overrides({"topple.stroke": 0.06, "contacts.push_depth": 0.05})
    assert Config().with_overrides({"topple.stroke": 0.06, "contacts.push_depth": 0.06}).topple.stroke == 0.06
    # The push depth alone carries the stroke with it, from --set and from a file or an old manifest.
    assert Config().with_overrides({"contacts.push_depth": 0.05}).topple.stroke == 0.05
    assert Config.from_dict({"contacts": {"push_depth": 0.03}, "topple": {"n_trials": 10}}).topple.stroke == 0.03
    assert Config.from_dict({"contacts": {"push_depth": 0.03}}).topple.stroke == 0.03


@pytest.fixture(scope="module")
def frustum():
    return overhanging_frustum()


FRUSTUM_BASE, FRUSTUM_HEIGHT = 0.02, 0.06
"""m, the frustum's base half-width (its centre of mass is that far inside each base edge) and height."""


@pytest.mark.parametrize("x", [0.025, 0.03, 0.035])
def test_a_push_down_onto_an_overhang_tips_it_with_the_stuck_finger(frustum, x):
    """C.11 on the upside-down frustum: pushed 30 degrees below horizontal onto its top face
    x beyond the +x base edge, the finger-friction model (C.2) says it cannot tip (the face
    would slide under the finger, whose friction then holds it back); with ``stuck_finger`` it
    tips over that edge with the force along u whose moment matches gravity's,
    F = m g a / (h u_x + (x - a) |u_z|).  The push player topples it (test_pushsim)."""
    obj, pose_set, index = frustum
    direction = np.array([0.87, 0.0, -0.5]) / np.hypot(0.87, 0.5)
    point = [[x, 0.0, FRUSTUM_HEIGHT]]
    sliding = _push(frustum, point, direction, noise_free(corrections="finger_friction"))
    stuck = _push(frustum, point, direction, noise_free(corrections="finger_friction,stuck_finger", stuck_finger_share=1.0))
    assert sliding.p_topple.tolist() == [0.0] and stuck.p_topple.tolist() == [1.0]
    lever = FRUSTUM_HEIGHT * direction[0] + (x - FRUSTUM_BASE) * -direction[2]
    assert stuck.mean_force[0] == pytest.approx(obj.mass * 9.81 * FRUSTUM_BASE / lever, rel=1e-9)
    landed = pose_set.poses[index].edge_final_pose[stuck.outcomes[0, 0]]
    # Onto a side face (the four are one pose, merged by symmetry), tilted atan(2 / 6) from it.
    assert landed != index and pose_set.poses[landed].down[2] == pytest.approx(-np.sin(np.arctan2(0.02, 0.06)), abs=1e-3)


def test_the_stuck_finger_pushes_no_harder_than_the_finger_can(frustum):
    """C.11 with the force limit (C.1): the overhang of the test above tips with F = m g a / lever exactly
    when the limit admits F, whichever tile or block of the engine the trial falls in."""
    obj, _, _ = frustum
    direction = np.array([0.87, 0.0, -0.5]) / np.hypot(0.87, 0.5)
    x = 0.03
    force = obj.mass * 9.81 * FRUSTUM_BASE / (FRUSTUM_HEIGHT * direction[0] + (x - FRUSTUM_BASE) * -direction[2])
    for limit, toppled in ((force * (1 + 1e-9), 1.0), (force * (1 - 1e-9), 0.0)):
        topple = noise_free(corrections="finger_friction,stuck_finger,force_limit", stuck_finger_share=1.0,
                            max_finger_force=limit)
        assert _push(frustum, [[x, 0.0, FRUSTUM_HEIGHT]], direction, topple).p_topple.tolist() == [toppled], limit


@pytest.mark.parametrize("direction", [[0.0, 0.0, -1.0], [0.26, 0.0, -0.97], [-0.5, 0.0, -0.87], [0.87, 0.0, 0.5]])
def test_the_stuck_finger_leaves_steep_inward_and_upward_pushes_alone(frustum, direction):
    """Too steep to drag the base (|u_xy| <= mu_T |u_z|: the player leaves the frustum standing
    under both), pointing inward (no outward moment) or upward, the same overhang is not
    tipped by ``stuck_finger``."""
    direction = np.array(direction) / np.linalg.norm(direction)
    table = _push(frustum, [[0.035, 0.0, FRUSTUM_HEIGHT]], direction, noise_free(corrections="finger_friction,stuck_finger", stuck_finger_share=1.0))
    assert table.p_topple.tolist() == [0.0]


def test_the_stuck_finger_never_tips_a_box_pushed_from_above(box):
    """A box's top face lies inside its base: no base edge is overhung, nothing changes."""
    points = [[0.015, 0.0, 0.15], [0.02, 0.03, 0.15], [-0.02, -0.03, 0.15]]
    for direction in ([0.45, 0.0, -1.0], [0.0, 0.6, -0.8], [-0.8, 0.0, -0.6]):
        direction = np.array(direction) / np.linalg.norm(direction)
        with_stuck = _push(box, points, direction, noise_free(corrections="finger_friction,stuck_finger", stuck_finger_share=1.0))
        without = _push(box, points, direction, noise_free(corrections="finger_friction"))
        assert with_stuck.p_topple.tolist() == without.p_topple.tolist()


def test_the_stuck_finger_share_is_the_fraction_of_qualifying_trials_that_topple(frustum):
    """Noise-free (every spread 0; the variant still draws per trial), a share q of 400
    qualifying trials topples: 0.3 +- 3.5 standard deviations of the binomial."""
    direction = np.array([0.87, 0.0, -0.5]) / np.hypot(0.87, 0.5)
    point = [[0.03, 0.0, FRUSTUM_HEIGHT]]
    for share, low, high in ((0.0, 0.0, 0.0), (0.3, 0.23, 0.37), (1.0, 1.0, 1.0)):
        topple = noise_free(corrections="finger_friction,stuck_finger", stuck_finger_share=share, n_trials=400)
        assert low <= _push(frustum, point, direction, topple).p_topple[0] <= high, share


def test_tip_back_re_aims_the_stuck_fingers_topple_at_the_lines_edge(frustum):
    """C.22 after C.11: pushed 30 degrees below horizontal along +x onto the top face beyond the frustum's +x+y
    corner (5 mm past the +x base edge, 15 mm past the +y one), the stuck finger tips it over +x, whose lever
    h u_x + (x - a) |u_z| is the longer; the line from the centre of mass's foot through the contact meets y = a
    first (at 4/7 of the way, x = a at 4/5), so a hard press tips it over +y instead, with the stuck finger's force."""
    obj, pose_set, index = frustum
    pose = pose_set.poses[index]
    edges = edge_geometry(pose.base_edges, transform_points(pose.transform, obj.center_mass[None])[0])
    side = lambda outward: int(np.argmax(edges.outward @ np.array(outward)))
    direction = np.array([0.87, 0.0, -0.5]) / np.hypot(0.87, 0.5)
    point = [[0.025, 0.035, FRUSTUM_HEIGHT]]
    stuck = "finger_friction,stuck_finger,tip_back"
    hard = _push(frustum, point, direction, noise_free(corrections=stuck, stuck_finger_share=1.0, tip_back_force=0.0))
    light = _push(frustum, point, direction, noise_free(corrections=stuck, stuck_finger_share=1.0, tip_back_force=1e9))
    assert light.outcomes[0, 0] == side([1.0, 0.0, 0.0]) and hard.outcomes[0, 0] == side([0.0, 1.0, 0.0])
    lever = FRUSTUM_HEIGHT * direction[0] + (0.025 - FRUSTUM_BASE) * -direction[2]
    assert hard.mean_force[0] == light.mean_force[0] == pytest.approx(obj.mass * 9.81 * FRUSTUM_BASE / lever, rel=1e-9)


def test_thesis_model_ignores_finger_friction_in_the_moment_balance(box):
    """The thesis's threshold is d / mu_T whatever mu_f (the ``rotations`` variant, noise-free)."""
    d = 0.025
    heights = np.array([d / MU_TABLE - STEP, d / MU_TABLE + STEP])
    points = np.column_stack([np.full(2, -d), np.zeros(2), heights])
    table = _push(box, points, [1.0, 0.0, 0.0], noise_free("rotations", mu_finger_mean=0.98))
    assert table.p_topple.tolist() == [0.0, 1.0]


def test_push_from_above_cannot_tip_what_would_have_to_rise_into_the_finger(box):
    """A push down-and-forward onto the top face, inside the base: to tip over the far edge
    the top face would rise into the finger, so the corrected model says it stays; the
    thesis's model, whose force simply points along the push, tips it."""
    points = [[0.015, 0.0, 0.15], [0.02, 0.01, 0.15]]
    direction = np.array([0.45, 0.0, -1.0]) / np.hypot(0.45, 1.0)  # inside the 44 degree cone of mu_f 0.98
    thesis = _push(box, points, direction, noise_free("rotations"))
    corrected = _push(box, points, direction, noise_free(corrections="finger_friction"))
    assert thesis.p_topple.tolist() == [1.0, 1.0]
    assert corrected.p_topple.tolist() == [0.0, 0.0]


def test_force_limit_stops_pushes_that_need_more(box):
    d = 0.025
    points = np.array([[-d, 0.0, 0.06], [-d, 0.0, 0.12]])  # the lower push needs more force
    free = _push(box, points, [1.0, 0.0, 0.0], noise_free(corrections="none"))
    assert free.p_topple.tolist() == [1.0, 1.0] and free.mean_force[0] > free.mean_force[1]
    limit = 0.5 * (free.mean_force[0] + free.mean_force[1])
    capped = _push(box, points, [1.0, 0.0, 0.0], noise_free(corrections="force_limit", max_finger_force=limit))
    assert capped.p_topple.tolist() == [0.0, 1.0]
    assert capped.mean_force[1] == free.mean_force[1]


def test_limited_forces_are_positive_and_below_the_limit_on_a_random_object():
    obj = random_object(4)
    from pipeline.model.contacts import object_contacts
    from pipeline.model.poses import stable_poses

    pose_set = stable_poses(obj)
    pose = pose_set.poses[0]
    points, _ = object_contacts(obj, replace(Config().contacts, n_contacts=80), seed=3)
    from schema.frames import transform_points

    actions = explicit_actions(obj, pose.transform, transform_points(pose.transform, points), None)
    topple = replace(Config().topple, variant="corrected", n_trials=20, max_finger_force=1.5, recalibration_x=(), recalibration_y=(), down_map=(), boosted_map="")
    table = evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(0, obj.name, 0, "trials"))
    forces = table.mean_force[np.isfinite(table.mean_force)]
    assert len(forces) > 0 and np.all(forces > 0) and np.all(forces <= 1.5)


def test_thesis_variants_apply_no_correction_and_unknown_names_are_refused():
    for variant in ("baseline", "rotations", "robustness", "robust"):
        assert replace(Config().topple, variant=variant, corrections="all").applied_corrections == frozenset()
    assert replace(Config().topple, variant="corrected", corrections="all").applied_corrections == frozenset(CORRECTIONS)
    assert replace(Config().topple, variant="corrected").applied_corrections == {"finger_friction", "force_limit", "momentum", "stuck_finger", "tip_path",
                                                                               "tip_back"}
    assert replace(Config().topple, variant="corrected", corrections="none").applied_corrections == frozenset()
    one = Config().with_overrides({"topple.variant": "corrected", "topple.corrections": "force_limit"})
    assert one.topple.applied_corrections == {"force_limit"}
    with pytest.raises(ValueError, match="unknown correction.*slippery"):
        Config().with_overrides({"topple.corrections": "force_limit,slippery"})
    with pytest.raises(ValueError, match="tip_path checks finger_friction's balance.*add finger_friction"):
        Config().with_overrides({"topple.corrections": "force_limit,tip_path"})


def test_a_marginal_pose_falls_over_its_nearest_edge_whatever_the_push():
    """Centre of mass 0.5 mm inside the standing box's +x edge: with ``stability_margin`` every
    push (and the weakest) lands where that edge leads, with no force; without, the pushes differ."""
    from shapes import box_object, pose_with_down

    from pipeline.model.poses import stability_margin, stable_poses

    box = box_object((0.05, 0.08, 0.15))
    obj = replace(box, center_mass=box.center_mass + np.array([0.0245, 0.0, 0.0]))
    pose_set = stable_poses(obj, merge_symmetric=False)  # the pose addressed by its own down vector
    pose = pose_set.poses[pose_with_down(pose_set, [0, 0, -1])]
    margin, edge = stability_margin(pose, obj.center_mass)
    assert margin == pytest.approx(5e-4, abs=1e-9)
    outward = np.cross(pose.base_edges[edge, 1] - pose.base_edges[edge, 0], [0, 0, 1])
    np.testing.assert_allclose(outward / np.linalg.norm(outward), pose.transform[:3, :3] @ [1, 0, 0], atol=1e-9)

    # Pose frame (the centre of mass above the origin): the -x face low and high, the top's centre.
    points = np.array([[-0.0495, 0.0, 0.02], [-0.0495, 0.0, 0.14], [-0.0245, 0.0, 0.15]])
    actions = explicit_actions(obj, pose.transform, points, None)
    falls = replace(Config().topple, variant="corrected", corrections="stability_margin,finger_friction", n_trials=5,
                    recalibration_x=(), recalibration_y=(), down_map=(), boosted_map="")
    table = evaluate_pose(obj, pose, pose_set.probabilities, actions, falls, stream(0, "m", pose.index, "trials"))
    landing = pose.edge_final_pose[edge]
    assert landing != pose.index
    np.testing.assert_array_equal(table.next_pose[:, landing], 1.0)
    np.testing.assert_array_equal(table.mean_force, 0.0)
    stands = replace(falls, min_stability_margin=4e-4)  # 0.5 mm is not marginal at 0.4 mm
    table = evaluate_pose(obj, pose, pose_set.probabilities, actions, stands, stream(0, "m", pose.index, "trials"))
    assert table.p_topple[2] == 0.0  # pushed down onto the top, inside the base: it stays



@pytest.fixture(scope="module")
def elliptic_prism():
    """A 12-sided cylinder stretched 3:1 across its axis, lying on a facet next to its lowest
    vertex, and that pose's blocked edge: the neighbouring facet slopes by ~11 degrees, far less
    than the ~40 degrees that would bring the centre of mass above the edge (MODEL.md C.6)."""
    import trimesh

    from pipeline.model.mesh import model_from_mesh
    from pipeline.model.poses import stable_poses

    mesh = trimesh.creation.cylinder(radius=0.02, height=0.12, sections=12)
    mesh.apply_scale([3.0, 1.0, 1.0])
    obj = model_from_mesh(mesh, mass=0.2, name="ellipse")
    pose_set = stable_poses(obj, merge_symmetric=False)  # the far side is its own pose, not merged with the near one
    # The lying pose on the low facet on the +x side of the lowest vertex (down ~ (0.09, -1, 0)).
    index = next(p.index for p in pose_set.poses if p.down[0] > 0.05 and p.down[1] < -0.9)
    return obj, pose_set, index


def test_a_blocked_topple_rolls_on_to_the_far_side_with_rolling(elliptic_prism):
    """By the prism's mirror symmetry about its major axis, rolling over the +x end ends on the
    facet mirroring the start (down (x, -y) -> (x, y)); without the correction, and in the
    thesis's variants, the same push returns to the start pose."""
    obj, pose_set, index = elliptic_prism
    pose = pose_set.poses[index]
    blocked = np.flatnonzero(pose.edge_blocked)
    assert len(blocked) == 1
    edge = int(blocked[0])
    assert pose.edge_final_pose[edge] == index
    rolled = pose.edge_rolled_pose[edge]
    np.testing.assert_allclose(pose_set.poses[rolled].down, pose.down * [1, -1, 1], atol=1e-6)
    unblocked = ~pose.edge_blocked
    np.testing.assert_array_equal(pose.edge_rolled_pose[unblocked], pose.edge_final_pose[unblocked])

    # Push along the blocked edge's outward direction, low on the far side (the ellipse's -x end).
    y0, y1 = pose.base_edges[edge]
    outward = np.cross(y1 - y0, [0.0, 0.0, 1.0])
    outward /= np.linalg.norm(outward)
    center = pose.transform[:3, :3] @ obj.center_mass + pose.transform[:3, 3]
    point = center * [1.0, 1.0, 0.0] - 0.07 * outward + [0.0, 0.0, 0.002]  # snapped onto the mesh
    # 21 mm off: further than a caller's push may be (SNAP_TOLERANCE), so this one asks to be snapped.
    actions = explicit_actions(obj, pose.transform, point[None], outward[None], tolerance=np.inf)
    for corrections, lands in [("finger_friction,force_limit,rolling", rolled), ("finger_friction,force_limit", index)]:
        # k mu_f = 0.245: with the whole Coulomb friction (0.98) this low push jams instead of tipping.
        topple = noise_free(corrections=corrections, finger_friction_scale=0.25)
        table = evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(0, "e", index, "trials"))
        assert table.outcomes[0, 0] == edge, corrections
        assert table.next_pose[0, lands] == 1.0, corrections
    # The thesis's variants ignore every correction: their topples over an edge land as in 4.2.4.
    for variant in ("baseline", "rotations", "robustness", "robust"):
        applied = noise_free(variant, corrections="all").applied_corrections
        np.testing.assert_array_equal(landed_poses(pose, applied), pose.edge_final_pose)


def test_the_boot_rolls_over_its_toe_with_rolling():
    """Standing, the boot's topple over the toe's edge is blocked (the toe meets the table at 10
    degrees, the apex is ~18): the thesis returns it to standing; with ``rolling`` the finger
    turns it on over the toe's tip onto a pose tipped towards +x (the toe's side), and every
    unblocked edge keeps its thesis outcome."""
    from shapes import boot_object, pose_with_down

    from pipeline.model.poses import stable_poses

    pose_set = stable_poses(boot_object())
    standing = pose_with_down(pose_set, [0, 0, -1])
    pose = pose_set.poses[standing]
    edge = int(np.flatnonzero(pose.edge_blocked)[0])
    assert pose.edge_final_pose[edge] == standing
    rolled = pose.edge_rolled_pose[edge]
    assert rolled != standing
    assert pose_set.poses[rolled].down[0] > 0.5  # turned well past 30 degrees towards the toe
    for p in pose_set.poses:
        same = ~p.edge_blocked
        np.testing.assert_array_equal(p.edge_rolled_pose[same], p.edge_final_pose[same])
    assert replace(Config().topple, variant="robust", corrections="rolling").applied_corrections == frozenset()


# ---------------------------------------------------------------- C.14: the balance on the way to the apex


def _box_along_tip(height, mu, theta, weight, d=0.04, w=0.08, com_height=0.075, mu_table=MU_TABLE, max_force=np.inf):
    """C.2's balance for the standing box pushed horizontally at ``height`` across its 8 cm side,
    turned by ``theta`` about the far edge (MODEL.md C.14, in closed form).  In the plane of the
    push (x along it, z up, the far edge at the origin) the near face's normal has turned to
    n = (-cos theta, sin theta) and keeps n . x = w, so the finger (z = height) meets it at
    x_q = (height sin theta - w) / cos theta; a point there moves at v = (height, -x_q) per
    radian, and v . n = (w sin theta - height) / cos theta < 0 while the face recedes.  Along
    the face (t = (sin theta, cos theta)) it slides at (w - height sin theta) / cos^2 theta
    relative to the finger, so friction adds -sign(that) mu t to -n, the torque per newton of
    normal force is tau = (height - w sin theta) / cos theta - sign mu w, and the centre of mass
    is d cos theta - com_height sin theta inside the edge."""
    s, c = np.sin(theta), np.cos(theta)
    recedes = height > w * s
    sign = np.sign(w - height * s)
    tau = (height - w * s) / c - sign * mu * w
    inside = d * c - com_height * s
    if not (recedes and tau > 0 and inside > 0):
        return False, np.inf
    normal_force = weight * inside / tau
    f_push, f_up = normal_force * (c - sign * mu * s), normal_force * (-s - sign * mu * c)
    force = normal_force * np.hypot(1.0, mu)
    table = weight - f_up
    return bool(table > 0 and abs(f_push) <= mu_table * table and force <= max_force), force


@pytest.mark.parametrize("mu_finger", [0.0, 0.98])
def test_the_balance_half_way_to_the_apex_is_the_closed_form(box, mu_finger):
    obj, _, _ = box
    edges, far = _box_far_edge(box)
    weight = obj.mass * 9.81
    theta = edges.apex_angle[far] / 2  # points = 1: the one angle half way
    outcomes = []
    for height in (0.005, 0.02, 0.06, 0.1, 0.135, 0.149):
        for margin in (np.inf, 1 + 1e-9, 1 - 1e-9):  # no limit, a limit just above and just below the force
            _, force = _box_along_tip(height, mu_finger, theta, weight)
            limit = force * margin if np.isfinite(force) and np.isfinite(margin) else np.inf
            expected, _ = _box_along_tip(height, mu_finger, theta, weight, max_force=limit)
            trials = Trials(np.array([[0.0, -0.04, height]]), np.array([[0.0, -1.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]),
                            np.array([MU_TABLE]), np.array([mu_finger]), np.ones(1, bool), np.zeros(1))
            held = holds_along_tip(trials, edges, np.array([far]), obj.mass, 9.81, 1.0, limit, True, 1)
            assert held.tolist() == [expected], (height, margin)
            outcomes.append(expected)
    assert True in outcomes and False in outcomes  # both sides of the balance are exercised


@pytest.mark.parametrize("mu_finger", [0.0, 0.98])
def test_the_standing_box_keeps_its_threshold_with_the_balance_on_the_way(box, mu_finger):
    """Pushed horizontally, the box needs less as it turns (the centre of mass nears the edge
    faster than the torque falls), so ``tip_path`` leaves (C.2.3)'s threshold where it is."""
    d, width = 0.04, 0.08
    threshold = d / MU_TABLE + mu_finger * (width - d)
    points = [[0.0, -d, threshold - STEP], [0.0, -d, threshold + STEP], [0.0, -d, threshold + 10 * STEP]]
    for points_checked in (1, 2, 5):
        topple = noise_free(corrections="finger_friction,tip_path", mu_finger_mean=mu_finger, tip_path_points=points_checked)
        assert _push(box, points, [0.0, 1.0, 0.0], topple).p_topple.tolist() == [0.0, 1.0, 1.0]


def test_the_balance_on_the_way_only_removes_topples_and_stops_some():
    """On a random object under the default noise, ``tip_path`` keeps every trial's outcome or
    stops it (a trial it stops toppled over the edge C.2 chose at the start, and stays): no
    trial topples that did not, and some that did stall on the way (C.14)."""
    from pipeline.model.collision import collision_object
    from pipeline.model.contacts import object_contacts, pose_actions
    from pipeline.model.poses import stable_poses

    obj = random_object(44)
    pose_set = stable_poses(obj)
    contacts = replace(Config().contacts, n_contacts=150)
    points, normals = object_contacts(obj, contacts, seed=5)
    collision = collision_object(obj.mesh)
    base = replace(Config().topple.counted(), n_trials=20, corrections="finger_friction,force_limit")
    stopped = 0
    for pose in pose_set.poses[:4]:
        actions = pose_actions(points, normals, obj.mesh, collision, pose.transform, contacts)
        tables = [evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(5, obj.name, pose.index, "trials"))
                  for topple in (base, replace(base, corrections="finger_friction,force_limit,tip_path"))]
        start, path = (t.outcomes for t in tables)
        changed = start != path
        assert (path[changed] == OUTCOME_NO_EDGE).all()
        stopped += int(changed.sum())
    assert stopped > 0, "some trials should start to tip and stall on the way"


# ---------------------------------------------------------------- C.14 and C.2 at their boundaries (found by mutation testing)
def _square_edges(center_mass):
    """EdgeGeometry of a 1 x 1 (m) square base centred on the origin, edges counter-clockwise
    seen from above; edge 2 runs from (0.5, 0.5) to (-0.5, 0.5): e = (-1, 0, 0), outward +y.
    Every quantity is a small binary fraction, so C.2's arithmetic on it is exact."""
    corners = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    return edge_geometry(np.stack([corners, np.roll(corners, -1, axis=0)], axis=1), np.asarray(center_mass, float))


def _one_trial(contact, normal, push, mu_table, mu_finger=0.0):
    return Trials(np.array([contact], float), np.array([normal], float), np.array([push], float),
                  np.array([mu_table], float), np.array([mu_finger], float), np.ones(1, bool), np.zeros(1))


def test_the_table_check_is_inclusive_at_the_closed_form_threshold():
    """(C.2.5) admits f_xy^2 <= (mu_T N_T)^2, equality included.  Pushed horizontally (u = -n,
    frictionless finger) at height h on the face 1 m from edge 2, the unit-weight body with its
    centre of mass d = 0.5 m inside that edge needs F = d / h (C.2.3 with mu_f = 0) and the table
    carries 1, so at mu_T = 0.5 the threshold is h* = d / mu_T = 1 m exactly."""

    edges = _square_edges([0.0, 0.0, 1.0])
    for height, passes in ((1.0 - 2.0**-10, False), (1.0, True), (1.0 + 2.0**-10, True)):
        force, passed = sliding_contact(_one_trial([0.0, -0.5, height], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], 0.5),
                                        edges, 1.0, 1.0, 1.0, True)
        assert passed[0, 2] == passes, height
        assert force[0, 2] == 0.5 / height  # F = m g d / h, exact in binary


def test_a_finger_moving_off_the_face_pushes_nothing():
    """(C.2.1) follows_e needs u . n < 0: a finger whose push has no component into the face
    (u . n >= 0) loses it at once, however the face would move, so no edge passes, though the
    face over edge 2 recedes (v . n = -h) and the same contact pushed into the face tips it."""

    edges = _square_edges([0.0, 0.0, 1.0])
    contact, normal = [0.0, -0.5, 1.0], [0.0, -1.0, 0.0]
    _, into = sliding_contact(_one_trial(contact, normal, [0.0, 1.0, 0.0], 0.9), edges, 1.0, 1.0, 1.0, True)
    assert into[0, 2]  # F = 0.5 <= 0.9 mu_T: tips
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # u . n = 0 is not into the face: no advance s_e = v_e . n / 0 is formed
        for push in ([0.0, -0.6, 0.8], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]):  # u . n = 0.6, 0, 1
            for mu_finger in (0.0, 0.98):
                force, passes = sliding_contact(_one_trial(contact, normal, push, 0.9, mu_finger), edges, 1.0, 1.0, 1.0, True)
                assert not passes.any(), (push, mu_finger)
                assert np.isinf(force).all(), (push, mu_finger)


def test_no_push_tips_over_an_edge_the_centre_of_mass_is_on():
    """(C.2.4) rotates_e needs d_e > 0: with the centre of mass above edge 2's line (d = 0) the
    moment balance needs no force, and C.2 does not call that a topple over the edge (the reference's
    ``sliding_force`` returns None for d <= 0); just inside (d = 2^-10 m) the same push, 1 m up,
    tips it with F = m g d / h = 2^-10 N."""

    trial = _one_trial([0.0, -0.5, 1.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], 0.5)
    on_edge = _square_edges([0.0, 0.5, 1.0])
    assert on_edge.com_distance[2] == 0.0
    force, passes = sliding_contact(trial, on_edge, 1.0, 1.0, 1.0, True)
    assert not passes[0, 2] and np.isinf(force[0, 2])
    inside = _square_edges([0.0, 0.5 - 2.0**-10, 1.0])
    force, passes = sliding_contact(trial, inside, 1.0, 1.0, 1.0, True)
    assert passes[0, 2] and force[0, 2] == 2.0**-10


def test_a_frictionless_table_holds_nothing_even_under_a_vertical_push():
    """(C.2.5) passes only if mu_T > 0 (a draw at or below zero holds nothing, exactly).  A
    frictionless finger pushing straight down on an overhang 0.25 m beyond edge 2 puts no horizontal
    force on the table (f = (0, 0, -m g d / 0.25)), so the friction limit alone would pass it at
    mu_T = 0; the rule does not."""

    edges = _square_edges([0.0, 0.0, 1.0])
    down = ([0.0, 0.75, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
    force, passes = sliding_contact(_one_trial(*down, 0.5), edges, 1.0, 1.0, 1.0, True)
    assert passes[0, 2] and force[0, 2] == 2.0  # F_n = m g d / tau = 0.5 / 0.25
    for mu_table in (0.0, -0.1):
        _, passes = sliding_contact(_one_trial(*down, mu_table), edges, 1.0, 1.0, 1.0, True)
        assert not passes.any(), mu_table


def test_a_push_that_carries_the_whole_weight_is_not_a_topple():
    """(C.2.5) N_T = m g - f_z must be > 0.  A frictionless finger pushing straight up under a
    down-facing face at the centre of the unit square, 0.5 m from edge 2 (d = 0.5 m), needs
    F = m g d / 0.5 = m g: the table carries exactly nothing and the body is lifted, not tipped.
    From under the near edge (1 m from edge 2) it needs half the weight and tips; from 0.25 m,
    twice the weight, and it does not."""

    edges = _square_edges([0.0, 0.0, 1.0])
    for y, force_needed, passes in ((-0.5, 0.5, True), (0.0, 1.0, False), (0.25, 2.0, False)):
        force, passed = sliding_contact(_one_trial([0.0, y, 0.5], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 0.5),
                                        edges, 1.0, 1.0, 1.0, True)
        assert force[0, 2] == force_needed, y
        assert passed[0, 2] == passes, y


@pytest.mark.parametrize("mu_finger", [0.0, 0.98])
def test_the_force_limit_on_the_way_is_inclusive(box, mu_finger):
    """(C.14.2) asks F_e(theta_k) <= max_finger_force: a limit equal to the force C.2 needs half
    way (``sliding_contact`` at q(theta), n_t, d_e(theta) of (C.14.1), which is (C.14.3) for the
    box) holds, the next float below it does not."""
    obj, _, _ = box
    edges, far = _box_far_edge(box)
    one = EdgeGeometry(*(getattr(edges, f.name)[[far]] for f in fields(EdgeGeometry)))  # the far edge alone
    height = 0.14
    trials = _one_trial([0.0, -0.04, height], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], MU_TABLE, mu_finger)
    theta = one.apex_angle * (1 / 2)
    turned = np.einsum("rij,rj->ri", axis_angle_matrices(one.direction, theta), trials.normal)  # n_t
    advance = np.einsum("ij,ij->i", trials.normal - turned, trials.contact - one.start) / np.einsum("ij,ij->i", turned, trials.push)
    finger = trials.contact + advance[:, None] * trials.push  # q(theta), (C.14.1)
    inside = one.com_distance * (np.sin(one.apex_angle - theta) / np.sin(one.apex_angle))  # d_e(theta)
    force, passes = sliding_contact(replace(trials, contact=finger, normal=turned), replace(one, com_distance=inside),
                                    obj.mass, 9.81, 1.0, True)
    needed = force[0, 0]
    held, closed_form = _box_along_tip(height, mu_finger, theta[0], obj.mass * 9.81)
    assert passes[0, 0] and held
    assert np.isclose(needed, closed_form, rtol=1e-9)  # (C.14.3)

    def holds(limit):
        return holds_along_tip(trials, edges, np.array([far]), obj.mass, 9.81, 1.0, limit, True, 1)[0]

    assert holds(needed)
    assert not holds(np.nextafter(needed, 0.0))


def test_the_force_limit_bites_on_the_way_only_with_force_limit(box):
    """On a grippy table (mu_T = 2) a frictionless finger low on the box's 8 cm side (h = 2.8 cm)
    starts the tip with F_0 = m g d / h and needs more half way ((C.14.3): the torque arm
    h - w sin theta shrinks faster than d_e(theta)).  With a finger force limit between the two
    the push topples with ``force_limit`` alone and with ``tip_path`` alone (no limit on the way
    without ``force_limit``), and stalls with both; a limit above both lets it topple."""
    height, mu_table = 0.028, 2.0
    obj, _, _ = box
    weight = obj.mass * noise_free().gravity
    apex = np.arctan2(0.04, 0.075)
    starts, start = _box_along_tip(height, 0.0, 0.0, weight, mu_table=mu_table)
    holds, half_way = _box_along_tip(height, 0.0, apex / 2, weight, mu_table=mu_table)
    assert starts and holds and half_way > 1.2 * start

    def p_topple(corrections, limit):
        topple = noise_free(corrections=corrections, mu_table_mean=mu_table, mu_finger_mean=0.0,
                            max_finger_force=limit, tip_path_points=1)
        return _push(box, [[0.0, -0.04, height]], [0.0, 1.0, 0.0], topple).p_topple[0]

    between = (start + half_way) / 2
    assert p_topple("finger_friction,force_limit", between) == 1.0
    assert p_topple("finger_friction,tip_path", between) == 1.0
    assert p_topple("finger_friction,force_limit,tip_path", between) == 0.0
    assert p_topple("finger_friction,force_limit,tip_path", 1.1 * half_way) == 1.0


def test_a_trial_that_stalls_on_the_way_reports_no_edge_and_infinite_force(box):
    """``trial_outcomes`` returns OUTCOME_NO_EDGE and an infinite force for a trial that does not
    topple, a stalled one (C.14) included, as for one whose finger missed the object (invalid, NaN
    contact: it is never computed); a trial that topples keeps its start force (C.2.3)."""

    obj, _, _ = box
    edges, far = _box_far_edge(box)
    mu_table, weight = 2.0, obj.mass * noise_free().gravity
    apex = np.arctan2(0.04, 0.075)
    heights = np.array([0.028, 0.06])  # stalls half way under the limit below; topples
    _, start = _box_along_tip(heights[0], 0.0, 0.0, weight, mu_table=mu_table)
    _, half_way = _box_along_tip(heights[0], 0.0, apex / 2, weight, mu_table=mu_table)
    topple = noise_free(corrections="finger_friction,force_limit,tip_path", mu_table_mean=mu_table, mu_finger_mean=0.0,
                        max_finger_force=(start + half_way) / 2, tip_path_points=1)
    contact = np.vstack([np.column_stack([np.zeros(2), np.full(2, -0.04), heights]), np.full((1, 3), np.nan)])
    normal = np.vstack([np.tile([0.0, -1.0, 0.0], (2, 1)), np.full((1, 3), np.nan)])
    trials = Trials(contact, normal, np.tile([0.0, 1.0, 0.0], (3, 1)), np.full(3, mu_table), np.zeros(3),
                    np.array([True, True, False]), np.zeros(3))
    edge, force = trial_outcomes(trials, edges, obj.mass, topple)
    assert edge[0] == OUTCOME_NO_EDGE and force[0] == np.inf
    assert edge[1] == far and np.isclose(force[1], weight * 0.04 / heights[1], rtol=1e-9)
    assert edge[2] == OUTCOME_NO_EDGE and force[2] == np.inf


def test_the_stuck_finger_takes_only_valid_pushes_that_press_down_and_drag_the_base():
    """C.11 qualifies a trial over an edge only if its push moves down (u_z < 0) and drags the base
    (|u_xy| > mu_T |u_z|), as the reference's ``drags_base``.  On an overhang 0.25 m beyond edge 2 of
    the unit square (centre of mass 1 m up, d = 0.5 m): pushed down and outward it tips over edge 2
    with F = m g d / (h u_y + 0.25 |u_z|); the same push from an invalid trial, a horizontal push
    (which presses nothing down) and a push straight down on a frictionless table (no horizontal
    part to drag with) tip nothing, though each turns the body outward about edge 2.  Through
    ``trial_outcomes`` (finger friction 0.98, which holds the sliding finger back: C.2 alone tips
    nothing) the first trial tips at that force with a share of 1, and with a share of 0 nothing
    tips, though these trials drew 0, the lowest draw (draws lie in [0, 1): a share q takes draw < q)."""
    from pipeline.model import reference
    from pipeline.model.topple import drags_base, stuck_finger

    edges = _square_edges([0.0, 0.0, 1.0])
    pushes = np.array([[0.0, 0.8, -0.6], [0.0, 0.8, -0.6], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    mu_table = np.array([0.5, 0.5, 0.5, 0.0])
    trials = Trials(np.tile([0.0, 0.75, 1.0], (4, 1)), np.tile([0.0, 0.0, 1.0], (4, 1)), pushes, mu_table, np.full(4, MU_FINGER),
                    np.array([True, False, True, True]), np.zeros(4))
    drags = drags_base(pushes, mu_table)
    assert drags.tolist() == [reference.drags_base(tuple(u), mu) for u, mu in zip(pushes, mu_table)] == [True, True, False, False]
    edge, force = stuck_finger(trials, edges, 1.0, 1.0, 10.0)
    assert edge[0] == 2 and force[0] == pytest.approx(0.5 / (0.8 + 0.25 * 0.6), rel=1e-12)
    assert np.isinf(force[1:]).all()
    # The limit is inclusive (F <= max_force); an edge the centre of mass is on (d = 0) is not tipped (F = 0).
    assert stuck_finger(trials, edges, 1.0, 1.0, force[0])[1][0] == force[0]
    assert np.isinf(stuck_finger(trials, edges, 1.0, 1.0, np.nextafter(force[0], 0.0))[1][0])
    assert np.isinf(stuck_finger(trials, _square_edges([0.0, 0.5, 1.0]), 1.0, 1.0, 10.0)[1]).all()
    for corrections, share, tips in (("finger_friction", 1.0, False), ("finger_friction,stuck_finger", 1.0, True),
                                     ("finger_friction,stuck_finger", 0.0, False)):
        config = noise_free(corrections=corrections, stuck_finger_share=share, gravity=1.0)
        edge, force = trial_outcomes(trials, edges, 1.0, config)
        assert edge.tolist() == [2 if tips else OUTCOME_NO_EDGE] + [OUTCOME_NO_EDGE] * 3, (corrections, share)
        assert force[0] == (pytest.approx(0.5 / 0.95, rel=1e-12) if tips else np.inf) and np.isinf(force[1:]).all()


@pytest.mark.parametrize("corrections", ["finger_friction,force_limit", "finger_friction,stroke"])
def test_the_force_limit_and_the_stroke_are_inclusive(box, corrections):
    """C.1 lets the finger push with F <= max_finger_force and C.10 carry the box as far as s <= stroke,
    equality included: pushed horizontally high on the 8 cm side, the trial with a limit (a stroke)
    equal to the force it needs (the travel to the apex, ``finger_travel``) topples at the force it
    needs without one; with the next float below, ``trial_outcomes`` reports no edge at infinite force."""
    obj, _, _ = box
    edges, far = _box_far_edge(box)
    trials = _one_trial([0.0, -0.04, 0.145], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], MU_TABLE, MU_FINGER)
    edge, free = trial_outcomes(trials, edges, obj.mass, noise_free(corrections="finger_friction"))
    assert edge[0] == far and np.isfinite(free[0])
    if "force_limit" in corrections:
        field, needed = "max_finger_force", free[0]
    else:
        field, needed = "stroke", finger_travel(trials, edges, np.array([far]))[0]
        assert 0 < needed < np.inf
    edge, force = trial_outcomes(trials, edges, obj.mass, noise_free(corrections=corrections, **{field: needed}))
    assert edge[0] == far and force[0] == free[0]
    edge, force = trial_outcomes(trials, edges, obj.mass, noise_free(corrections=corrections, **{field: np.nextafter(needed, 0.0)}))
    assert edge[0] == OUTCOME_NO_EDGE and force[0] == np.inf


def test_each_edge_alone_gets_the_bits_it_gets_among_all_edges():
    """C.2's balance runs only on the (trial, edge) pairs whose face recedes from the finger: a trial's
    force and verdict over an edge are the same to the bit whether the edge comes alone or among the
    pose's others (other pairs kept).  That they are C.2's, pairs left out included, is what
    tests/test_reference.py holds trial by trial against the scalar reference."""
    rng = np.random.default_rng(7)
    n = 400
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    push = -normal + 0.6 * rng.normal(size=(n, 3))
    push /= np.linalg.norm(push, axis=1)[:, None]
    contact = rng.uniform([-0.6, -0.6, 0.0], [0.6, 0.6, 1.0], (n, 3))
    trials = Trials(contact, normal, push, rng.uniform(0.2, 1.0, n), rng.uniform(0.0, 1.0, n), rng.random(n) < 0.95,
                    np.zeros(n))
    edges = _square_edges([0.1, -0.05, 0.4])
    for spin_stops in (True, False):
        force, passes = sliding_contact(trials, edges, 0.3, 9.81, 1.0, spin_stops)  # (n, 4) each
        for e in range(4):
            alone = EdgeGeometry(**{f: getattr(edges, f)[[e]] for f in EdgeGeometry.__dataclass_fields__})
            force_e, passes_e = sliding_contact(trials, alone, 0.3, 9.81, 1.0, spin_stops)
            assert force_e[:, 0].tobytes() == force[:, e].tobytes() and np.array_equal(passes_e[:, 0], passes[:, e])
        assert passes.any() and not passes.all() and np.isfinite(force).any() and np.isinf(force).any()
        assert not passes[~trials.valid].any()


def test_the_least_force_from_the_passing_pairs_is_the_grids_argmin():
    """(10.6) from the passing pairs alone is ``argmin(where(passes, force, inf))`` over the whole grid and its
    value: ties go to the first edge, a row with no passing pair keeps inf (its edge is never read)."""
    rng = np.random.default_rng(3)
    n, width = 300, 6
    force = rng.choice([0.5, 1.0, 2.0, 3.0, np.inf], size=(n, width))  # few values: many ties
    passes = rng.random((n, width)) < 0.3
    pair = np.flatnonzero(passes)
    edge, required = _least_passing((n, width), pair, force.ravel()[pair])
    candidate = np.where(passes, force, np.inf)
    expected = np.argmin(candidate, axis=1)
    assert np.array_equal(required, candidate[np.arange(n), expected])
    some = np.isfinite(required)
    assert np.array_equal(edge[some], expected[some]) and some.any() and not some.all()
    ties = (candidate == candidate.min(axis=1, keepdims=True)).sum(axis=1) > 1
    assert (ties & some).any(), "the test needs rows whose least force two edges share"
    assert np.isinf(_least_passing((n, width), pair[:0], force.ravel()[:0])[1]).all()
    # argmin's other rules: a NaN wins from where it stands, and -0.0 and 0.0 tie (the first is taken).
    odd = np.array([[1.0, np.nan, 0.5, np.nan], [0.0, -0.0, 2.0, 1.0], [np.inf, np.inf, 3.0, np.inf]])
    every = np.arange(odd.size)
    edge, required = _least_passing(odd.shape, every, odd.ravel())
    assert edge.tolist() == np.argmin(odd, axis=1).tolist() == [1, 0, 2]
    assert required.tobytes() == odd[np.arange(3), edge].tobytes()


def test_trials_take_rows_by_index_mask_or_slice_alike():
    """``Trials.take`` gathers along the rows with ``ndarray.take``, which would read a boolean mask as
    indices 0 and 1: a mask, its indices and a slice give the same trials."""
    rng = np.random.default_rng(5)
    trials = Trials(rng.random((6, 3)), rng.random((6, 3)), rng.random((6, 3)), rng.random(6), rng.random(6),
                    rng.random(6) < 0.5, rng.random(6))
    mask = np.array([False, True, True, True, False, False])
    for rows in (np.flatnonzero(mask), slice(1, 4)):
        for field in Trials.__dataclass_fields__:
            assert np.array_equal(getattr(trials.take(mask), field), getattr(trials.take(rows), field))


def test_tip_back_finds_the_edge_the_line_from_the_centre_of_mass_through_the_contact_leaves_by():
    # C.22 on the standing box's 5 x 8 cm base: a contact's foot beyond or inside each side names that side; towards a
    # corner the side the line meets first; at the centre of mass's own foot, none.  The reference agrees.
    from pipeline.model.reference import line_edge
    from pipeline.model.topple import line_edges

    obj, pose_set, standing = standing_box()
    pose = pose_set.poses[standing]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edges = edge_geometry(pose.base_edges, center_mass)
    half = np.abs(pose.base_edges[:, :, :2].reshape(-1, 2)).max(axis=0)  # (2,)
    side = lambda e: np.round(edges.outward[e, :2], 12).tolist()
    contacts, expected = [], []
    for direction in ([1, 0], [-1, 0], [0, 1], [0, -1]):
        for reach in (0.4, 2.0):
            contacts.append([*(reach * half * direction), 0.1])
            expected.append([float(d) for d in direction])
    contacts += [[*(3 * half * [0.9, 0.1]), 0.1], [*(3 * half * [0.1, 0.9]), 0.1], [0.0, 0.0, 0.12]]
    expected += [[1.0, 0.0], [0.0, 1.0], None]
    found = line_edges(np.array(contacts, dtype=float), edges)
    for edge, want, contact in zip(found, expected, contacts):
        assert (edge == -1) if want is None else side(edge) == want
        assert edge == line_edge(tuple(contact), [tuple(map(tuple, e)) for e in pose.base_edges], tuple(center_mass))


def test_tip_back_changes_only_hard_presses_from_above():
    # random_044's pushes, with tip_back and a threshold over every force, and without it: the same outcomes; with a
    # low threshold some trials move to another edge, none pushed from below, and what topples and its force do not.
    obj = random_object(44)
    from pipeline.model.collision import collision_object
    from pipeline.model.contacts import object_contacts, pose_actions
    from pipeline.model.poses import stable_poses

    pose_set = stable_poses(obj)
    contacts = replace(Config().contacts, n_contacts=80)
    points, normals = object_contacts(obj, contacts, seed=5)
    default = Config().topple.counted()
    base = replace(default, n_trials=10, corrections=",".join(sorted(default.applied_corrections - {"tip_back"})))
    moved = 0
    for pose in pose_set.poses[:4]:
        actions = pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), pose.transform, contacts)
        variants = (base, replace(base, corrections=base.corrections + ",tip_back", tip_back_force=1e9),
                    replace(base, corrections=base.corrections + ",tip_back", tip_back_force=0.1))
        without, never, low = [evaluate_pose(obj, pose, pose_set.probabilities, actions, topple,
                                             stream(5, obj.name, pose.index, "trials")) for topple in variants]
        np.testing.assert_array_equal(never.outcomes, without.outcomes)
        np.testing.assert_array_equal(low.outcomes >= 0, without.outcomes >= 0)  # what topples does not change
        np.testing.assert_array_equal(low.mean_force, without.mean_force)
        changed = low.outcomes != without.outcomes  # (A, T)
        # Only trials pushed from above move; their pushes are nominally from above or the side, never from below.
        assert np.all(actions.directions[np.nonzero(changed)[0], 2] < 0.3)
        moved += changed.sum()
    assert moved > 0, "a low threshold should tip some trials back"
