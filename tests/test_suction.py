"""Suction grasp quality V_s (pipeline/suction.py): known answers on simple shapes,
the closed-form seal and wrench checks, and the gripper body against overhangs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from pipeline.model.collision import collision_object
from pipeline.model.config import SuctionConfig, ToppleConfig
from pipeline.model.suction import (
    body_collisions,
    cast_depths,
    grasp_qualities,
    perturb,
    sample_candidates,
    seal_contacts,
    suction_quality,
    table_collisions,
    upward_faces,
    wrench_resisted,
)

CONFIG = SuctionConfig()
NO_BENDING = dataclasses.replace(CONFIG, elastic_limit=np.inf)
"""For tests that bound V_s from above: every wrench constraint only removes successes,
so a shape that scores low without the bending limit scores low with any limit --
the low score is then the geometry's doing, whatever the default limit is."""
LIGHT = 0.05
"""kg; light enough that tests bounding V_s from below hold at the default bending limit."""


def resting(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy translated so that it rests on z = 0 with its centre of mass over the origin."""
    mesh = mesh.copy()
    com = mesh.center_mass
    mesh.apply_translation([-com[0], -com[1], -mesh.bounds[0, 2]])
    return mesh


def lying(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Rotate a z-axis solid of revolution (cylinder) onto its side."""
    mesh = mesh.copy()
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return resting(mesh)


def quality(mesh, mass=LIGHT, config=CONFIG, seed=0, com=None):
    com = mesh.center_mass if com is None else com
    return suction_quality(mesh, com, mass, config, np.random.default_rng(seed))


def prism(width: float, height: float, length: float) -> trimesh.Trimesh:
    """A triangular prism lying on its base (width along x), ridge on top along y."""
    section = np.array([[-width / 2, 0.0], [width / 2, 0.0], [0.0, height]])
    points = [[x, y, z] for x, z in section for y in (-length / 2, length / 2)]
    return trimesh.convex.convex_hull(np.array(points))


def sheltered_slab(with_roof: bool = True) -> trimesh.Trimesh:
    """A 10 x 10 x 1 cm slab whose flat top lies 3 cm under a roof.

    The roof is a row of steep (60 degree) triangular ridges carried by a 1 cm wall at
    +x, so it offers no upward face within 45 degrees and the wall's 1 cm wide top is
    too narrow for the 3 cm cup: the slab's top is the only place a cup can seal.  The
    parts overlap instead of being fused; ray casting and fcl need no watertight union.
    """
    parts = [trimesh.creation.box([0.11, 0.10, 0.01], trimesh.transformations.translation_matrix([0.005, 0, 0.005]))]
    if with_roof:
        parts.append(trimesh.creation.box([0.01, 0.10, 0.04], trimesh.transformations.translation_matrix([0.055, 0, 0.03])))
        ridge_height = 0.01 * np.sqrt(3) / 2
        for x in np.arange(-0.045, 0.055, 0.01):
            ridge = prism(0.01, ridge_height, 0.10)
            ridge.apply_translation([x, 0.0, 0.04])
            parts.append(ridge)
    return trimesh.util.concatenate(parts)


# ----------------------------------------------------------------------------- known answers


def test_flat_top_of_a_box_is_a_robust_grasp():
    box = resting(trimesh.creation.box([0.08, 0.08, 0.05]))
    for seed in range(3):
        result = quality(box, seed=seed)
        assert result.quality >= 0.9
        assert result.point[2] == pytest.approx(0.05, abs=1e-9)
        np.testing.assert_allclose(result.axis, [0, 0, -1], atol=1e-9)


@pytest.mark.parametrize("radius", [0.01, 0.02])
def test_thin_cylinder_lying_on_its_side_is_a_poor_grasp(radius):
    cylinder = lying(trimesh.creation.cylinder(radius=radius, height=0.15, sections=48))
    points, _ = sample_candidates(cylinder, CONFIG.n_candidates, CONFIG.max_approach_angle, np.random.default_rng(0))
    assert len(points) > 0  # there are upward faces: the cup fails on the curvature, not on reach
    assert quality(cylinder, config=NO_BENDING).quality <= 0.3


def test_wide_cylinder_lying_on_its_side_is_graspable():
    # The contrast to the thin cylinder: the same shape with a gentle curvature seals.
    cylinder = lying(trimesh.creation.cylinder(radius=0.08, height=0.15, sections=96))
    assert quality(cylinder).quality >= 0.5


@pytest.mark.parametrize(
    "shape",
    [
        pytest.param(lambda: trimesh.creation.cone(radius=0.03, height=0.02, sections=4), id="pyramid"),
        pytest.param(lambda: trimesh.creation.cone(radius=0.04, height=0.015, sections=3), id="tetrahedron"),
        pytest.param(lambda: trimesh.creation.cone(radius=0.03, height=0.02, sections=64), id="cone"),
        pytest.param(lambda: prism(0.04, 0.01, 0.10), id="ridge"),
    ],
)
def test_top_that_is_only_a_vertex_or_ridge_gives_no_grasp(shape):
    mesh = resting(shape())
    points, _ = sample_candidates(mesh, CONFIG.n_candidates, CONFIG.max_approach_angle, np.random.default_rng(0))
    assert len(points) > 0  # slopes are within reach: it is the seal across the apex that fails
    assert quality(mesh, config=NO_BENDING).quality <= 0.05


def test_gripper_body_hitting_an_overhang_fails():
    open_slab = resting(sheltered_slab(with_roof=False))
    sheltered = sheltered_slab(with_roof=True)
    com = open_slab.center_mass  # same slab, same load; the roof only gets in the way
    assert quality(open_slab, com=com).quality >= 0.9
    assert quality(sheltered, com=com, config=NO_BENDING).quality <= 0.05

    # The slab top still seals under the roof: the body, not the cup, is what fails.
    point, axis = np.array([[0.0, 0.0, 0.01]]), np.array([[0.0, 0.0, -1.0]])
    sealed, _ = seal_contacts(sheltered, point, axis, CONFIG)
    assert sealed.all()
    assert body_collisions(collision_object(sheltered), point, axis, CONFIG).all()
    assert not body_collisions(collision_object(open_slab), point, axis, CONFIG).any()


def test_heavier_object_of_the_same_shape_never_scores_higher():
    shapes = [
        resting(trimesh.creation.box([0.08, 0.08, 0.05])),
        resting(trimesh.creation.box([0.12, 0.03, 0.04])),
        lying(trimesh.creation.cylinder(radius=0.05, height=0.12, sections=64)),
    ]
    dropped = False
    for mesh in shapes:
        scores = [quality(mesh, mass=m, seed=7).quality for m in (0.01, 0.1, 0.3, 1.0, 3.0)]
        assert all(b <= a for a, b in zip(scores, scores[1:])), scores
        dropped |= scores[-1] < scores[0]
    assert dropped  # the masses span the bending limit, so the check above has teeth


def test_quality_is_a_fraction_and_a_failed_pose_has_no_grasp():
    rng = np.random.default_rng(3)
    shapes = [
        trimesh.creation.icosphere(subdivisions=2, radius=0.04),
        trimesh.creation.capsule(height=0.08, radius=0.02),
        trimesh.creation.box([0.05, 0.07, 0.02]),
        trimesh.convex.convex_hull(rng.normal(0, 0.03, (30, 3))),
    ]
    for mesh in map(resting, shapes):
        result = quality(mesh, mass=0.2)
        assert 0.0 <= result.quality <= 1.0
        k = CONFIG.n_samples
        assert result.quality * k == pytest.approx(round(result.quality * k))
        if result.quality == 0.0:
            assert np.isnan(result.point).all() and np.isnan(result.axis).all()
        else:
            assert np.isfinite(result.point).all()
            assert np.linalg.norm(result.axis) == pytest.approx(1.0)
            assert result.axis[2] <= -np.cos(CONFIG.max_approach_angle) + 1e-9


def test_same_generator_state_gives_the_same_result():
    mesh = lying(trimesh.creation.cylinder(radius=0.05, height=0.12, sections=64))
    a, b = quality(mesh, mass=0.3, seed=11), quality(mesh, mass=0.3, seed=11)
    assert a.quality == b.quality
    np.testing.assert_array_equal(a.point, b.point)


def test_no_face_within_reach_means_no_grasp():
    # A steep spike (72 degree slopes) offers no face within 45 degrees of vertical.
    mesh = resting(trimesh.creation.cone(radius=0.02, height=0.06, sections=32))
    points, axes = sample_candidates(mesh, CONFIG.n_candidates, CONFIG.max_approach_angle, np.random.default_rng(0))
    assert points.shape == (0, 3) and axes.shape == (0, 3)
    result = quality(mesh)
    assert result.quality == 0.0 and np.isnan(result.point).all()
    assert result.point.shape == (3,) and result.axis.shape == (3,)


def test_a_face_at_exactly_the_largest_approach_angle_is_within_reach():
    angle = CONFIG.max_approach_angle
    normals = np.array([[np.sin(a), 0.0, np.cos(a)] for a in (0.0, angle, angle + 1e-6, np.pi / 2)])
    np.testing.assert_array_equal(upward_faces(normals, angle), [True, True, False, False])


@pytest.mark.parametrize("count", [1, 7])
def test_candidates_are_as_many_as_asked_and_lie_on_the_upward_faces(count):
    box = resting(trimesh.creation.box([0.06, 0.04, 0.03]))
    points, axes = sample_candidates(box, count, CONFIG.max_approach_angle, np.random.default_rng(2))
    assert points.shape == axes.shape == (count, 3)
    np.testing.assert_allclose(points[:, 2], 0.03, atol=1e-12)  # the box's only upward face is its top
    np.testing.assert_allclose(axes, np.tile([0.0, 0.0, -1.0], (count, 1)), atol=1e-12)
    assert np.all(np.abs(points[:, :2]) <= [0.03, 0.02])


def test_rays_find_their_distance_to_every_face_the_first_included():
    # Face indices start at 0; a hit on face 0 is a hit like any other.
    box = resting(trimesh.creation.box([0.1, 0.08, 0.06]))
    gap = 0.01
    origins = box.triangles_center + gap * box.face_normals
    depths = cast_depths(box, origins, -box.face_normals)
    np.testing.assert_allclose(depths, gap, atol=1e-9)
    away = cast_depths(box, origins[:1], box.face_normals[:1])
    assert np.isnan(away).all()


def test_rays_from_inside_find_the_face_they_leave_through():
    # From the centre of a box, a ray along each face's outward normal meets that face (seen
    # from behind) at half the box's extent: a first hit is a hit whichever side it is seen from.
    extents = np.array([0.1, 0.08, 0.06])
    box = trimesh.creation.box(extents)
    directions = np.vstack([np.eye(3), -np.eye(3)])
    depths = cast_depths(box, np.zeros((6, 3)), directions)
    np.testing.assert_allclose(depths, np.tile(extents / 2, 2), atol=1e-12)


def test_perturbations_draw_the_configured_noise_around_each_grasp():
    config = dataclasses.replace(CONFIG, n_samples=20000, friction_std=0.05)
    tilt, mass = 0.4, 0.3
    points = np.array([[0.01, -0.02, 0.05], [0.0, 0.03, 0.1]])
    axes = np.array([[0.0, 0.0, -1.0], [np.sin(tilt), 0.0, -np.cos(tilt)]])
    p, a, mu, m = perturb(points, axes, mass, config, np.random.default_rng(0))
    n = config.n_samples
    assert p.shape == a.shape == (2, n, 3) and mu.shape == m.shape == (2, n)
    # Each draw is independent, so the sample means sit within a few standard errors.
    np.testing.assert_allclose(p.mean(axis=1), points, atol=5 * config.position_std / np.sqrt(n))
    np.testing.assert_allclose((p - points[:, None]).std(axis=1), config.position_std, rtol=0.05)
    assert mu.mean() == pytest.approx(config.friction, abs=5 * config.friction_std / np.sqrt(mu.size))
    assert mu.std() == pytest.approx(config.friction_std, rel=0.05)
    spread = mass * config.mass_std_fraction
    assert m.mean() == pytest.approx(mass, abs=5 * spread / np.sqrt(m.size))
    assert m.std() == pytest.approx(spread, rel=0.05)
    # Axes stay unit and tilt by axis_std about each of the two perpendicular directions.
    np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0)
    angle = np.arccos(np.clip(np.sum(a * axes[:, None], axis=-1), -1.0, 1.0))
    np.testing.assert_allclose(np.sqrt(np.mean(angle**2, axis=1)), np.sqrt(2) * config.axis_std, rtol=0.05)


