# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""schema.neighbourhood: the mean P(topple) around a candidate push, and /plan reporting it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schema.neighbourhood import MAX_ANGLE, RADIUS, Neighbours, neighbour_mean, neighbour_pairs, neighbours
from tests.test_service import client, dataset, planar_transform, stored_transform, tables, xyz  # noqa: F401 (fixtures)


def test_neighbours_are_near_in_contact_and_direction_and_ok():
    x = np.array([1.0, 0.0, 0.0])
    points = np.array([[0, 0, 0], [0.015, 0, 0], [0.03, 0, 0], [0.005, 0, 0], [0.001, 0, 0]], dtype=float)
    turned = np.array([math.cos(0.6), math.sin(0.6), 0.0])  # 0.6 rad > MAX_ANGLE away
    directions = np.array([x, x, x, turned, x])
    values = np.array([0.9, 0.3, 0.0, 0.0, np.nan])  # the last is not ok: nobody's neighbour
    mean, count = neighbour_mean(points, directions, values)
    # 0: itself and 1 (15 mm); not 2 (30 mm), 3 (turned), 4 (not ok).
    assert count[0] == 2 and mean[0] == pytest.approx((0.9 + 0.3) / 2)
    assert count[2] == 2 and mean[2] == pytest.approx(0.15), "30 mm from 0, but 15 mm from 1"
    assert np.isnan(mean[4]) and count[4] == 0
    one, n = neighbour_mean(points, directions, values, rows=[1])
    assert one[0] == pytest.approx(mean[1]) and n[0] == count[1], "one row is that row of the whole"
    wider, _ = neighbour_mean(points, directions, values, radius=0.05, max_angle=1.0)
    assert wider[0] == pytest.approx(np.mean([0.9, 0.3, 0.0, 0.0]))
    assert RADIUS == 0.02 and MAX_ANGLE == 0.5
    # One candidate's neighbourhood, ok or not (what a failed push rules out): 0, 1 and 4.
    assert neighbours(points, directions, 0).tolist() == [True, True, False, False, True]
    assert neighbours(points, directions, 3).tolist() == [False, False, False, True, False], "only itself: turned"
    assert neighbours(points, directions, 0, radius=0.0).tolist() == [True, False, False, False, False]


def test_plan_reports_the_mean_p_topple_around_its_push(client, tables):
    rng = np.random.default_rng(3)
    checked = 0
    for (object_id, pose) in tables["poses"]:
        observed = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.3, 0.3, 2)) @ stored_transform(
            tables, object_id, pose)
        body = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "policy": "greedy"}).json()
        if body["action"] is None:
            assert body["p_topple_neighbourhood"] is None
            continue
        # By hand from the analysts' tables: this pose's ok candidates within 2 cm and 0.5 rad.
        rows = [r for (o, p, _), r in tables["actions"].items() if o == object_id and p == pose and r["status"] == "ok"]
        chosen = tables["actions"][(object_id, pose, body["action"])]
        near = [r["p_topple"] for r in rows
                if np.linalg.norm(xyz(r, "point") - xyz(chosen, "point")) <= RADIUS + 1e-6
                and xyz(r, "direction") @ xyz(chosen, "direction") >= math.cos(MAX_ANGLE) - 1e-6]
        assert body["p_topple_neighbourhood"] == pytest.approx(np.mean(near), abs=1e-6)
        assert f"({body['p_topple_neighbourhood']:.3g} around it)" in body["reason"]
        checked += 1
    assert checked >= 5


