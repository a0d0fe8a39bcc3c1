"""The toppling model: analytic cases and invariants (thesis 4.2, docs/MODEL.md 7)."""

import itertools
import re
import warnings
from dataclasses import replace

import numpy as np
import pytest
from shapes import THESIS, boot_object, pose_with_down, random_object, standing_box

from pipeline.api import evaluate
from pipeline.model import topple
from pipeline.model.config import Config
from pipeline.model.poses import stable_poses
from pipeline.model.reference import draw_of, reference_trial, scene_from_pose
from pipeline.model.rng import stream
from pipeline.model.topple import sample_noise
from schema.frames import transform_points
from schema.vocabulary import OUTCOME_NOT_EVALUATED, STATUS_OK

MU_TABLE = THESIS.topple.mu_table_mean


@pytest.fixture(scope="module")
def box():
    return standing_box()


def _side_pushes(heights, y=0.0):
    """Horizontal pushes along -x on the box's +x face (width 0.05 along x)."""
    return np.column_stack([np.full(len(heights), 0.025), np.full(len(heights), y), heights])


@pytest.mark.parametrize("variant", ["baseline", "rotations"])
def test_box_topples_above_friction_height_and_slides_below(box, variant):
    obj, pose_set, standing = box
    threshold = 0.05 / (2 * MU_TABLE)  # F* = m g w / 2h <= mu_T m g
    heights = threshold * np.array([0.5, 0.9, 0.98, 1.02, 1.1, 2.0])
    result = evaluate(obj, pose_set, standing, points=_side_pushes(heights), variant=variant, config=THESIS)
    assert np.array_equal(result.table.p_topple, [0, 0, 0, 1, 1, 1])
    # It rolls onto the -x face, the one it was pushed towards.
    assert np.all(result.table.next_pose[3:, pose_with_down(pose_set, [-1, 0, 0])] == 1)
    # The required force is m g w / (2 h).
    expected = obj.mass * 9.81 * 0.05 / (2 * heights[3:])
    assert np.allclose(result.table.mean_force[3:], expected)


def test_push_pointing_away_never_topples(box):
    obj, pose_set, standing = box
    heights = np.linspace(0.03, 0.14, 8)
    away = np.tile([1.0, 0.0, 0.0], (8, 1))  # along the outward normal of the +x face
    for variant in ("baseline", "robust"):
        result = evaluate(obj, pose_set, standing, points=_side_pushes(heights), directions=away, variant=variant, config=THESIS)
        assert np.all(result.table.p_topple == 0)


def test_push_outside_friction_cone_slips(box):
    obj, pose_set, standing = box
    steep = np.array([[-1.0, 0.0, -1.5]])  # 56 degrees from the inward normal; tan > mu_f = 0.98
    result = evaluate(obj, pose_set, standing, points=_side_pushes([0.14]), directions=steep, variant="baseline", config=THESIS)
    assert result.table.p_topple[0] == 0


def test_baseline_ignores_planar_rotation_and_rotations_variant_does_not(box):
    obj, pose_set, standing = box
    # Just above the friction height, pushed near the face's end: a large torque about z.
    points = _side_pushes([0.07, 0.07], y=0.0)
    points[1, 1] = 0.039
    baseline = evaluate(obj, pose_set, standing, points=points, variant="baseline", config=THESIS).table.p_topple
    rotations = evaluate(obj, pose_set, standing, points=points, variant="rotations", config=THESIS).table.p_topple
    assert np.array_equal(baseline, [1, 1])
    assert np.array_equal(rotations, [1, 0])


def test_blocked_topple_returns_to_start_pose():
    obj = boot_object()
    pose_set = stable_poses(obj)
    standing = pose_with_down(pose_set, [0, 0, -1])
    pose = pose_set.poses[standing]
    blocked_edge = int(np.flatnonzero(pose.edge_blocked)[0])
    # Push the block's -x face towards +x, high up: it tips towards the toe.
    push = transform_points(pose.transform, np.array([[0.0, 0.02, 0.09]]))
    result = evaluate(obj, pose_set, standing, points=push, variant="baseline", config=THESIS)
    assert result.table.outcomes[0, 0] == blocked_edge
    assert result.table.p_topple[0] == 0 and result.table.next_pose[0, standing] == 1


@pytest.fixture(scope="module")
def random_table():
    # Pose 4 of random object 1 stands on end: many pushes topple it (lying flat, none do).
    obj = random_object(1)
    pose_set = stable_poses(obj)
    return obj, pose_set, evaluate(obj, pose_set, 4, n_contacts=150, n_trials=40, seed=3)