def test_a_large_axis_noise_tilts_by_the_drawn_perpendicular_amount_only():
    # a_s = unit(a + t_perp): the tilt's tangent is |t_perp| exactly, whose mean square is
    # 2 axis_std^2 (two perpendicular components), and a_s never turns past 90 degrees from a;
    # a component of the draw along a would only rescale a and is removed, not kept.
    config = dataclasses.replace(CONFIG, n_samples=20000, axis_std=1.0)
    axes = np.array([[0.0, 0.0, -1.0], [np.sin(0.4), 0.0, -np.cos(0.4)]])
    _, a, _, _ = perturb(np.zeros((2, 3)), axes, 0.3, config, np.random.default_rng(5))
    along = np.sum(a * axes[:, None], axis=-1)
    assert along.min() > 0.0
    tangent = np.linalg.norm(a - along[..., None] * axes[:, None], axis=-1) / along
    np.testing.assert_allclose(np.sqrt(np.mean(tangent**2, axis=1)), np.sqrt(2) * config.axis_std, rtol=0.05)


def test_perturbed_friction_and_mass_are_never_negative():
    config = dataclasses.replace(CONFIG, n_samples=5000, friction_std=1.0, mass_std_fraction=2.0)
    _, _, mu, m = perturb(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]), 0.2, config, np.random.default_rng(1))
    assert mu.min() == 0.0 and m.min() == 0.0  # the draws below zero are held at zero, not redrawn
    assert (mu > 0).mean() > 0.5 and (m > 0).mean() > 0.5