def test_boundaries_are_neighbours_within_rounding_and_a_hair_beyond_is_not():
    # Exactly RADIUS apart and exactly MAX_ANGLE turned are neighbours though |a - b|^2 and the
    # cosine round either way; a micrometre or a microradian more is not.
    def heading(angle):
        return [math.cos(angle), math.sin(angle), 0.0]

    x = heading(0.3)  # 0.3 rad: the cosine at MAX_ANGLE rounds below cos(MAX_ANGLE), 0.1 m the distance above
    points = np.array([[0.1, 0.2, 0.0], [0.1 + RADIUS, 0.2, 0.0], [0.1 + RADIUS + 1e-6, 0.2, 0.0], [0.1, 0.2, 0.0],
                       [0.1, 0.2, 0.0]])
    directions = np.array([x, x, x, heading(0.3 + MAX_ANGLE), heading(0.3 + MAX_ANGLE + 1e-6)])
    assert neighbours(points, directions, 0).tolist() == [True, True, False, True, False]
    mean, count = neighbour_mean(points, directions, np.array([0.0, 0.3, 0.9, 0.6, 0.9]), rows=[0])
    assert count.tolist() == [3] and mean[0] == pytest.approx(0.3)


def test_a_candidate_is_its_own_neighbour_whatever_its_direction():
    # A degenerate (zero) direction has cosine 0 with itself: still its own neighbourhood.
    points, directions = np.zeros((2, 3)), np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert neighbours(points, directions, 0).tolist() == [True, False]
    mean, count = neighbour_mean(points, directions, np.array([0.25, 0.75]))
    assert count.tolist() == [1, 1] and mean.tolist() == [0.25, 0.75]


def test_k_values_per_candidate_average_column_by_column_and_need_all_finite():
    x = np.array([1.0, 0.0, 0.0])
    points, directions = np.zeros((3, 3)), np.array([x, x, x])
    values = np.array([[0.2, 1.0], [0.4, 3.0], [np.nan, 5.0]])  # the last row is not finite: nobody's neighbour
    mean, count = neighbour_mean(points, directions, values)
    assert mean.shape == (3, 2) and count.tolist() == [2, 2, 0]
    np.testing.assert_allclose(mean[:2], [[0.3, 2.0], [0.3, 2.0]])
    assert np.isnan(mean[2]).all()
    one, n = neighbour_mean(points, directions, values, rows=[1])
    assert one.shape == (1, 2) and n.tolist() == [2] and one[0].tolist() == mean[1].tolist()


def test_a_row_past_the_pool_averages_over_the_pool_and_itself_only():
    # Rows 0, 1: the pose's candidates; row 2: a probe (a logged push) at the same place, in no one's mean.
    x = np.array([1.0, 0.0, 0.0])
    points, directions = np.zeros((3, 3)), np.array([x, x, x])
    values = np.array([0.2, 0.4, 0.9])
    mean, count = neighbour_mean(points, directions, values, pool=2)
    assert count.tolist() == [2, 2, 3]
    np.testing.assert_allclose(mean, [0.3, 0.3, 0.5])
    probe, n = neighbour_mean(points, directions, values, rows=[2], pool=2)
    assert n.tolist() == [3] and probe[0] == pytest.approx(0.5)
    everyone, _ = neighbour_mean(points, directions, values)
    np.testing.assert_allclose(everyone, [0.5, 0.5, 0.5])


