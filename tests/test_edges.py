"""Base polygon and per-edge toppling geometry (pipeline/model/edges.py) on shapes
whose answers follow by hand: a standing box, an off-centre centre of mass, and
single raised vertices."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.model.edges import base_edges, base_polygon, edge_geometry, landing_angles, landing_down, rolled_down
from schema.frames import axis_angle_matrices

WIDTH, DEPTH, HEIGHT = 0.05, 0.08, 0.15  # m, box standing on its 0.05 x 0.08 face
TOLERANCE = 1e-4  # m


def box_vertices(com_xy=(0.0, 0.0)):
    """(8, 3) corners of the standing box in a pose frame, base on z = 0, shifted by -com_xy."""
    x, y = WIDTH / 2, DEPTH / 2
    corners = np.array([[sx * x, sy * y, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, HEIGHT)])
    corners[:, :2] -= com_xy
    return corners


def signed_area(polygon):
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def edge_towards(geometry, outward):
    """Index of the edge whose outward normal is ``outward``."""
    return int(np.flatnonzero(np.all(np.isclose(geometry.outward, outward), axis=1))[0])


# ----------------------------------------------------------------------------- base polygon


def test_base_polygon_is_the_counter_clockwise_footprint():
    vertices = box_vertices()
    vertices[0, 2] = 0.5 * TOLERANCE  # resting within tolerance still touches
    polygon = base_polygon(vertices, TOLERANCE)
    assert polygon.shape == (4, 3) and np.all(polygon[:, 2] == 0)
    assert signed_area(polygon) == pytest.approx(WIDTH * DEPTH)  # positive: counter-clockwise
    assert {tuple(np.round(p[:2], 6)) for p in polygon} == {(sx * 0.025, sy * 0.04) for sx in (-1, 1) for sy in (-1, 1)}


@pytest.mark.parametrize("lift", [TOLERANCE, 2 * TOLERANCE])
def test_vertices_above_the_tolerance_are_not_part_of_the_base(lift):
    vertices = box_vertices()
    vertices[vertices[:, 0] > 0, 2] += lift  # tilted: the +x side no longer touches (z < tolerance touches)
    with pytest.raises(ValueError, match="degenerate"):
        base_polygon(vertices, TOLERANCE)  # only the two -x corners are left: a line


@pytest.mark.parametrize(
    "points",
    [
        [[0, 0, 0], [0.01, 0, 0]],  # two points
        [[0, 0, 0], [0.01, 0.01, 0], [0.02, 0.02, 0], [0.0, 0.0, 0.05]],  # collinear on the table
    ],
)
def test_degenerate_base_is_a_clear_error(points):
    with pytest.raises(ValueError, match="fewer than three non-collinear contact points"):
        base_polygon(np.array(points, dtype=float), TOLERANCE)


def test_base_edges_join_consecutive_corners_and_close_the_loop():
    polygon = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]], dtype=float)
    edges = base_edges(polygon)
    assert edges.shape == (3, 2, 3)
    np.testing.assert_array_equal(edges[:, 0], polygon)
    np.testing.assert_array_equal(edges[:, 1], polygon[[1, 2, 0]])


# ----------------------------------------------------------------------------- edge geometry


def test_box_edge_geometry():
    com = np.array([0.0, 0.0, HEIGHT / 2])
    geometry = edge_geometry(base_edges(base_polygon(box_vertices(), TOLERANCE)), com)
    plus_x = edge_towards(geometry, [1, 0, 0])
    np.testing.assert_allclose(geometry.direction[plus_x], [0, 1, 0], atol=1e-12)  # counter-clockwise seen from above
    assert geometry.com_distance[plus_x] == pytest.approx(WIDTH / 2)
    np.testing.assert_allclose(geometry.origin[plus_x], [WIDTH / 2, 0, 0], atol=1e-12)
    assert geometry.half_span[plus_x] == pytest.approx(DEPTH / 2)
    assert geometry.apex_angle[plus_x] == pytest.approx(np.arctan2(WIDTH / 2, HEIGHT / 2))
    plus_y = edge_towards(geometry, [0, 1, 0])
    assert geometry.com_distance[plus_y] == pytest.approx(DEPTH / 2)
    assert geometry.half_span[plus_y] == pytest.approx(WIDTH / 2)
    assert geometry.apex_angle[plus_y] == pytest.approx(np.arctan2(DEPTH / 2, HEIGHT / 2))
    # Every edge: unit direction, horizontal outward normal at right angles to it.
    np.testing.assert_allclose(np.linalg.norm(geometry.direction, axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", geometry.direction, geometry.outward), 0.0, atol=1e-12)
    assert np.all(geometry.outward[:, 2] == 0)


def test_off_centre_mass_distances_and_spans():
    # COM 1 cm towards +x and 3 cm towards +y of the base's centre, 5 cm up.
    com = np.array([0.01, 0.03, 0.05])
    geometry = edge_geometry(base_edges(base_polygon(box_vertices(), TOLERANCE)), com)
    expected = {  # outward normal: (distance to the edge, half span about the COM's projection)
        (1, 0, 0): (0.025 - 0.01, 0.5 * ((0.04 + 0.03) + (0.04 - 0.03))),
        (-1, 0, 0): (0.025 + 0.01, 0.5 * ((0.04 + 0.03) + (0.04 - 0.03))),
        (0, 1, 0): (0.04 - 0.03, 0.5 * ((0.025 + 0.01) + (0.025 - 0.01))),
        (0, -1, 0): (0.04 + 0.03, 0.5 * ((0.025 + 0.01) + (0.025 - 0.01))),
    }
    for outward, (distance, span) in expected.items():
        e = edge_towards(geometry, outward)
        assert geometry.com_distance[e] == pytest.approx(distance)
        assert geometry.half_span[e] == pytest.approx(span)
        assert geometry.apex_angle[e] == pytest.approx(np.arctan2(distance, com[2]))
        # The COM's projection on the edge line lies on the edge, at the COM's height 0.
        projection = geometry.origin[e]
        assert projection[2] == 0 and np.dot(com[:2] - projection[:2], geometry.direction[e][:2]) == pytest.approx(0, abs=1e-12)


def test_centre_of_mass_outside_the_base_has_negative_distance():
    triangle = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], dtype=float)  # counter-clockwise
    geometry = edge_geometry(base_edges(triangle), np.array([0.02, -0.03, 0.04]))
    assert geometry.com_distance[0] == pytest.approx(-0.03)  # beyond the y = 0 edge
    assert geometry.com_distance[2] == pytest.approx(0.02)  # inside the x = 0 edge
    # A COM whose projection on the y = 0 edge falls beyond its end (0.1, 0): the mean distance to both ends.
    far = edge_geometry(base_edges(triangle), np.array([0.15, 0.01, 0.04]))
    assert far.half_span[0] == pytest.approx(0.5 * (0.15 + 0.05))


def test_tipping_to_the_apex_puts_the_centre_of_mass_over_the_edge():
    rng = np.random.default_rng(4)
    for _ in range(5):
        angles = np.sort(rng.uniform(0, 2 * np.pi, 6))
        polygon = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(6)]) * rng.uniform(0.02, 0.08)
        com = np.array([*rng.uniform(-0.005, 0.005, 2), rng.uniform(0.01, 0.1)])
        geometry = edge_geometry(base_edges(polygon), com)
        assert np.all(geometry.com_distance > 0) and np.all(geometry.apex_angle > 0)
        for e in range(len(polygon)):
            # Rotate the COM about the edge line (through y0) by the apex angle.
            lever = axis_angle_matrices(geometry.direction[e], geometry.apex_angle[e]) @ (com - geometry.start[e])
            assert np.dot(lever, geometry.outward[e]) == pytest.approx(0.0, abs=1e-12)  # right above the edge
            assert lever[2] == pytest.approx(np.hypot(geometry.com_distance[e], com[2]))  # at its highest
            np.testing.assert_allclose(geometry.tip_rotation[e], axis_angle_matrices(geometry.direction[e], geometry.apex_angle[e]))


# ----------------------------------------------------------------------------- landing


def test_box_lands_on_the_side_face_a_quarter_turn_later():
    com = np.array([0.0, 0.0, HEIGHT / 2])
    vertices = box_vertices()
    geometry = edge_geometry(base_edges(base_polygon(vertices, TOLERANCE)), com)
    angles = landing_angles(geometry, vertices, TOLERANCE)
    np.testing.assert_allclose(angles, np.pi / 2)
    down = landing_down(geometry, angles)
    np.testing.assert_allclose(down, geometry.outward, atol=1e-12)  # toppled over +x, the +x face is down


def test_landing_angle_of_single_raised_vertices():
    polygon = base_polygon(box_vertices(), TOLERANCE)
    geometry = edge_geometry(base_edges(polygon), np.array([0.0, 0.0, 0.05]))
    plus_x = edge_towards(geometry, [1, 0, 0])
    # A vertex 1 cm beyond the +x edge and 2 cm up meets the table after atan2(0.02, 0.01);
    # one 3 cm inside it and 1 cm up only after atan2(0.01, -0.03) (more than a quarter turn).
    outside = np.array([[WIDTH / 2 + 0.01, 0.0, 0.02]])
    inside = np.array([[WIDTH / 2 - 0.03, 0.0, 0.01]])
    base = np.column_stack([polygon[:, :2], np.zeros(4)])
    assert landing_angles(geometry, np.vstack([base, outside]), TOLERANCE)[plus_x] == pytest.approx(np.arctan2(0.02, 0.01))
    assert landing_angles(geometry, np.vstack([base, inside]), TOLERANCE)[plus_x] == pytest.approx(np.arctan2(0.01, -0.03))
    # The smallest angle wins.
    both = landing_angles(geometry, np.vstack([base, outside, inside]), TOLERANCE)[plus_x]
    assert both == pytest.approx(np.arctan2(0.02, 0.01))
    # A vertex at the tolerance is off the table (the base takes z < tolerance): it is raised and lands first.
    grazing = np.array([[WIDTH / 2 + 0.01, 0.0, TOLERANCE]])
    assert landing_angles(geometry, np.vstack([base, outside, grazing]), TOLERANCE)[plus_x] == pytest.approx(np.arctan2(TOLERANCE, 0.01))
    # Vertices on the table never stop the rotation: with nothing raised it is a half turn.
    np.testing.assert_array_equal(landing_angles(geometry, base, TOLERANCE), np.pi)


def test_landing_down_rotates_back_about_the_edge():
    polygon = base_polygon(box_vertices(), TOLERANCE)
    geometry = edge_geometry(base_edges(polygon), np.array([0.0, 0.0, 0.05]))
    angles = np.full(len(polygon), 0.3)
    down = landing_down(geometry, angles)
    # Tipped by 0.3 rad outward, the new down vector leans 0.3 rad towards the outward side.
    np.testing.assert_allclose(down @ np.array([0, 0, -1.0]), np.cos(0.3))
    np.testing.assert_allclose(np.einsum("ij,ij->i", down, geometry.outward), np.sin(0.3))


def test_a_blocked_topple_rolls_on_over_the_toe_wherever_the_edge_lies():
    """A prism along y whose cross-section (x, z) is (-1, 0), (0, 0), a low toe (0.5, 0.1), (0.9,
    0.35), (0, 1), (-1, 1) (m), its centre of mass at (-0.4, 0.5): tipped over the base edge x = 0
    (outward +x) the toe's first facet meets the table at atan(0.1 / 0.5) = 0.2 rad, long before
    the apex (0.67 rad; blocked, MODEL.md C.6); turned on about the toe's tip, the next facet lands
    first again (0.36 rad, apex 0.96 rad); turned on about (0.9, 0.35), the centre of mass passes it
    (0.90 rad) long before the face up to (0, 1) would land (1.96 rad), so the prism comes to rest on
    that face: down is its outward normal (0.65, 0, 0.9) / |.|.  Moved along the table and turned
    about the vertical, the same prism rolls the same way: the answer turns with it."""
    profile = [(-1.0, 0.0), (0.0, 0.0), (0.5, 0.1), (0.9, 0.35), (0.0, 1.0), (-1.0, 1.0)]
    vertices = np.array([[x, y, z] for x, z in profile for y in (-1.0, 1.0)])
    com, start, direction = np.array([-0.4, 0.0, 0.5]), np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])
    down = rolled_down(vertices, com, start, direction, TOLERANCE)
    np.testing.assert_allclose(down, np.array([0.65, 0.0, 0.9]) / np.hypot(0.65, 0.9), atol=1e-12)
    for angle, shift in ((0.5, [0.0, 0.0, 0.0]), (2.0, [-1.0, 0.5, 0.0]), (-2.5, [0.3, -0.2, 0.0]), (1.0, [1.0, 2.0, 0.0])):
        turn = axis_angle_matrices(np.array([0.0, 0.0, 1.0]), np.array(angle))
        moved = [(np.asarray(points) + shift) @ turn.T for points in (vertices, com, start)]  # along the table, then about the vertical
        turned = rolled_down(*moved, turn @ direction, TOLERANCE)
        np.testing.assert_allclose(turned, turn @ down, atol=1e-12, err_msg=str(angle))