def test_grasp_qualities_has_one_value_per_candidate():
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    rng = np.random.default_rng(0)
    one = grasp_qualities(box, box.center_mass, LIGHT, np.array([[0.0, 0.0, 0.05]]), np.array([[0.0, 0.0, -1.0]]), CONFIG, rng)
    none = grasp_qualities(box, box.center_mass, LIGHT, np.zeros((0, 3)), np.zeros((0, 3)), CONFIG, rng)
    assert one.shape == (1,) and one[0] == 1.0
    assert none.shape == (0,)


def test_the_chosen_grasp_is_the_tied_one_nearest_the_centre_of_mass():
    # With no perturbation every candidate on a light box's wide top holds: a 100-way tie, which
    # the grasp nearest the centre of mass in plan wins (1.5 cm covers 7 % of the top: the nearest
    # of 100 uniform candidates is that close unless about 1 in 1,400 draws).
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    exact = dataclasses.replace(CONFIG, position_std=0.0, axis_std=0.0)
    for seed in range(5):
        result = quality(box, config=exact, seed=seed)
        assert result.quality == 1.0
        assert np.linalg.norm(result.point[:2] - box.center_mass[:2]) < 0.015


def test_the_grasp_moves_with_the_object_across_the_table():
    box = resting(trimesh.creation.box([0.1, 0.07, 0.05]))
    shift = np.array([0.3, -0.2, 0.0])
    moved = box.copy()
    moved.apply_translation(shift)
    here, there = quality(box, mass=0.4, seed=4), quality(moved, mass=0.4, seed=4)
    assert here.quality > 0.5
    assert there.quality == here.quality
    np.testing.assert_allclose(there.point, here.point + shift, atol=1e-9)
    np.testing.assert_allclose(there.axis, here.axis, atol=1e-12)