def test_neighbours_found_once_give_every_mean_bit_for_bit():
    """One pose's maps share ``neighbour_pairs``: each mean over them is the mean found from scratch,
    for any rows (in any order), a pool, k columns and narrower limits, and the pairs passed are the ones used."""
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.03, 0.03, (300, 3))
    directions = np.array([1.0, 0.0, 0.0]) + 0.4 * rng.normal(size=(300, 3))  # some within MAX_ANGLE, some not
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    values = rng.random((300, 2))
    values[rng.random(300) < 0.1] = np.nan
    near = neighbour_pairs(points, directions, pool=250)
    matrix = np.zeros((300, 300), dtype=bool)
    matrix[near.row, near.neighbour] = True
    assert matrix.diagonal().all() and not matrix[:, 250:][~np.eye(300, dtype=bool)[:, 250:]].any()
    assert np.all(np.diff(near.row * 300 + near.neighbour) > 0), "sorted by row, then by neighbour"
    rows = np.flatnonzero(np.isfinite(values[:, 0]))[::3]
    for kwargs in ({}, {"rows": rows}, {"rows": rows[::-1]}, {"rows": [7]}):
        shared = neighbour_mean(points, directions, values, pool=250, near=near, **kwargs)
        fresh = neighbour_mean(points, directions, values, pool=250, **kwargs)
        assert np.array_equal(shared[0], fresh[0], equal_nan=True) and np.array_equal(shared[1], fresh[1])
    narrow = near.narrower(0.01, 0.35)
    assert 0 < len(narrow.row) < len(near.row)
    shared = neighbour_mean(points, directions, values, 0.01, 0.35, pool=250, near=narrow)
    fresh = neighbour_mean(points, directions, values, 0.01, 0.35, pool=250)
    assert np.array_equal(shared[0], fresh[0], equal_nan=True) and np.array_equal(shared[1], fresh[1])
    with pytest.raises(ValueError, match="not within"):
        near.narrower(0.03, 0.35)
    with pytest.raises(ValueError, match="distinct"):
        neighbour_mean(points, directions, values, pool=250, near=near, rows=[3, 3])
    self_only = np.arange(300)
    alone, count = neighbour_mean(points, directions, values[:, 0],
                                  near=Neighbours(self_only, self_only, np.zeros(300), np.ones(300), 300, RADIUS, MAX_ANGLE))
    assert np.array_equal(alone, values[:, 0], equal_nan=True) and count.max() == 1, "the pairs given are the ones read"
    assert 3 < neighbour_mean(points, directions, values[:, 0], pool=250)[1].mean(), "the test needs real neighbourhoods"


