"""clutter.footprints: footprints, distances, sweeps and clearances against independent
formulas (separating axes, vertex-to-edge distances, point sampling) and hand-worked cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clutter import footprints as fp
from tests.test_clutter_policies import box, placed

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def random_polygon(rng, centre, radius=1.0, count=12) -> np.ndarray:
    return fp.convex_hull_2d(centre + rng.normal(size=(count, 2)) * radius)


def sat_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating axis theorem: two convex polygons overlap (positive area in common) iff no
    edge normal of either separates their projections."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.stack([edges[:, 1], -edges[:, 0]], axis=1):
            pa, pb = a @ [nx, ny], b @ [nx, ny]
            if pa.max() <= pb.min() + 1e-12 or pb.max() <= pa.min() + 1e-12:
                return False
    return True


def vertex_edge_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two disjoint convex polygons: the nearest vertex of one to the other."""
    return float(min(fp.point_polygon_distance(a, b[None]).min(), fp.point_polygon_distance(b, a[None]).min()))


# --- footprints ---------------------------------------------------------------------------


def test_the_hull_drops_interior_and_collinear_points_and_runs_counter_clockwise():
    points = np.concatenate([SQUARE, [[0.5, 0.5], [0.2, 0.7], [0.5, 0.0], [1.0, 0.5]], SQUARE])
    hull = fp.convex_hull_2d(points)
    assert len(hull) == 4 and {tuple(p) for p in hull} == {tuple(p) for p in SQUARE}
    assert fp.polygon_areas(hull) == pytest.approx(1.0)


def test_the_hull_is_scipys_on_point_clouds_of_every_size():
    spatial = pytest.importorskip("scipy.spatial")
    rng = np.random.default_rng(9)
    for count in (3, 10, 17, 60, 400):  # below and above the octagon filter's threshold
        points = rng.normal(size=(count, 2)) * [1.0, 0.3]
        hull = fp.convex_hull_2d(points)
        reference = points[spatial.ConvexHull(points).vertices]  # counter-clockwise too
        start = int(np.argmin(np.linalg.norm(reference - hull[0], axis=1)))
        assert np.array_equal(np.roll(reference, -start, axis=0), hull)


def test_a_heaps_footprints_are_its_objects_footprints():
    rng = np.random.default_rng(10)
    hulls = [rng.normal(size=(v, 3)) * 0.05 for v in (8, 65, 30)]
    poses = np.stack([np.eye(4)] * 3)
    for k, pose in enumerate(poses):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        pose[:3, :3] = np.eye(3) + math.sin(k + 1.0) * skew + (1 - math.cos(k + 1.0)) * skew @ skew
        pose[:3, 3] = rng.normal(size=3) * 0.1
    for together, alone in zip(fp.footprints(hulls, poses), (fp.footprint(h, p) for h, p in zip(hulls, poses))):
        assert together.shape == alone.shape and np.allclose(together, alone, rtol=0, atol=1e-15)


def test_a_footprint_follows_the_pose():
    hull = box(0.05, 0.02, 0.03)
    pose = placed(0.1, -0.05, math.pi / 2)
    poly = fp.footprint(hull, pose)
    assert np.allclose(poly.min(axis=0), [0.1 - 0.02, -0.05 - 0.05]) and np.allclose(poly.max(axis=0), [0.12, 0.0])
    # Lying on its side (90 deg about x): the footprint is 2a x c.
    side = np.eye(4)
    side[1:3, 1:3] = [[0.0, -1.0], [1.0, 0.0]]
    assert fp.polygon_areas(fp.footprint(hull, side)) == pytest.approx(0.10 * 0.03)


def test_padding_changes_no_area_containment_or_distance():
    rng = np.random.default_rng(0)
    polys = [random_polygon(rng, [0, 0], count=k) for k in (5, 9, 30)]
    padded = fp.pad_polygons(polys)
    points = rng.uniform(-3, 3, size=(50, 2))
    for poly, pad in zip(polys, padded):
        assert fp.polygon_areas(pad) == pytest.approx(fp.polygon_areas(poly))
        assert np.array_equal(fp.points_in_polygons(points, pad[None]), fp.points_in_polygons(points, poly[None]))
        assert np.allclose(fp.point_polygon_distance(points, pad[None]), fp.point_polygon_distance(points, poly[None]))