def test_the_cup_lands_on_the_surface_wherever_the_noisy_aim_falls_along_the_approach():
    # A 2 mm plate on the table, approached straight down at its centre: every sample seals on
    # the flat top and a light plate held at its centre cannot slip or bend the cup.  The
    # position noise also moves the aim point up and down (here by 3 mm rms, often more than
    # the plate's 2 mm plus the body's 4 mm stand-off below the top), but the cup stops on the
    # plate, so the body is placed behind the contact the seal found, never in the table.
    plate = resting(trimesh.creation.box([0.2, 0.2, 0.002]))
    config = dataclasses.replace(CONFIG, position_std=0.003, axis_std=0.0, n_samples=500)
    point, down = np.array([[0.0, 0.0, 0.002]]), np.array([[0.0, 0.0, -1.0]])
    rng = np.random.default_rng(0)
    assert grasp_qualities(plate, plate.center_mass, LIGHT, point, down, config, rng)[0] == 1.0


def test_gravity_is_what_the_grasp_holds_against():
    # 40 kg on a 250 N cup: held on the moon, not on earth.
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    heavy, moon = 40.0, 1.62
    on_earth = suction_quality(box, box.center_mass, heavy, NO_BENDING, np.random.default_rng(0), 9.81)
    assert on_earth.quality == 0.0
    on_the_moon = suction_quality(box, box.center_mass, heavy, NO_BENDING, np.random.default_rng(0), moon)
    assert on_the_moon.quality == 1.0