def test_every_mean_is_summed_in_index_order_whatever_blas_threads_it_may_use():
    """A mean one rounding off crosses a threshold of the boosted map (MODEL.md C.19) now and then, so a
    table must not depend on how many threads a BLAS product splits its sums over: each neighbour is
    added in index order, as a plain loop adds them, and one or two BLAS threads give the same bits."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.02, 0.02, (1500, 3))  # dense: dozens of neighbours each
    directions = np.array([1.0, 0.0, 0.0]) + 0.3 * rng.normal(size=(1500, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    values = rng.random((1500, 3)) * 10.0 ** rng.integers(-8, 1, (1500, 3))  # magnitudes apart: order shows
    mean, count = neighbour_mean(points, directions, values)
    near = neighbour_pairs(points, directions)
    for row in (0, 1, 777, 1499):
        total = np.zeros(3)
        mine = near.neighbour[near.row == row]
        for j in mine:
            total = total + values[j]
        assert count[row] == len(mine) > 20 and np.array_equal(mean[row], total / count[row])
    for threads in (1, 2):
        with threadpoolctl.threadpool_limits(threads):
            again = neighbour_mean(points, directions, values)
            shared = neighbour_mean(points, directions, values, near=neighbour_pairs(points, directions))
        assert np.array_equal(again[0], mean) and np.array_equal(again[1], count)
        assert np.array_equal(shared[0], mean) and np.array_equal(shared[1], count)


def test_chosen_means_average_around_each_pose_s_own_candidates():
    from schema.neighbourhood import chosen_means
    from schema.vocabulary import NO_OP

    x, turned = [1.0, 0.0, 0.0], [math.cos(0.6), math.sin(0.6), 0.0]  # 0.6 rad > MAX_ANGLE apart
    # Pose 0: rows 0, 1 (10 mm, 0.6 rad apart); pose 1: rows 2, 3, 4 (row 4 30 mm away); pose 2: no candidates.
    points = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0, 0], [0.01, 0, 0], [0.04, 0, 0]], dtype=float)
    directions = np.array([x, turned, x, x, x])
    p_topple = np.array([0.2, 0.4, 0.6, np.nan, 1.0])
    chosen = np.array([[1, NO_OP], [0, 2], [NO_OP, NO_OP]])
    offsets = np.array([0, 2, 5, 5])
    means = chosen_means(offsets, points, directions, p_topple, chosen)
    assert means.shape == (3, 2) and np.isnan(means[0, 1]) and np.isnan(means[2]).all()
    np.testing.assert_allclose([means[0, 0], means[1, 0], means[1, 1]], [0.4, 0.6, 1.0])
    wider = chosen_means(offsets, points, directions, p_topple, chosen, radius=0.05)
    np.testing.assert_allclose([wider[0, 0], wider[1, 0]], [0.4, 0.8])
    turning = chosen_means(offsets, points, directions, p_topple, chosen, max_angle=0.7)
    np.testing.assert_allclose([turning[0, 0], turning[1, 0]], [0.3, 0.6])


def test_float32_candidates_have_the_neighbourhoods_and_means_of_their_float64_values():
    # The service holds float32 contacts, directions and P(topple), the pipeline float64 ones: both
    # must find the same neighbours and the same mean, computed in float64.
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.03, 0.03, (60, 3)).astype(np.float32)
    directions = rng.normal(size=(60, 3))
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)
    directions[:20] = directions[0]  # enough neighbours that the float32 and float64 sums differ
    p_topple = rng.random(60).astype(np.float32)
    wide = [a.astype(np.float64) for a in (points, directions, p_topple)]
    mean, count = neighbour_mean(points, directions, p_topple)
    expected, expected_count = neighbour_mean(*wide)
    assert mean.dtype == np.float64 and mean.tolist() == expected.tolist() and count.tolist() == expected_count.tolist()
    assert (count > 1).sum() >= 10
    # Half a metre from the origin, |a|^2 + |b|^2 - 2 a.b loses ~1e-7 m^2 in float32: a ring of
    # contacts within 2 um of RADIUS around the first must be split as in float64.
    ring = rng.normal(size=(40, 3))
    ring = 0.02 * ring / np.linalg.norm(ring, axis=1, keepdims=True) * (1 + np.linspace(-1e-4, 1e-4, 40))[:, None]
    points = (np.array([0.5, 0.4, 0.3]) + np.vstack([np.zeros(3), ring])).astype(np.float32)
    directions = np.tile(np.float32([0.0, 0.0, 1.0]), (41, 1))
    near = neighbours(points, directions, 0)
    assert near.tolist() == neighbours(points.astype(np.float64), directions.astype(np.float64), 0).tolist()
    assert 5 <= near.sum() <= 36, "the ring straddles the limit"
    pairs = neighbour_pairs(points, directions)  # the KD-tree's path, as the pipeline calls it, in float64 too
    assert pairs.neighbour[pairs.row == 0].tolist() == np.flatnonzero(near).tolist()
    values = np.linspace(0.0, 1.0, 41, dtype=np.float32)
    _, count = neighbour_mean(points, directions, values, rows=[0])
    _, expected_count = neighbour_mean(points.astype(np.float64), directions.astype(np.float64), values.astype(np.float64), rows=[0])
    assert count.tolist() == expected_count.tolist() == [near.sum()]


@pytest.mark.parametrize("pool", [None, 150])
def test_the_kd_tree_finds_the_pairs_brute_force_finds_bit_for_bit(monkeypatch, pool):
    """Every row's neighbourhood comes from scipy's KD-tree, a few rows' by brute force, and the service's
    install (no scipy) brute-forces every row: all three must agree pair for pair, to the bit, with contacts
    strewn about the limit, repeated contacts, a NaN contact and a zero direction among them."""
    from schema import neighbourhood

    rng = np.random.default_rng(11)
    centre = rng.uniform(-0.05, 0.05, (40, 3))
    offsets = rng.normal(size=(200, 3))
    offsets *= (RADIUS * (1 + rng.uniform(-1e-6, 1e-6, 200)) / np.linalg.norm(offsets, axis=1))[:, None]
    points = np.vstack([centre, centre[rng.integers(0, 40, 200)] + offsets, centre[:5]])  # 245: on the limit, repeated
    points[7] = np.nan
    directions = rng.normal(size=(245, 3)) * [1.0, 1.0, 0.2] + [3.0, 0.0, 0.0]
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    directions[9] = 0.0
    tree = neighbour_pairs(points, directions, pool=pool)
    matrix = neighbourhood._near(points, directions, np.arange(245), RADIUS, MAX_ANGLE, pool)
    row, neighbour = np.nonzero(matrix)
    assert np.array_equal(tree.row, row) and np.array_equal(tree.neighbour, neighbour), "the same pairs, in the same order"
    assert tree.row[tree.neighbour == 7].tolist() == [7] and tree.row[tree.neighbour == 9].tolist() == [9]
    monkeypatch.setitem(__import__("sys").modules, "scipy.spatial", None)  # ``import`` now raises ImportError
    brute = neighbour_pairs(points, directions, pool=pool)
    for field in ("row", "neighbour", "distance2", "cosine"):
        assert np.array_equal(getattr(tree, field), getattr(brute, field), equal_nan=True), field
    values = rng.random(245)
    whole = neighbour_mean(points, directions, values, pool=pool)  # every row: through the tree
    for chunk in np.array_split(np.arange(245), 10):  # a few rows at a time: by brute force
        assert len(chunk) <= neighbourhood.BRUTE_FORCE_ROWS
        part = neighbour_mean(points, directions, values, pool=pool, rows=chunk)
        assert np.array_equal(part[0], whole[0][chunk]) and np.array_equal(part[1], whole[1][chunk])
    apart = tree.row != tree.neighbour
    assert apart.sum() > 245 and (np.abs(np.sqrt(tree.distance2[apart]) - RADIUS) < 1e-7).sum() > 20, \
        "the test needs neighbours, many of them on the limit"


def test_pairs_on_the_limits_are_kept_by_the_tree_and_by_narrower_limits():
    """The KD-tree searches a hair beyond RADIUS + TOLERANCE, so a pair that only the slack admits is still
    found; and ``narrower`` keeps the pairs exactly on its limits, as a fresh search with them does."""
    def heading(angle):
        return [math.cos(angle), math.sin(angle), 0.0]

    from schema.neighbourhood import TOLERANCE

    x = heading(0.3)
    hair = RADIUS + TOLERANCE - 5e-12  # inside the limit by less than the tree's own rounding could misplace
    points = np.array([[0.1, 0.2, 0.0], [0.1 + hair, 0.2, 0.0], [0.1 + 0.01, 0.2, 0.0], [0.1, 0.2, 0.0]])
    directions = np.array([x, x, x, heading(0.3 + 0.35)])
    assert neighbours(points, directions, 0).tolist() == [True, True, True, True], "brute force: all on their limits"
    near = neighbour_pairs(points, directions)
    assert near.neighbour[near.row == 0].tolist() == [0, 1, 2, 3], "the tree finds the pair the slack admits"
    narrow = near.narrower(0.01, 0.35)
    fresh = neighbour_pairs(points, directions, 0.01, 0.35)
    assert narrow.neighbour[narrow.row == 0].tolist() == fresh.neighbour[fresh.row == 0].tolist() == [0, 2, 3]
    assert np.array_equal(narrow.row, fresh.row) and np.array_equal(narrow.neighbour, fresh.neighbour)


def test_many_rows_go_through_the_tree_and_a_few_or_repeated_ones_by_brute_force(monkeypatch):
    """A map that asks for every row by number (``feature_map.pose_features``) must not build an (A, A) search."""
    from schema import neighbourhood

    rng = np.random.default_rng(2)
    points, directions = rng.uniform(-0.03, 0.03, (100, 3)), np.tile([1.0, 0.0, 0.0], (100, 1))
    values = rng.random(100)
    expected = neighbour_mean(points, directions, values)

    def refused(*args, **kwargs):
        raise AssertionError("brute force")

    monkeypatch.setattr(neighbourhood, "_near", refused)
    many = np.arange(neighbourhood.BRUTE_FORCE_ROWS + 1)
    assert np.array_equal(neighbour_mean(points, directions, values, rows=many)[0], expected[0][many])
    with pytest.raises(AssertionError, match="brute force"):
        neighbour_mean(points, directions, values, rows=[3, 4])
    with pytest.raises(AssertionError, match="brute force"):
        neighbour_mean(points, directions, values, rows=np.append(many, 0))  # repeated: pairs cannot number them