# --- points and segments --------------------------------------------------------------------


def test_point_and_segment_distances_to_a_square():
    square = SQUARE[None]
    points = np.array([[2.0, 0.5], [2.0, 2.0], [0.5, 0.5], [1.0, 1.0]])
    assert np.allclose(fp.point_polygon_distance(points, square), [1.0, math.sqrt(2), 0.0, 0.0])
    starts = np.array([[-1.0, 0.5], [-1.0, 1.5], [0.2, 0.2], [3.0, 3.0], [-1.0, -1.0]])
    ends = np.array([[2.0, 0.5], [2.0, 1.5], [0.8, 0.8], [4.0, 3.0], [2.0, -0.5]])
    # through; parallel 0.5 above; wholly inside; far corner; below, slanting up to 0.5 under it
    expected = [0.0, 0.5, 0.0, math.sqrt(8)]
    got = fp.segment_polygon_distance(starts, ends, square)
    assert np.allclose(got[:4], expected)
    # The slanted one: nearest at the corner (1, 0) or (0, 0) to the line y = -1 + (x + 1) / 6.
    corner_gap = min(abs(-1.0 + (x + 1.0) / 6.0) / math.hypot(1.0, 1.0 / 6.0) for x in (0.0, 1.0))
    assert got[4] == pytest.approx(corner_gap)


def test_segment_distance_matches_dense_sampling():
    rng = np.random.default_rng(1)
    for _ in range(30):
        poly = random_polygon(rng, rng.uniform(-1, 1, 2), radius=0.5)
        a, b = rng.uniform(-3, 3, size=(2, 2))
        samples = a + np.linspace(0, 1, 4001)[:, None] * (b - a)
        sampled = fp.point_polygon_distance(samples, poly[None]).min()
        exact = fp.segment_polygon_distance(a[None], b[None], poly[None])[0]
        assert exact <= sampled + 1e-12 and sampled - exact < 1e-3 * np.linalg.norm(b - a)


def test_a_capsule_touching_is_not_a_hit_but_closer_is():
    starts, ends = np.array([[-1.0, 1.5]]), np.array([[2.0, 1.5]])
    assert not fp.capsule_hits(starts, ends, 0.5, SQUARE[None])[0]
    assert fp.capsule_hits(starts, ends, 0.51, SQUARE[None])[0]


# --- rays, sums and clearances --------------------------------------------------------


def test_ray_interval_through_a_square():
    t_in, t_out = fp.ray_interval(np.array([[-1.0, 0.5], [-1.0, 1.5], [0.5, 0.5]]), np.array([[1.0, 0.0]] * 3), SQUARE[None])
    assert (t_in[0], t_out[0]) == pytest.approx((1.0, 2.0))
    assert t_in[1] > t_out[1]  # misses
    assert t_in[2] < 0 < t_out[2] == pytest.approx(0.5)  # starts inside


def test_the_minkowski_difference_holds_exactly_the_overlapping_translations():
    rng = np.random.default_rng(2)
    seen = set()
    for _ in range(10):
        a, b = random_polygon(rng, [0, 0], 0.5, 7), random_polygon(rng, [0.3, 0.1], 0.5, 9)
        pa, pb = fp.pad_polygons([a, b])
        diff = fp.minkowski_difference(pa, pb)
        assert fp.polygon_areas(diff) > fp.polygon_areas(a) + fp.polygon_areas(b)
        for t in rng.uniform(-2, 2, size=(60, 2)):
            if abs(fp.edge_slack(t, diff).max()) > 1e-6:  # not on the boundary
                inside = bool(fp.points_in_polygons(t, diff, 0.0))
                assert inside == sat_overlap(a + t, b)
                seen.add(inside)
    assert seen == {True, False}