def test_without_a_gravity_argument_the_grasp_holds_against_the_models_gravity():
    # A cup that pulls 250 N holds 25.5 kg on earth: masses just either side of that, with no
    # perturbation of the mass, decide every function called without ``gravity``.
    g = ToppleConfig().gravity
    exact = dataclasses.replace(NO_BENDING, mass_std_fraction=0.0, axis_std=0.0, position_std=0.0)
    light, heavy = np.array([0.99, 1.01]) * exact.vacuum_force / g
    contact, down = np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.0, -1.0])
    held = wrench_resisted(np.tile(contact, (2, 1)), np.tile(down, (2, 1)), contact, np.array([light, heavy]), np.full(2, 0.5), exact)
    np.testing.assert_array_equal(held, [True, False])
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    for mass, expected in ((light, 1.0), (heavy, 0.0)):
        rng = np.random.default_rng(0)
        assert grasp_qualities(box, box.center_mass, mass, contact[None], down[None], exact, rng)[0] == expected
        assert suction_quality(box, box.center_mass, mass, exact, np.random.default_rng(0)).quality == expected


# ----------------------------------------------------------------------------- seal


def test_seal_deflection_limit_on_a_tilted_approach():
    # On a flat face the ring's hit depths spread by 2 r tan(tilt): the seal holds
    # just under max_deflection and breaks just over it.
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    limit = np.arctan(CONFIG.max_deflection / (2 * CONFIG.cup_radius))
    tilts = np.array([0.0, 0.9 * limit, 1.1 * limit, 3 * limit])
    axes = np.column_stack([np.sin(tilts), np.zeros(4), -np.cos(tilts)])
    points = np.tile([0.0, 0.0, 0.05], (4, 1))
    sealed, contacts = seal_contacts(box, points, axes, CONFIG)
    np.testing.assert_array_equal(sealed, [True, True, False, False])
    np.testing.assert_allclose(contacts[:, 2], 0.05, atol=1e-9)


def test_seal_needs_the_whole_ring_on_the_surface():
    box = resting(trimesh.creation.box([0.1, 0.1, 0.05]))
    axis = np.array([[0.0, 0.0, -1.0]] * 2)
    inside = 0.05 - CONFIG.cup_radius - 0.002
    outside = 0.05 - CONFIG.cup_radius + 0.002  # part of the ring hangs over the edge
    sealed, _ = seal_contacts(box, np.array([[inside, 0, 0.05], [outside, 0, 0.05]]), axis, CONFIG)
    np.testing.assert_array_equal(sealed, [True, False])


def test_seal_fails_over_a_hole_inside_the_ring():
    # A washer: the ring lands flat on it all round, but the vacuum leaks through the hole.
    washer = resting(trimesh.creation.annulus(r_min=0.006, r_max=0.05, height=0.01, sections=64))
    axis = np.array([[0.0, 0.0, -1.0]] * 2)
    points = np.array([[0.0, 0.0, 0.01], [0.03, 0.0, 0.01]])  # over the hole; beside it
    small = dataclasses.replace(CONFIG, cup_radius=0.01)
    sealed, contacts = seal_contacts(washer, points, axis, small)
    np.testing.assert_array_equal(sealed, [False, True])
    assert np.isnan(contacts[0]).all()