def test_probabilities_sum_to_one_and_statuses_gate_evaluation(random_table):
    _, pose_set, result = random_table
    table, status = result.table, result.actions.status
    ok = status == STATUS_OK
    assert ok.sum() > 20 and (~ok).sum() > 0
    assert np.allclose(table.next_pose[ok].sum(axis=1), 1.0)
    assert np.all(table.next_pose[ok] >= 0)
    assert np.all(np.isnan(table.next_pose[~ok])) and np.all(np.isnan(table.p_topple[~ok]))
    assert np.all(table.outcomes[~ok] == OUTCOME_NOT_EVALUATED) and np.all(table.outcomes[ok] >= -1)
    assert np.allclose(table.p_topple[ok], 1 - table.next_pose[ok, 4])
    assert table.p_topple[ok].max() > 0, "some push should topple a random object"
    assert table.next_pose.shape == (151, len(pose_set.poses))


def test_same_seed_same_result_different_seed_differs(random_table):
    obj, pose_set, first = random_table
    again = evaluate(obj, pose_set, 4, n_contacts=150, n_trials=40, seed=3)
    other = evaluate(obj, pose_set, 4, n_contacts=150, n_trials=40, seed=4)
    assert np.array_equal(first.table.outcomes, again.table.outcomes)
    assert np.array_equal(first.actions.points, again.actions.points)
    assert not np.array_equal(first.table.outcomes, other.table.outcomes)


def test_tile_size_never_changes_a_result(random_table, monkeypatch):
    # The engine runs its conditions over row tiles sized for speed; every operation is
    # row-wise, so many small, uneven tiles must give the very same table as the default's few.
    obj, pose_set, first = random_table
    monkeypatch.setattr(topple, "TILE_ELEMENTS", 97)
    assert len(topple._row_tiles(40 * 100, 4)) > 100, "97 entries split a block into many tiles"
    tiled = evaluate(obj, pose_set, 4, n_contacts=150, n_trials=40, seed=3)
    assert np.array_equal(first.table.outcomes, tiled.table.outcomes)
    assert np.array_equal(first.table.mean_force, tiled.table.mean_force, equal_nan=True)
    assert np.array_equal(first.table.next_pose, tiled.table.next_pose, equal_nan=True)
    assert (first.table.outcomes >= 0).sum() > 100, "the comparison needs trials that topple"