def test_signed_distances_agree_with_vertex_distances_and_separating_axes():
    rng = np.random.default_rng(3)
    polys = [random_polygon(rng, rng.uniform(-2, 2, 2), 0.4, 8) for _ in range(8)]
    signed = fp.signed_distances(fp.pad_polygons(polys))
    assert np.allclose(signed, signed.T) and np.all(np.diag(signed) == 0)
    for i in range(8):
        for j in range(i + 1, 8):
            overlap = sat_overlap(polys[i], polys[j])
            assert (signed[i, j] < 0) == overlap
            if not overlap:
                assert signed[i, j] == pytest.approx(vertex_edge_distance(polys[i], polys[j]), abs=1e-12)


def test_clearance_between_two_squares_and_to_the_walls():
    polys = np.stack([SQUARE, SQUARE + [2.0, 0.0]])
    directions = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [math.sqrt(0.5), math.sqrt(0.5)]])
    clear = fp.translation_clearance(polys, directions)
    assert clear[0, 0] == pytest.approx(1.0) and clear[1, 1] == pytest.approx(1.0)
    assert np.isinf(clear[0, 1]) and np.isinf(clear[0, 2]) and np.isinf(clear[1, 0])
    assert np.isinf(clear[0, 3])  # diagonally its corner (1, 1) only touches the other's corner (2, 1)
    walls = fp.wall_clearance(polys - [1.5, 0.5], directions, np.array([3.0, 2.0]))
    assert walls[0, 0] == pytest.approx(3.0 - (-0.5)) and walls[0, 1] == pytest.approx(3.0 - 1.5)
    assert walls[0, 2] == pytest.approx(1.5)


def test_clearance_is_the_first_overlapping_translation():
    rng = np.random.default_rng(4)
    polys = [random_polygon(rng, rng.uniform(-1.5, 1.5, 2), 0.3, 8) for _ in range(6)]
    padded = fp.pad_polygons(polys)
    signed = fp.signed_distances(padded)
    directions = np.stack([np.cos(np.arange(16) * np.pi / 8), np.sin(np.arange(16) * np.pi / 8)], axis=1)
    clear = fp.translation_clearance(padded, directions)
    checked = 0
    for i in range(6):
        if (signed[i, np.arange(6) != i] < 0).any():
            continue  # overlapping from the start: the separating rule applies instead
        for k, d in enumerate(directions):
            if np.isfinite(clear[i, k]):
                before = [sat_overlap(polys[i] + d * (clear[i, k] - 1e-6), polys[j]) for j in range(6) if j != i]
                after = [sat_overlap(polys[i] + d * (clear[i, k] + 1e-3), polys[j]) for j in range(6) if j != i]
                assert not any(before) and any(after)
                checked += 1
    assert checked >= 10


def test_overlapping_footprints_block_only_slides_that_deepen_the_overlap():
    polys = np.stack([SQUARE, SQUARE + [0.9, 0.0]])  # 0.1 of overlap along x
    clear = fp.translation_clearance(polys, np.array([[-1.0, 0.0], [1.0, 0.0]]))
    assert np.isinf(clear[0, 0]) and clear[0, 1] == 0.0
    assert clear[1, 0] == 0.0 and np.isinf(clear[1, 1])


def test_clip_overhang_and_inside_box():
    half = np.array([1.0, 0.5])
    low, high = fp.clip_to_box(np.array([[-2.0, 0.0], [0.0, 0.0], [0.0, 2.0]]), np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]]), half)
    assert (low[0], high[0]) == pytest.approx((1.0, 3.0)) and (low[1], high[1]) == pytest.approx((-0.5, 0.5))
    assert low[2] > high[2]
    assert fp.overhang(np.array([[[0.0, 0.0], [1.2, 0.1]], [[0.1, 0.1], [-0.5, 0.4]]]), half) == pytest.approx([0.2, -0.1])
    assert list(fp.inside_box(np.array([[1.0, 0.5], [1.01, 0.0]]), half)) == [True, False]


# --- cases the mutation run (stop 71) found untested ------------------------------------------