def test_a_bump_under_the_centre_exactly_max_deflection_high_still_seals():
    # A flat top with a small bump under the cup's centre, the ring all round it on the top:
    # the hits' spread along the approach is the bump's height d.  Every length is a power of
    # two, so the depths are exact and the limit (iii), spread <= max_deflection, is met at equality.
    d = 2.0**-8
    top = trimesh.creation.box([0.125, 0.125, 0.0625], trimesh.transformations.translation_matrix([0, 0, 0.03125]))
    bump = trimesh.creation.box([2.0**-7, 2.0**-7, 2 * d], trimesh.transformations.translation_matrix([0, 0, 0.0625]))
    mesh = trimesh.util.concatenate([top, bump])
    config = dataclasses.replace(CONFIG, cup_radius=2.0**-6)
    point, down = np.array([[0.0, 0.0, 0.0625]]), np.array([[0.0, 0.0, -1.0]])
    sealed = [seal_contacts(mesh, point, down, dataclasses.replace(config, max_deflection=m))[0][0] for m in (d, d - 2.0**-16)]
    assert sealed == [True, False]


def test_seal_strain_limit_on_a_curved_surface():
    # Ring across a cylinder of radius R: strain and deflection grow as R shrinks.
    loose = dataclasses.replace(CONFIG, max_deflection=1.0)  # isolate the strain check
    axis = np.array([[0.0, 0.0, -1.0]])
    results = []
    for radius in (0.2, 0.016):
        cylinder = lying(trimesh.creation.cylinder(radius=radius, height=0.2, sections=256))
        top = np.array([[0.0, 0.0, cylinder.bounds[1, 2]]])
        results.append(seal_contacts(cylinder, top, axis, loose)[0][0])
    assert results == [True, False]


# ----------------------------------------------------------------------------- wrench


def test_bending_limit_bounds_the_lever_arm_of_gravity():
    # Vertical approach, centre of mass d beside the contact: torque m g d about a tangent.
    config = dataclasses.replace(CONFIG, elastic_limit=0.1)
    m, g = 0.5, 9.81
    lever = config.elastic_limit / (m * g)
    d = np.array([0.5, 0.99, 1.01, 2.0]) * lever
    contacts = np.column_stack([d, np.zeros(4), np.full(4, 0.05)])
    axes = np.tile([0.0, 0.0, -1.0], (4, 1))
    held = wrench_resisted(contacts, axes, np.array([0.0, 0.0, 0.02]), np.full(4, m), np.full(4, 0.5), config, g)
    np.testing.assert_array_equal(held, [True, True, False, False])


def test_friction_on_a_tilted_approach_uses_the_vacuum_augmented_normal_force():
    # Centre of mass at the contact (no torque); approach tilted by theta:
    # tangential load m g sin(theta) <= mu (V - m g cos(theta)).
    config = dataclasses.replace(CONFIG, vacuum_force=10.0, friction=0.5)
    g, theta = 9.81, np.radians(40)
    critical = config.vacuum_force / (g * (np.sin(theta) / config.friction + np.cos(theta)))
    mass = critical * np.array([0.9, 1.1])
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    contact = np.array([0.0, 0.0, 0.05])
    held = wrench_resisted(np.tile(contact, (2, 1)), np.tile(axis, (2, 1)), contact, mass, np.full(2, 0.5), config, g)
    np.testing.assert_array_equal(held, [True, False])


def test_friction_limit_follows_a_normal_force_below_one_newton():
    # The same balance when the vacuum barely outpulls the weight: the normal force is a
    # fraction of a newton, and the friction limit is mu times that fraction.
    g, theta, m, mu = 9.81, np.radians(40), 0.1, 0.9
    critical = m * g * (np.sin(theta) / mu + np.cos(theta))  # N of vacuum
    assert critical - m * g * np.cos(theta) < 1.0
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    contact = np.array([0.0, 0.0, 0.05])
    held = [
        wrench_resisted(contact, axis, contact, np.array(m), np.array(mu), dataclasses.replace(CONFIG, vacuum_force=v), g).item()
        for v in (0.9 * critical, 1.1 * critical)
    ]
    assert held == [False, True]