def test_row_tiles_are_the_fewest_nearly_equal_ranges_within_the_budget():
    """``_row_tiles`` covers range(n) with ceil(n per_row / TILE_ELEMENTS) contiguous, disjoint ranges
    of nearly equal size (one empty range when n = 0), never one of fewer than min(n, 2) rows."""
    for n in (0, 1, 2, 3, 5, 97, 1000, 4000):
        for per_row in (1, 7, 65536, 10**6):
            tiles = topple._row_tiles(n, per_row)
            sizes = [t.stop - t.start for t in tiles]
            assert tiles[0].start == 0 and tiles[-1].stop == n, (n, per_row)
            assert all(a.stop == b.start for a, b in itertools.pairwise(tiles)), (n, per_row)
            assert max(sizes) - min(sizes) <= 1 and min(sizes) >= min(n, 2), (n, per_row, sizes)
            wanted = -(-n * per_row // topple.TILE_ELEMENTS)  # ceil: the fewest within the budget
            assert len(tiles) == max(1, min(wanted, n // 2)), (n, per_row)


def test_unit_rows_are_schema_units_bit_for_bit_zero_vectors_included():
    """``_unit_rows`` is ``schema.frames.unit`` without its masked division: the same bits for
    (..., 3) arrays of any vectors, and a zero vector stays zero (not NaN, no warning)."""
    from schema.frames import unit

    vectors = np.random.default_rng(2).normal(size=(4, 50, 3)) * np.logspace(-9, 3, 50)[:, None]
    np.testing.assert_array_equal(topple._unit_rows(vectors), unit(vectors))
    vectors[1, 7] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(topple._unit_rows(vectors), unit(vectors))
    assert np.all(topple._unit_rows(vectors)[1, 7] == 0.0)


def test_drop_probabilities_of_another_pose_set_are_refused(box):
    """A row is as wide as the pose set: ``evaluate_pose`` refuses probabilities that do not cover
    every pose a topple lands in (here one short of the highest) or are not one per pose (2-D),
    naming the pose, the highest pose it lands in and the shape given."""
    from pipeline.model.contacts import explicit_actions
    from pipeline.model.rng import stream as trials_stream

    obj, pose_set, standing = box
    pose = pose_set.poses[standing]
    actions = explicit_actions(obj, pose.transform, _side_pushes([0.1]), None)
    highest = int(max(pose.edge_final_pose.max(), pose.edge_onward_pose.max(), standing))
    assert highest >= 1
    for probabilities in (pose_set.probabilities[:highest], pose_set.probabilities[None]):
        message = rf"pose {standing} lands in poses up to {highest}, and {re.escape(str(probabilities.shape))} probabilities"
        with pytest.raises(ValueError, match=message):
            topple.evaluate_pose(obj, pose, probabilities, actions, THESIS.topple, trials_stream(0, "box", standing, "trials"))


def test_robust_estimate_converges_with_trials(box):
    obj, pose_set, standing = box
    # Near the friction height the outcome is genuinely uncertain under noise.
    points = _side_pushes([0.06, 0.07, 0.09])
    estimates = {
        trials: evaluate(obj, pose_set, standing, points=points, n_trials=trials, seed=7).table.p_topple
        for trials in (25, 400, 6400)
    }
    truth = estimates[6400]
    assert np.all((truth > 0.05) & (truth < 0.95))
    # Monte Carlo error shrinks like 1/sqrt(T): stay within 4 standard errors.
    for trials in (25, 400):
        bound = 4 * np.sqrt(truth * (1 - truth) / trials) + 4 * np.sqrt(truth * (1 - truth) / 6400)
        assert np.all(np.abs(estimates[trials] - truth) <= bound)
    assert np.abs(estimates[400] - truth).max() < 0.1


def test_noise_free_variants_run_one_trial(box):
    obj, pose_set, standing = box
    for variant, trials in (("baseline", 1), ("rotations", 1), ("robustness", 100), ("robust", 100)):
        result = evaluate(obj, pose_set, standing, points=_side_pushes([0.1]), variant=variant, config=THESIS)
        assert result.table.outcomes.shape == (1, trials)


def test_unknown_variant_is_rejected(box):
    obj, pose_set, standing = box
    with pytest.raises(ValueError, match="unknown variant"):
        evaluate(obj, pose_set, standing, points=_side_pushes([0.1]), variant="magic")


def test_mean_force_is_the_mean_over_the_trials_that_topple(box):
    # Under noise each trial needs its own force (contact height, direction and the
    # object's tilt change the torques); the table keeps their mean over toppling trials.
    obj, pose_set, standing = box
    config = THESIS  # the thesis's robust trial, the reference without corrections
    heights = [0.07, 0.1, 0.14]  # the lowest is near the friction height: only some trials topple
    # Then the other three faces, high up, so that every base edge is toppled over.
    points = np.vstack([_side_pushes(heights), [[-0.025, 0.0, 0.14], [0.0, 0.04, 0.14], [0.0, -0.04, 0.14]]])
    result = evaluate(obj, pose_set, standing, points=points, n_trials=60, seed=5, config=config)
    topple = config.topple
    noise = sample_noise(stream(5, obj.name, standing, "trials"), len(points), replace(topple, n_trials=60))
    scene = scene_from_pose(obj, pose_set.poses[standing], topple.gravity)
    assert set(result.table.outcomes.ravel()) >= {0, 1, 2, 3}
    for action in range(len(points)):
        toppled = result.table.outcomes[action] >= 0
        forces = []
        for trial in np.flatnonzero(toppled):
            draw = draw_of(result.actions, noise, action, trial)
            edge, force = reference_trial(scene, draw, True, topple.predicts_rotations, topple.ray_offset)
            assert edge == result.table.outcomes[action, trial]
            forces.append(force)
        assert len(forces) >= 10 and np.ptp(forces) > 0.01 * np.mean(forces), "the forces should vary over trials"
        assert result.table.mean_force[action] == pytest.approx(np.mean(forces), rel=1e-6)
    assert 0 < result.table.p_topple[0] < 1


def test_noise_draws_follow_the_configured_distributions():
    topple = replace(THESIS.topple, n_trials=200)  # mu_f 0.98 +- 0.2: clipping at 0 is negligible
    noise = sample_noise(np.random.default_rng(9), 50, topple)
    n = 50 * 200
    for field, mean, std in [
        (noise.mu_table, topple.mu_table_mean, topple.mu_table_std),
        (noise.mu_finger, topple.mu_finger_mean, topple.mu_finger_std),  # 4.9 std above 0: clipping is negligible
        (noise.rotation_angle, 0.0, topple.rotation_std),
    ]:
        assert field.shape == (50, 200)
        assert field.mean() == pytest.approx(mean, abs=4 * std / np.sqrt(n))
        assert field.std() == pytest.approx(std, rel=0.05)
    for field, std in [(noise.contact_offset, topple.contact_std), (noise.direction_offset, topple.direction_std)]:
        assert field.shape == (50, 200, 3)
        np.testing.assert_allclose(field.mean(axis=(0, 1)), 0.0, atol=4 * std / np.sqrt(n))
        np.testing.assert_allclose(field.std(axis=(0, 1)), std, rtol=0.05)  # isotropic
    assert noise.rotation_axis.shape == (50, 200, 3)
    np.testing.assert_allclose(np.linalg.norm(noise.rotation_axis, axis=-1), 1.0)
    np.testing.assert_allclose(noise.rotation_axis.mean(axis=(0, 1)), 0.0, atol=4 / np.sqrt(3 * n))  # uniform on the sphere

    # Finger friction cannot be negative: draws below 0 are clipped to exactly 0, and only those.
    slippery = sample_noise(np.random.default_rng(9), 50, replace(topple, mu_finger_mean=0.1, mu_finger_std=0.2))
    clipped = np.mean(slippery.mu_finger == 0.0)
    assert slippery.mu_finger.min() == 0.0 and clipped == pytest.approx(0.3085, abs=0.02)  # P(N(0.1, 0.2) < 0)
    assert np.median(slippery.mu_finger) == pytest.approx(0.1, abs=0.01)


@pytest.mark.parametrize("variant", ["baseline", "rotations"])
def test_noise_free_variants_draw_nothing(variant):
    topple = replace(Config().topple, variant=variant)
    rng = np.random.default_rng(1)
    noise = sample_noise(rng, 4, topple)
    assert rng.random() == np.random.default_rng(1).random(), "the stream is left untouched"
    np.testing.assert_array_equal(noise.mu_table, np.full((4, 1), topple.mu_table_mean))
    np.testing.assert_array_equal(noise.mu_finger, np.full((4, 1), topple.mu_finger_mean))
    np.testing.assert_array_equal(noise.contact_offset, np.zeros((4, 1, 3)))
    np.testing.assert_array_equal(noise.direction_offset, np.zeros((4, 1, 3)))
    np.testing.assert_array_equal(noise.rotation_angle, np.zeros((4, 1)))
    assert noise.rotation_axis.shape == (4, 1, 3)
    np.testing.assert_allclose(np.linalg.norm(noise.rotation_axis, axis=-1), 1.0)


def test_pushes_that_never_topple_give_nan_force_without_warnings(box):
    # No toppling trial: mean_force is NaN (not 0, not a RuntimeWarning in the job's log).
    obj, pose_set, standing = box
    away = np.tile([1.0, 0.0, 0.0], (2, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        table = evaluate(obj, pose_set, standing, points=_side_pushes([0.05, 0.14]), directions=away, n_trials=20).table
        counted = evaluate(obj, pose_set, standing, points=_side_pushes([0.05, 0.14]), directions=away, n_trials=20,
                           variant="robust").table
    assert np.all(table.outcomes < 0) and np.all(np.isnan(table.mean_force))
    # The thesis's rows are the trials' counts; the default's maps read the pose's candidates too, so
    # they need not map a push no trial topples to exactly 0 (docs/MODEL.md C.19).
    assert np.all(counted.p_topple == 0) and np.all(np.isnan(counted.mean_force))
    assert table.outcomes.dtype == np.int16  # the HDF5 layout's dtype (schema/hdf5.py)


# ---------------------------------------------------------------- the thesis's conditions at their boundaries (found by mutation testing)
SQUARE = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
"""m, a 1 x 1 square base, counter-clockwise seen from above; edge 2 runs from (0.5, 0.5) to
(-0.5, 0.5): e = (-1, 0, 0), outward +y.  Every quantity below is a small binary fraction, so
the conditions' arithmetic on it is exact and a threshold can be met exactly."""


def _square_trial(center_mass, contact, normal, push, mu_table, mu_finger, variant="rotations", corrections="none"):
    """One noise-free trial on the square base (unit mass and gravity) through the engine's
    ``trial_outcomes`` and through the scalar ``reference_trial``: ((edge, force), (edge, force))."""
    from pipeline.model.edges import base_edges, edge_geometry
    from pipeline.model.reference import Scene, TrialDraw

    config = replace(Config().topple, variant=variant, corrections=corrections, gravity=1.0)
    edges = base_edges(SQUARE)
    one = lambda v: np.array([v], float)  # (1, 3) or (1,)
    trials = topple.Trials(one(contact), one(normal), one(push), one(mu_table), one(mu_finger), np.ones(1, bool), np.zeros(1))
    edge, force = topple.trial_outcomes(trials, edge_geometry(edges, np.asarray(center_mass, float)), 1.0, config)
    vec = lambda v: tuple(float(x) for x in v)
    scene = Scene([], [], vec(center_mass), 1.0, 1.0, [(vec(y0), vec(y1)) for y0, y1 in edges])
    draw = TrialDraw(vec(contact), vec(normal), vec(push), mu_table, mu_finger, (0.0,) * 3, (0.0,) * 3, (0.0, 0.0, 1.0), 0.0)
    reference = reference_trial(scene, draw, False, config.predicts_rotations, 0.0, config.applied_corrections,
                                config.max_finger_force)
    return (int(edge[0]), float(force[0])), reference


@pytest.mark.parametrize("variant", ["baseline", "rotations"])
def test_the_thesis_table_check_is_inclusive_at_the_closed_form_threshold(variant):
    """(7.9) admits |f_xy| <= mu_T F_n, equality included.  Pushed horizontally on the face 1 m
    from edge 2, the unit-weight body with its centre of mass d = 0.5 m inside that edge needs
    F* = d / h (7.5), and the table holds mu_T: at mu_T = 0.5 the threshold is h* = d / mu_T = 1 m
    exactly (no moment about the vertical: the push is on the centre line)."""
    for height, toppled in ((1.0 - 2.0**-10, False), (1.0, True), (1.0 + 2.0**-10, True)):
        engine, reference = _square_trial([0.0, 0.0, 1.0], [0.0, -0.5, height], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], 0.5, 0.98,
                                          variant)
        assert engine == reference, height
        assert engine == ((2, 0.5 / height) if toppled else (-1, np.inf)), height


def test_a_frictionless_table_holds_nothing_in_the_thesis_model():
    """(7.9) passes only if mu_T > 0 (a draw at or below zero holds nothing, exactly).  Pushed
    straight down on an overhang 0.25 m beyond edge 2, the body needs F* = m g d / 0.25 = 2 N and
    puts no horizontal force on the table, so the friction limit alone would pass it at mu_T = 0."""
    down = ([0.0, 0.0, 1.0], [0.0, 0.75, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
    engine, reference = _square_trial(*down, 0.5, 0.98)
    assert engine == reference == (2, 2.0)
    for mu_table in (0.0, -0.1):
        engine, reference = _square_trial(*down, mu_table, 0.98)
        assert engine == reference == (-1, np.inf), mu_table


def test_an_edge_under_the_centre_of_mass_needs_no_force_and_warns_nothing():
    """With the centre of mass right above edge 2's line (d = 0, apex angle 0) the thesis's
    F* = m g d / tau (7.5) is 0: the push tips the body over that edge at no force, as the reference
    says, without a division warning (the friction check divides m g by F*).  A finger pushes
    (C.1: 0 < F*), so with ``force_limit`` nothing tips.  The push is along the inward normal,
    so even a frictionless finger's cone holds it (tan 0 <= 0 at the start and at the apex)."""
    on_edge = ([0.0, 0.5, 1.0], [0.0, -0.5, 1.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], 0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for mu_finger in (0.0, 0.98):
            engine, reference = _square_trial(*on_edge, mu_finger)
            assert engine == reference == (2, 0.0), mu_finger
        engine, reference = _square_trial(*on_edge, 0.98, variant="corrected", corrections="force_limit")
        assert engine == reference == (-1, np.inf)
        # A frictionless table holds nothing, even the push that needs no force.
        engine, reference = _square_trial(*on_edge[:4], 0.0, 0.98)
    assert engine == reference == (-1, np.inf)
    # Pushed a little off the normal, the frictionless finger's cone holds nothing.
    engine, reference = _square_trial(*on_edge[:3], [0.0, 0.8, 0.6], 0.5, 0.0)
    assert engine == reference == (-1, np.inf)