def test_three_points_make_a_counter_clockwise_hull_without_collinear_ones():
    # Sorted by x these run clockwise; the hull must turn them and drop the collinear middle point.
    hull = fp.convex_hull_2d(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]]))
    assert len(hull) == 3 and fp.polygon_areas(hull) == pytest.approx(1.0)
    line = fp.convex_hull_2d(np.array([[0.0, 0.0], [2.0, 2.0], [1.0, 1.0]]))
    assert {tuple(p) for p in line} == {(0.0, 0.0), (2.0, 2.0)}


def test_the_hull_of_grid_points_with_ties_and_repeats():
    # Many points share an x or a y, some repeat: the hull is the grid's bounding corners.
    rng = np.random.default_rng(12)
    for _ in range(20):
        points = rng.integers(0, 4, size=(int(rng.integers(5, 40)), 2)).astype(float)
        hull = fp.convex_hull_2d(points)
        assert fp.polygon_areas(hull) > 0 or len(hull) <= 2
        # Every point is inside the hull, every hull vertex is a strict corner (a left turn).
        if len(hull) >= 3:
            assert fp.points_in_polygons(points, hull[None]).all()
            a, b = np.roll(hull, -1, axis=0) - hull, np.roll(hull, -2, axis=0) - np.roll(hull, -1, axis=0)
            turn = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
            assert np.all(turn > 0)


def test_the_octagon_filter_drops_only_points_strictly_inside_it():
    # A square's corners (the octagon repeats them: axis directions tie on two corners) and
    # points inside it: every interior point is dropped, no corner is.
    rng = np.random.default_rng(13)
    interior = rng.uniform(-0.9, 0.9, size=(30, 2))
    points = np.concatenate([[[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], interior, [[0.0, 0.0], [0.5, 0.0], [0.0, -0.5]]])
    inside = fp.strictly_inside_octagon(points)
    assert not inside[:4].any() and inside[4:].all()
    # On a circle every point is its own extreme in some direction or on the octagon's edge.
    circle = np.stack([np.cos(np.arange(24) * np.pi / 12), np.sin(np.arange(24) * np.pi / 12)], axis=1)
    assert not fp.strictly_inside_octagon(circle).any()
    assert np.array_equal(fp.convex_hull_2d(points), fp.monotone_chain(points))


def test_a_segment_that_ends_inside_a_polygon_meets_it():
    # Start outside, end inside: exactly one edge crossed, so the crossing test alone decides.
    rng = np.random.default_rng(14)
    for _ in range(40):
        poly = random_polygon(rng, [0.0, 0.0], 0.5, 10)
        end = poly.mean(axis=0)
        start = end + rng.normal(size=2) * 3.0
        if fp.points_in_polygons(start, poly[None], 0.0):
            continue
        assert fp.segment_polygon_distance(start[None], end[None], poly[None])[0] == 0.0
        assert fp.segment_polygon_distance(end[None], start[None], poly[None])[0] == 0.0


def test_ray_interval_along_slanted_directions_and_through_padded_polygons():
    rng = np.random.default_rng(15)
    poly = random_polygon(rng, [0.0, 0.0], 0.5, 9)
    padded = fp.pad_polygons([poly, np.zeros((len(poly) + 4, 2))])[0]
    origins = rng.uniform(-2, 2, size=(50, 2))
    angles = rng.uniform(0, 2 * np.pi, 50)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1) * rng.uniform(0.5, 2.0, (50, 1))
    t_in, t_out = fp.ray_interval(origins, directions, poly[None])
    pad_in, pad_out = fp.ray_interval(origins, directions, padded[None])
    assert np.allclose(t_in, pad_in) and np.allclose(t_out, pad_out)
    hit = t_in < t_out
    assert 5 < hit.sum() < 50
    # Where it hits, the ends of the interval are on the boundary and its middle is inside.
    for t in (t_in[hit], t_out[hit]):
        ends = origins[hit] + t[:, None] * directions[hit]
        assert np.allclose(fp.point_polygon_distance(ends, poly[None]), 0.0, atol=1e-9)
        assert np.all(np.abs(fp.edge_slack(ends, poly[None]).max(axis=-1)) < 1e-9)
    middle = origins[hit] + ((t_in + t_out) / 2)[hit, None] * directions[hit]
    assert fp.points_in_polygons(middle, poly[None]).all()
    # A miss: no point of the line is inside.
    for o, d in zip(origins[~hit], directions[~hit]):
        samples = o + np.linspace(-5, 5, 2001)[:, None] * d
        assert not fp.points_in_polygons(samples, poly[None], 0.0).any()