def test_bending_limit_reads_only_the_torque_about_the_tangent_axes():
    # Tilted approach, centre of mass y beside the contact: gravity's torque (y m g, 0, 0) splits
    # into tau_z = y m g sin(theta) about the approach and y m g cos(theta) about a tangent.
    theta, g, m, y = np.radians(30), 9.81, 0.2, 0.01
    bending = y * m * g * np.cos(theta)
    config = dataclasses.replace(CONFIG, torsional_friction=1.0, friction=1.0, vacuum_force=1e3)
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    held = [
        wrench_resisted(np.zeros(3), axis, np.array([0.0, y, 0.0]), np.array(m), np.array(1.0),
                        dataclasses.replace(config, elastic_limit=limit), g).item()
        for limit in (0.9 * bending, 1.1 * bending)
    ]
    assert held == [False, True]


def test_vacuum_force_limits_the_pull():
    config = dataclasses.replace(CONFIG, vacuum_force=5.0)
    g = 9.81
    mass = np.array([0.99, 1.01]) * config.vacuum_force / g
    contact = np.array([0.0, 0.0, 0.05])
    held = wrench_resisted(
        np.tile(contact, (2, 1)), np.tile([0.0, 0.0, -1.0], (2, 1)), contact, mass, np.full(2, 0.5), config, g
    )
    np.testing.assert_array_equal(held, [True, False])


def test_the_wrench_limits_hold_at_equality():
    # Dex-Net's constraints are closed: f_z >= -V and |tau_t| <= M_b.  With powers of two the
    # wrench is exact: 1 kg at g = 8 pulls 8 N; its centre of mass 0.25 m beside a vertical
    # contact bends the cup by 2 N m.  A vacuum of exactly 8 N (f_N = 0) and a limit of exactly
    # 2 N m hold; a hair less does not.
    g, m, tiny = 8.0, np.array(1.0), 2.0**-10
    down, contact = np.array([0.0, 0.0, -1.0]), np.zeros(3)
    pull = [wrench_resisted(contact, down, contact, m, np.array(0.5), dataclasses.replace(CONFIG, vacuum_force=v), g).item()
            for v in (8.0, 8.0 - tiny)]
    assert pull == [True, False]
    beside = np.array([0.25, 0.0, 0.0])
    bend = [wrench_resisted(contact, down, beside, m, np.array(0.5), dataclasses.replace(CONFIG, elastic_limit=b), g).item()
            for b in (2.0, 2.0 - tiny)]
    assert bend == [True, False]


def test_torsional_friction_limits_twist_about_the_approach():
    # Tilted approach with the centre of mass off to the side in y: gravity twists the cup.
    config = dataclasses.replace(CONFIG, elastic_limit=1e3)
    theta, g, m, mu = np.radians(30), 9.81, 0.2, 0.5
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    contact = np.zeros(3)
    normal = config.vacuum_force - m * g * np.cos(theta)
    f_t = m * g * np.sin(theta)
    # tau_z = m g sin(theta) * y; the elliptic limit gives the largest |y|.
    y_max = config.torsional_friction * np.sqrt((mu * normal) ** 2 - f_t**2) / (m * g * np.sin(theta))
    coms = np.array([[0.0, 0.9 * y_max, 0.0], [0.0, 1.1 * y_max, 0.0]])
    held = [
        wrench_resisted(contact, axis, com, np.array(m), np.array(mu), config, g).item() for com in coms
    ]
    assert held == [True, False]


def test_without_torsional_friction_the_ring_still_limits_sliding():
    # r_t = 0: the limit surface collapses to |f_t| <= mu f_N with no twist at all.  Centre of
    # mass at the contact (no torque), approach tilted by theta: the friction balance of
    # test_friction_on_a_tilted_approach_... decides, r_t or no r_t; and any twist slips.
    config = dataclasses.replace(CONFIG, vacuum_force=10.0, friction=0.5, torsional_friction=0.0)
    g, theta = 9.81, np.radians(40)
    critical = config.vacuum_force / (g * (np.sin(theta) / config.friction + np.cos(theta)))
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    contact = np.zeros(3)
    held = [
        wrench_resisted(contact, axis, com, np.array(critical * f), np.array(0.5), config, g).item()
        for com, f in (([0.0, 0.0, 0.0], 0.9), ([0.0, 0.0, 0.0], 1.1), ([0.0, 0.001, 0.0], 0.1))
    ]
    assert held == [True, False, False]
    assert not wrench_resisted(contact, axis, contact, np.array(0.1), np.array(0.0), config).item()


