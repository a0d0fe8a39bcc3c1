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