def test_functions_broadcast_over_leading_dimensions():
    rng = np.random.default_rng(16)
    polys = fp.pad_polygons([random_polygon(rng, rng.uniform(-1, 1, 2), 0.5, k) for k in (5, 8, 11, 6, 9, 7)]).reshape(2, 3, -1, 2)
    origins = rng.uniform(-2, 2, size=(2, 3, 2))
    directions = rng.normal(size=(2, 3, 2))
    t_in, t_out = fp.ray_interval(origins, directions, polys)
    assert t_in.shape == t_out.shape == (2, 3)
    for a in range(2):
        for b in range(3):
            one_in, one_out = fp.ray_interval(origins[a, b][None], directions[a, b][None], polys[a, b][None])
            assert (t_in[a, b], t_out[a, b]) == (one_in[0], one_out[0])
    points = np.array([[[0.5, 0.2], [1.2, 0.0]], [[0.0, -0.6], [-1.0, 0.5]]])
    assert fp.inside_box(points, np.array([1.0, 0.5])).tolist() == [[True, False], [False, True]]


def test_the_minkowski_difference_of_squares_with_level_edges():
    # Level bottom edges tie on the lowest y: the start must be the lowest-then-leftmost vertex.
    for roll, shift in enumerate(([2.0, 0.0], [0.5, -0.25], [-3.0, 1.0], [0.0, 0.0])):
        # The same square listed from every corner: the level edges' ends come in either order.
        moving, fixed = np.roll(SQUARE, roll, axis=0), np.roll(SQUARE, roll + 1, axis=0) + shift
        diff = fp.minkowski_difference(moving, fixed)
        expected = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) + shift
        assert np.allclose(diff.min(axis=0), expected.min(axis=0)) and np.allclose(diff.max(axis=0), expected.max(axis=0))
        assert fp.polygon_areas(diff) == pytest.approx(4.0)
        assert set(map(tuple, np.round(diff, 12))) >= set(map(tuple, np.round(expected, 12)))


def test_clip_to_box_along_slanted_lines():
    half = np.array([1.0, 0.5])
    d = np.array([[0.6, 0.8], [-0.8, 0.6]])
    starts = np.array([[-2.0, -2.0], [0.3, 0.1]])
    low, high = fp.clip_to_box(starts, d, half)
    for s, di, lo, hi in zip(starts, d, low, high):
        assert lo < hi
        for t in (lo, hi):  # the ends are on the box's boundary
            p = s + t * di
            assert fp.inside_box(p, half) and np.isclose(np.max(np.abs(p) - half), 0.0)
        assert not fp.inside_box(s + (lo - 1e-6) * di, half) and not fp.inside_box(s + (hi + 1e-6) * di, half)


def test_no_warning_on_parallel_edges_padding_and_points_on_walls():
    import warnings

    square = fp.pad_polygons([SQUARE, np.zeros((7, 2))])[:1]  # padded: zero-length edges
    axes = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fp.ray_interval(np.array([[0.0, 0.0], [-1.0, 0.5], [0.5, 2.0], [1.0, 1.0]]), axes, square)
        fp.translation_clearance(np.concatenate([square, square + [2.0, 0.0]]), axes)
        fp.wall_clearance(square - 1.0, axes, np.array([1.0, 1.0]))  # vertices on the walls
        fp.clip_to_box(np.array([[1.0, 0.0], [0.0, 0.5], [-1.0, -0.5], [0.2, 0.2]]), axes, np.array([1.0, 0.5]))