def test_sliding_and_twisting_share_one_elliptic_limit():
    # Tilted approach, centre of mass y beside the contact: a sliding load f_t = m g sin(theta)
    # and a twist tau_z = f_t y.  The vacuum is set so that f_t uses 0.6 of mu f_N; the ellipse
    # (f_t / mu f_N)^2 + (tau_z / r_t mu f_N)^2 <= 1 then leaves a twist of 0.8 r_t mu f_N, i.e.
    # y <= 0.8 / 0.6 r_t, where each limit alone (its bounding box) would allow y up to r_t / 0.6.
    theta, g, m, mu = np.radians(30), 9.81, 0.2, 0.5
    f_t = m * g * np.sin(theta)
    vacuum = m * g * np.cos(theta) + f_t / (0.6 * mu)
    config = dataclasses.replace(CONFIG, vacuum_force=vacuum, elastic_limit=1e3)
    r_t = config.torsional_friction
    y_max = 0.8 / 0.6 * r_t
    assert 1.1 * y_max < r_t / 0.6  # the outer case is inside the box, outside the ellipse
    axis = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    held = [
        wrench_resisted(np.zeros(3), axis, np.array([0.0, f * y_max, 0.0]), np.array(m), np.array(mu), config, g).item()
        for f in (0.9, 1.1)
    ]
    assert held == [True, False]


def test_zero_friction_cannot_hold_a_tilted_grasp():
    axis = np.array([np.sin(0.3), 0.0, -np.cos(0.3)])
    held = wrench_resisted(np.zeros(3), axis, np.zeros(3), np.array(0.1), np.array(0.0), CONFIG)
    assert not held


# ----------------------------------------------------------------------------- gripper and table


def test_gripper_body_near_the_table_collides_when_tilted():
    # A grasp 5 mm above the table: vertical is clear, 45 degrees swings the body's rim under the table.
    points = np.array([[0.0, 0.0, 0.005], [0.0, 0.0, 0.005], [0.0, 0.0, 0.05]])
    tilt = np.radians(45)
    axes = np.array([[0, 0, -1.0], [np.sin(tilt), 0, -np.cos(tilt)], [np.sin(tilt), 0, -np.cos(tilt)]])
    np.testing.assert_array_equal(table_collisions(points, axes, CONFIG), [False, True, False])


def test_gripper_body_touching_the_table_is_clear():
    # A horizontal body's lowest line is its axis lowered by the radius: with the axis exactly
    # one radius above the table it touches (clear, nothing dips below z = 0); lower, it collides.
    config = dataclasses.replace(CONFIG, gripper_radius=2.0**-6)
    points = np.array([[0.0, 0.0, 2.0**-6], [0.0, 0.0, 2.0**-6 - 2.0**-16]])
    axes = np.tile([1.0, 0.0, 0.0], (2, 1))
    np.testing.assert_array_equal(table_collisions(points, axes, config), [False, True])


def test_gripper_body_must_clear_the_table_on_a_low_slope():
    # A wedge whose only graspable face is a 40 degree ramp starting at the table.  The
    # default body clears the table; a 4 cm radius body tilted 40 degrees dips its rim
    # under it (the object itself lies wholly below the ramp's plane, so fcl sees nothing).
    run, rise = 0.036, 0.036 * np.tan(np.radians(40))
    section = [[0.0, 0.0], [run, 0.0], [run, rise]]
    wedge = trimesh.convex.convex_hull(np.array([[x, y, z] for x, z in section for y in (-0.05, 0.05)]))
    assert quality(wedge, mass=0.01).quality >= 0.8
    wide = dataclasses.replace(NO_BENDING, gripper_radius=0.04)
    assert quality(wedge, mass=0.01, config=wide).quality <= 0.1
