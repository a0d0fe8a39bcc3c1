"""The carried finger (docs/MODEL.md C.23) on a faceted rod, in closed form.

A regular 12-sided prism of circumradius R lies on a facet: its base edges are a = R sin 15 deg either side of
the centre of mass, which is h = R cos 15 deg up, so it tips over an edge at theta_e = 15 deg.  Pushed along the
inward normal at the centre of the facet tilted phi from the top, the push's line passes through the axis, so
without friction its moment about the far base edge is F R sin(phi - 15 deg) against gravity's m g a:

    F* = m g sin 15 deg / sin(phi - 15 deg)

and as the rod tips the face slides along the fingertip at |(p - y0) . n| per radian, so by

    slide = (h (1 + cos phi) + a sin phi) theta_e

before the apex.  C.2's finger follows its path and its friction (mu_f 0.98) holds the rod; carried with the
face (slide <= ``carried_slide``) it presses along the normal alone and the rod rolls, as the push player's
does (docs/VALIDATION.md, "The household set": pressed from above, a 12-sided rod rolled one facet on from
every facet tilted 23-69 degrees off the top).
"""

import numpy as np
import pytest
from shapes import explicit_trials, faceted_rod, noise_free, standing_box

from pipeline.model.contacts import explicit_actions
from pipeline.model.edges import edge_geometry
from pipeline.model.rng import stream
from pipeline.model.topple import TRIAL_STAGES, evaluate_pose
from schema.frames import transform_points

RADIUS = 0.02
SIXTH = np.radians(15.0)


@pytest.fixture(scope="module")
def rod():
    return faceted_rod(radius=RADIUS)


def _facet_push(rod, phi_degrees):
    """The centre of a facet tilted phi from the top, its outward normal, and the centre of mass (pose frame)."""
    obj, pose_set, index = rod
    pose = pose_set.poses[index]
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    normals = obj.mesh.face_normals @ pose.transform[:3, :3].T
    normal = normals[np.argmin(np.abs(normals[:, 2] - np.cos(np.radians(phi_degrees))) + 10 * (normals[:, 0] < 0))]
    return center_mass + RADIUS * np.cos(SIXTH) * normal, normal, center_mass


def _push(rod, point, direction, topple):
    obj, pose_set, index = rod
    pose = pose_set.poses[index]
    actions = explicit_actions(obj, pose.transform, np.atleast_2d(point), np.atleast_2d(direction))
    return evaluate_pose(obj, pose, pose_set.probabilities, actions, topple, stream(0, obj.name, index, "trials"))


def carried_config(**fields):
    """The noise-free trial with C.2, the force limit and the carried finger."""
    return noise_free(corrections="finger_friction,force_limit,carried_finger", **fields)


def _slide(phi_degrees):
    phi, a, h = np.radians(phi_degrees), RADIUS * np.sin(SIXTH), RADIUS * np.cos(SIXTH)
    return (h * (1 + np.cos(phi)) + a * np.sin(phi)) * SIXTH


@pytest.mark.parametrize("phi", [30.0, 60.0])
def test_a_rod_pressed_from_above_rolls_with_the_carried_finger_at_the_closed_form_force(rod, phi):
    obj, pose_set, index = rod
    point, normal, center_mass = _facet_push(rod, phi)
    held = _push(rod, point, -normal, noise_free(corrections="finger_friction,force_limit"))
    carried = _push(rod, point, -normal, carried_config())
    assert held.outcomes[0, 0] < 0 and carried.outcomes[0, 0] >= 0
    weight = obj.mass * carried_config().gravity
    assert carried.mean_force[0] == pytest.approx(weight * np.sin(SIXTH) / np.sin(np.radians(phi) - SIXTH), rel=1e-6)
    # It rolls away from the pushed facet: over the base edge on the far side of the centre of mass.
    edges = edge_geometry(pose_set.poses[index].base_edges, center_mass)
    assert edges.outward[carried.outcomes[0, 0]] @ normal < -0.1


@pytest.mark.parametrize("phi", [30.0, 60.0])
def test_the_rod_rolls_only_while_the_face_slides_less_than_the_give(rod, phi):
    point, normal, _ = _facet_push(rod, phi)
    slide = _slide(phi)
    assert 0.005 < slide < 0.016, "the default give (16 mm) carries the finger on both facets"
    for give, rolls in ((slide * (1 - 1e-6), False), (slide * (1 + 1e-6), True)):
        table = _push(rod, point, -normal, carried_config(carried_slide=give))
        assert (table.outcomes[0, 0] >= 0) == rolls, give


def test_the_carried_finger_leaves_pushes_from_the_side_to_c2():
    """The standing box pushed across its 5 cm side below C.2's threshold (8.3 cm) stays, however far the
    finger might give: a push from the side drags the object before the finger reaches its limit."""
    box = standing_box()
    points = [[-0.025, 0.0, h] for h in (0.03, 0.06, 0.08)]
    for topple in (noise_free(corrections="finger_friction,force_limit"), carried_config(carried_slide=1.0)):
        table = _push(box, points, np.tile([1.0, 0.0, 0.0], (3, 1)), topple)
        assert table.p_topple.tolist() == [0.0, 0.0, 0.0]


def test_the_carried_finger_pushes_no_harder_than_the_finger_can(rod):
    obj, _, _ = rod
    point, normal, _ = _facet_push(rod, 30.0)
    force = obj.mass * carried_config().gravity  # F* at phi = 30 degrees
    for limit, rolls in ((force * (1 + 1e-6), True), (force * (1 - 1e-6), False)):
        table = _push(rod, point, -normal, carried_config(max_finger_force=limit))
        assert (table.outcomes[0, 0] >= 0) == rolls, limit


def test_the_stage_census_names_the_carried_finger(rod):
    from pipeline.model.topple import trial_stages

    point, normal, _ = _facet_push(rod, 30.0)
    names = []
    for topple in (noise_free(corrections="finger_friction,force_limit"), carried_config()):
        obj, trials, edges = explicit_trials(rod, point[None], -normal[None], topple)
        names += [TRIAL_STAGES[s] for s in trial_stages(trials, edges, obj.mass, topple)]
    assert names[0] not in ("tips", "carried_finger_tips", "stuck_finger_tips") and names[1] == "carried_finger_tips"
