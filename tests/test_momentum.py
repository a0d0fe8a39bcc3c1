"""The ``momentum`` correction (docs/MODEL.md C.8) against closed forms and pybullet.

A prism's topples are planar: the impact keeps, of the energy m g (|c - P| - d_B) the
centre of mass c gains falling from its apex over the pivot P onto face B (d_B: c's
height over B), the share

    ((J + r1 . r2) / (J + |r2|^2))^2 (J + |r2|^2) / (J + |r1|^2)

(J: the cross-section's polar second moment about c per unit area; r1 = c - P, r2 = c - Q,
Q the far end of B), and the object rolls on over Q when that exceeds |c - Q| - d_B.
"""

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from shapes import box_object, pose_with_down

from pipeline.model.config import Config
from pipeline.model.mesh import model_from_mesh
from pipeline.model.momentum import exit_edge, impact_energy_ratio, inertia_per_mass, momentum_poses
from pipeline.model.poses import stable_poses
from pipeline.model.topple import landed_poses

QUADRILATERAL = np.array([[0.04, 0.022], [-0.035, 0.009], [0.003, -0.032], [0.059, -0.028]])
"""m, a convex cross-section (x, z), counter-clockwise: resting on its side 0, a topple over
vertex 1 lands on side 1 with its centre of mass 3 mm inside the far end (vertex 2), and
keeps 2.5 times the energy it needs to roll on over it."""
DEPTH = 0.1
"""m, the prism's length along y."""
CLEAR = 1.5
"""Kept energy over the barrier beyond which (or below whose inverse) the closed form's
verdict is clear of the model's small 3-D differences (the prism's end faces)."""
HEXAGON = np.array([30, 26, 22, 28, 24, 20])[:, None] / 1000 * np.column_stack(
    [np.cos(np.radians(10 + 60 * np.arange(6))), np.sin(np.radians(10 + 60 * np.arange(6)))])
"""m, a convex hexagonal cross-section (x, z), counter-clockwise, its vertices 20-30 mm out at 60
degree steps: stable on every side, and its vertices' distances from the centroid (29.4, 24.9,
21.5, 28.6, 25.1, 20.5 mm) differ by 0.8 mm or more."""


def prism(cross_section: np.ndarray, depth: float = DEPTH) -> trimesh.Trimesh:
    """The prism over a convex (x, z) cross-section, along y, centred on y = 0."""
    half = np.full(len(cross_section), depth / 2)
    x, z = cross_section[:, 0], cross_section[:, 1]
    return trimesh.convex.convex_hull(np.vstack([np.column_stack([x, -half, z]), np.column_stack([x, half, z])]))


def polygon_moments(v: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (2,) and polar second moment about it per unit area (m^2) of a counter-clockwise polygon."""
    x, z = v[:, 0], v[:, 1]
    x1, z1 = np.roll(x, -1), np.roll(z, -1)
    cross = x * z1 - x1 * z
    area = cross.sum() / 2
    centroid = np.array([((x + x1) * cross).sum(), ((z + z1) * cross).sum()]) / (6 * area)
    polar = ((x * x + x * x1 + x1 * x1 + z * z + z * z1 + z1 * z1) * cross).sum() / (12 * area)
    return centroid, polar - centroid @ centroid


def side_down(v: np.ndarray, side: int) -> np.ndarray:
    """Down vector (object frame) of the prism resting on side (v[side], v[side + 1])."""
    t = v[(side + 1) % len(v)] - v[side]
    outward = np.array([t[1], -t[0]]) / np.linalg.norm(t)
    return np.array([outward[0], 0.0, outward[1]])


def planar_roll_on(v: np.ndarray, side: int) -> tuple[float, float]:
    """Resting on ``side``, toppled over its end vertex onto the next side: (energy the impact
    keeps, energy needed to roll on over that side's far end), as heights (m)."""
    c, polar = polygon_moments(v)
    p, q = v[(side + 1) % len(v)], v[(side + 2) % len(v)]
    r1, r2 = c - p, c - q
    t = (q - p) / np.linalg.norm(q - p)
    height = abs(r1[0] * t[1] - r1[1] * t[0])  # d_B
    ratio = (polar + r1 @ r2) / (polar + r2 @ r2)
    kept = ratio**2 * (polar + r2 @ r2) / (polar + r1 @ r1) * (np.linalg.norm(r1) - height) if ratio > 0 else 0.0
    return kept, np.linalg.norm(r2) - height


def pivot_edge(pose, point: np.ndarray) -> int:
    """The base edge of ``pose`` on the line through ``point`` (object frame) along y."""
    at = pose.transform[:3, :3] @ point + pose.transform[:3, 3]
    distances = [np.linalg.norm(np.cross(y1 - y0, at - y0)) / np.linalg.norm(y1 - y0) for y0, y1 in pose.base_edges]
    return int(np.argmin(distances))


@pytest.fixture(scope="module")
def quad():
    obj = model_from_mesh(prism(QUADRILATERAL), mass=0.2, name="quad")
    return obj, stable_poses(obj, merge_symmetric=False)


@pytest.mark.parametrize("half_width, half_height", [(0.02, 0.06), (0.03, 0.05), (0.025, 0.025)])
def test_a_rocking_block_keeps_housners_share_of_its_energy(half_width, half_height):
    """Housner (1963): a block rocking about one bottom corner onto the other turns on with
    omega' / omega = 1 - 3/2 sin^2(alpha), tan(alpha) = b / h; the moments about the two
    corners are equal, so the energy kept is that ratio squared."""
    b, h = half_width, half_height
    inertia = np.diag([4 * h**2 + 4 * 0.01**2, 4 * b**2 + 4 * h**2, 4 * b**2 + 4 * 0.01**2]) / 12  # per unit mass
    com = np.array([0.0, 0.0, h])
    y = np.array([0.0, 1.0, 0.0])
    # Turning back about the +x corner onto the base, it pivots next about the -x corner,
    # turning the centre of mass out over it: about -y (o = e x z must point to -x).
    kept = impact_energy_ratio(inertia, com, np.array([b, 0.0, 0.0]), y, np.array([-b, 0.0, 0.0]), -y)
    alpha = np.arctan2(b, h)
    assert kept == pytest.approx((1 - 1.5 * np.sin(alpha) ** 2) ** 2, rel=1e-9)
    # The other sense about the new corner would turn the block back: no energy goes on.
    assert impact_energy_ratio(inertia, com, np.array([b, 0.0, 0.0]), y, np.array([-b, 0.0, 0.0]), y) == 0.0


def test_inertia_per_mass_of_a_box_is_the_closed_form():
    obj = box_object(size=(0.05, 0.08, 0.15))
    expected = np.diag([0.08**2 + 0.15**2, 0.05**2 + 0.15**2, 0.05**2 + 0.08**2]) / 12
    np.testing.assert_allclose(inertia_per_mass(obj.mesh, obj.hull, obj.center_mass), expected, atol=1e-12)


def test_inertia_moves_to_the_given_centre_of_mass_and_scales_to_the_mass():
    """Parallel axes: about a point d from the box's centroid, I + |d|^2 1 - d d^T per unit mass,
    m times that for a body of mass m (off-diagonal terms -d_i d_j, so d has no zero component)."""
    obj = box_object(size=(0.05, 0.08, 0.15))
    box = np.diag([0.08**2 + 0.15**2, 0.05**2 + 0.15**2, 0.05**2 + 0.08**2]) / 12
    d = np.array([0.004, -0.01, 0.02])
    expected = box + d @ d * np.eye(3) - np.outer(d, d)
    np.testing.assert_allclose(inertia_per_mass(obj.mesh, obj.hull, obj.center_mass + d), expected, atol=1e-12)
    np.testing.assert_allclose(inertia_per_mass(obj.mesh, obj.hull, obj.center_mass + d, mass=0.3), 0.3 * expected, atol=1e-12)


def test_inertia_is_the_mesh_s_own_and_its_hull_s_only_where_it_encloses_no_volume():
    """Two 4 cm cubes 10 cm apart: their own inertia about the midpoint, a^2/6 about x and
    a^2/6 + d^2 about y and z, not their hull's (a solid bar).  A box missing its top face
    encloses no volume: its hull's, the closed box's closed form."""
    a, d = 0.04, 0.05
    cubes = [trimesh.creation.box([a, a, a]) for _ in range(2)]
    for cube, side in zip(cubes, (-1, 1)):
        cube.apply_translation([side * d, 0.0, 0.0])
    two = trimesh.util.concatenate(cubes)
    assert two.is_volume
    np.testing.assert_allclose(inertia_per_mass(two, two.convex_hull, np.zeros(3)),
                               np.diag([a * a / 6, a * a / 6 + d * d, a * a / 6 + d * d]), atol=1e-12)
    box = trimesh.creation.box([0.05, 0.08, 0.15])
    open_box = trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.5])
    assert not open_box.is_volume
    np.testing.assert_allclose(inertia_per_mass(open_box, box, np.zeros(3)),
                               np.diag([0.08**2 + 0.15**2, 0.05**2 + 0.15**2, 0.05**2 + 0.08**2]) / 12, atol=1e-12)


def test_the_edge_ahead_is_the_one_the_centre_of_mass_heads_for():
    """A unit square base around the centre of mass: heading +x meets the +x edge, heading
    mostly -y the -y edge; no travel meets none (-1)."""
    outward = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    inside = np.array([0.5, 0.2, 0.5, 0.8])  # the centre of mass is 0.2 from the +x edge
    with np.errstate(all="raise"):  # edges parallel to the travel divide by zero, silently
        assert exit_edge(outward, inside, np.array([1.0, 0.0, 0.0])) == 1
        assert exit_edge(outward, inside, np.array([0.3, -0.95, 0.0])) == 0
        assert exit_edge(outward, inside, np.array([0.0, 0.0, 0.0])) == -1
        # On the -y edge's line (0 / 0 there), heading +x: still the +x edge.
        assert exit_edge(outward, np.array([0.0, 0.2, 1.0, 0.8]), np.array([1.0, 0.0, 0.0])) == 1


def test_a_box_never_rolls_on():
    """A box's topple falls |c - P| - d_B and then needs |c - Q| - d_B to pass the next edge,
    at least as much for a box standing on its smaller face; Housner's impact keeps at most
    (1 - 3/2 sin^2 45)^2 = 1/16 ... 1 of it, never enough: every landing is the quasi-static one."""
    obj = box_object(size=(0.05, 0.08, 0.15))
    for pose in stable_poses(obj, merge_symmetric=False).poses:
        np.testing.assert_array_equal(pose.edge_momentum_pose, pose.edge_final_pose)


def test_the_prism_rolls_on_where_the_planar_closed_form_says(quad):
    obj, pose_set = quad
    n = len(QUADRILATERAL)
    poses = [pose_with_down(pose_set, side_down(QUADRILATERAL, side), atol=1e-6) for side in range(n)]
    checked = rolls = 0
    for side in range(n):
        kept, needed = planar_roll_on(QUADRILATERAL, side)
        if CLEAR ** -1 < kept / needed < CLEAR:
            continue
        pose = pose_set.poses[poses[side]]
        edge = pivot_edge(pose, np.array([QUADRILATERAL[(side + 1) % n][0], 0.0, QUADRILATERAL[(side + 1) % n][1]]))
        landed, rolled_on = poses[(side + 1) % n], poses[(side + 2) % n]
        assert pose.edge_final_pose[edge] == landed, side
        assert pose.edge_momentum_pose[edge] == (rolled_on if kept > needed else landed), side
        checked += 1
        rolls += kept > needed
    assert checked >= 3 and rolls >= 1  # the closed form decides most sides, and one rolls on


def pose_tables(obj, pose_set) -> tuple:
    """``momentum_poses``' arguments but ``energy_scale``, from a pose set (as ``landing.land_object``)."""
    poses = pose_set.poses
    return (np.array([p.transform for p in poses]), [p.base_edges for p in poses], [p.edge_final_pose.copy() for p in poses],
            [p.edge_blocked.copy() for p in poses], obj.center_mass, inertia_per_mass(obj.mesh, obj.hull, obj.center_mass))


def test_lossless_impacts_roll_on_until_an_apex_higher_than_the_first():
    """With every impact keeping all its energy (a huge ``energy_scale``; C.8's share is at most
    one), energy is conserved: toppled over vertex k, the hexagonal prism rolls on over each next
    vertex nearer its centre of mass than vertex k, and stops on the side before the first one
    farther out; its onward pose is the side beyond that vertex.  Housner's share is positive at
    every impact here (the vertices are 60 degrees apart), so none stops it dead.  The topple over
    the farthest vertex is left out: it comes round to that vertex again at exactly its energy."""
    obj = model_from_mesh(prism(HEXAGON), mass=0.2, name="hexagon")
    pose_set = stable_poses(obj, merge_symmetric=False)
    n = len(HEXAGON)
    poses = [pose_with_down(pose_set, side_down(HEXAGON, side), atol=1e-6) for side in range(n)]
    ends, onwards = momentum_poses(*pose_tables(obj, pose_set), energy_scale=1e6)
    distance = np.linalg.norm(HEXAGON - polygon_moments(HEXAGON)[0], axis=1)
    rolls = []
    for side in range(n):
        first = (side + 1) % n
        if distance[first] == distance.max():
            continue
        last = next(k for k in range(first + 1, first + n) if distance[k % n] > distance[first]) - 1  # side (last, last + 1)
        pose = pose_set.poses[poses[side]]
        edge = pivot_edge(pose, np.array([HEXAGON[first][0], 0.0, HEXAGON[first][1]]))
        assert (ends[pose.index][edge], onwards[pose.index][edge]) == (poses[last % n], poses[(last + 1) % n]), side
        rolls.append(last - first)
    assert sorted(rolls) == [0, 0, 1, 1, 2]  # chains of none, one and two roll-ons


def test_an_edge_ahead_that_topples_back_into_the_pose_ends_the_chain(quad):
    """Toppled over vertex 1 from side 0, the prism lands on side 1 with energy enough to roll on
    over vertex 2.  Were that topple one back into side 1 (unblocked), or blocked (its final pose
    side 1 itself, as blocked ones are), the chain ends on side 1 and nothing lies onward."""
    obj, pose_set = quad
    side0, side1 = (pose_with_down(pose_set, side_down(QUADRILATERAL, side), atol=1e-6) for side in (0, 1))
    over1 = pivot_edge(pose_set.poses[side0], np.array([QUADRILATERAL[1][0], 0.0, QUADRILATERAL[1][1]]))
    over2 = pivot_edge(pose_set.poses[side1], np.array([QUADRILATERAL[2][0], 0.0, QUADRILATERAL[2][1]]))
    assert pose_set.poses[side0].edge_final_pose[over1] == side1 != pose_set.poses[side0].edge_momentum_pose[over1]
    for blocked in (False, True):
        tables = pose_tables(obj, pose_set)
        tables[2][side1][over2] = side1
        tables[3][side1][over2] = blocked
        ends, onwards = momentum_poses(*tables)
        assert (ends[side0][over1], onwards[side0][over1]) == (side1, side1), blocked


def test_released_at_its_apex_the_prism_rolls_on_in_pybullet_as_momentum_says(quad):
    """Turned 1 degree past the apex over vertex 1 and let go, the prism falls onto side 1
    and rolls on over vertex 2 onto side 2 (the quasi-static landing would stop on side 1)."""
    from pipeline.model.poses import settle
    from pipeline.studies.landing import FALL_TIME, apex_transform
    from pipeline.studies.pushsim import body_model, rest_on_table

    obj, pose_set = quad
    start = pose_set.poses[pose_with_down(pose_set, side_down(QUADRILATERAL, 0), atol=1e-6)]
    edge = pivot_edge(start, np.array([QUADRILATERAL[1][0], 0.0, QUADRILATERAL[1][1]]))
    assert start.edge_momentum_pose[edge] != start.edge_final_pose[edge]
    rest = rest_on_table(body_model(obj), apex_transform(start, edge), Config(), FALL_TIME)
    assert settle(pose_set, obj, rest[:3, :3]) == start.edge_momentum_pose[edge]


def test_landed_poses_apply_momentum_to_unblocked_edges_only(quad):
    obj, pose_set = quad
    topple = Config().topple
    for pose in pose_set.poses:
        with_momentum = landed_poses(pose, replace(topple, corrections="momentum").applied_corrections)
        np.testing.assert_array_equal(with_momentum, np.where(pose.edge_blocked, pose.edge_final_pose, pose.edge_momentum_pose))
        both = landed_poses(pose, replace(topple, corrections="momentum,rolling").applied_corrections)
        np.testing.assert_array_equal(both, np.where(pose.edge_blocked, pose.edge_rolled_pose, pose.edge_momentum_pose))
        thesis = landed_poses(pose, replace(topple, variant="robust", corrections="all").applied_corrections)
        np.testing.assert_array_equal(thesis, pose.edge_final_pose)


def test_apex_transform_turns_about_the_edge_to_just_past_the_apex():
    """The edge stays on the table and the centre of mass ends APEX_MARGIN past the edge's
    vertical plane: its horizontal offset outward is |c - e| sin(margin)."""
    from pipeline.studies.landing import APEX_MARGIN, apex_transform

    obj = box_object(size=(0.05, 0.08, 0.15))
    pose = stable_poses(obj).poses[0]
    for edge, (y0, y1) in enumerate(pose.base_edges):
        turned = apex_transform(pose, edge)
        back = turned @ np.linalg.inv(pose.transform)
        np.testing.assert_allclose((back[:3, :3] @ np.array([y0, y1]).T).T + back[:3, 3], [y0, y1], atol=1e-12)
        com = turned[:3, :3] @ obj.center_mass + turned[:3, 3]
        e = (y1 - y0) / np.linalg.norm(y1 - y0)
        outward = np.array([e[1], -e[0], 0.0])
        distance = np.linalg.norm(np.cross(com - y0, e))
        assert (com - y0) @ outward == pytest.approx(distance * np.sin(APEX_MARGIN), rel=1e-9)


def test_landing_summary_counts_each_predictor_against_physics():
    from pipeline.studies.landing import summarise

    rows = [  # physics, quasi-static, momentum at scales (0, 1)
        {"object": "a", "pose": 0, "edge": 0, "physics": 2, "quasi_static": 1, "momentum": [1, 2]},
        {"object": "a", "pose": 0, "edge": 1, "physics": 1, "quasi_static": 1, "momentum": [1, 1]},
        {"object": "b", "pose": 0, "edge": 0, "physics": 3, "quasi_static": 1, "momentum": [1, 2]},
        {"object": "b", "pose": 1, "edge": 0, "physics": -1, "quasi_static": 0, "momentum": [0, 0]},
    ]
    result = summarise(rows, scales=(0.0, 1.0))
    assert result["released"] == 4 and result["objects"] == 2 and result["outside_pose_set"] == 1
    assert result["momentum_differs"] == 2
    assert result["agreement"] == {"quasi_static": 0.25, "momentum x 0": 0.25, "momentum x 1": 0.5}
    assert result["agreement_where_they_differ"] == {"quasi_static": 0.0, "momentum": 0.5}
    assert "marginal_landings" not in result  # rows of a record written before C.18


def test_landing_summary_says_where_marginal_landings_rest():
    """Rows whose landing C.18 carries on: the share resting in the landing and in its onward pose."""
    from pipeline.studies.landing import summarise

    def row(obj, physics, landing, onward, carried):
        return {"object": obj, "pose": 0, "edge": 0, "physics": physics, "quasi_static": landing, "momentum": [landing],
                "onward": onward, "carried": carried}

    rows = [row("a", 3, 2, 3, True), row("a", 2, 2, 3, True), row("b", 3, 2, 3, True), row("b", 4, 2, 3, True),
            row("c", 3, 2, 3, False)]
    assert summarise(rows, scales=(1.0,))["marginal_landings"] == {
        "released": 4, "objects": 2, "rest_in_landing": 0.25, "rest_onward": 0.5}


def test_toppledb_landing_writes_a_record_that_reads_back(tmp_path, capsys):
    """One corpus object end to end: every row is a released unblocked topple of one of its
    poses, and the summary counts what the rows hold."""
    import json

    from pipeline.studies.landing import ENERGY_SCALES, ROW_FIELDS, main

    out = tmp_path / "landing.json"
    assert main(["--objects", "corpus", "--count", "1", "--workers", "1", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    rows = [dict(zip(record["row_fields"], row)) for row in record["rows"]]
    assert tuple(record["row_fields"]) == ROW_FIELDS and record["released"] == len(rows) > 0
    assert record["objects"] == 1 and not record["failed"]
    assert all(len(row["momentum"]) == len(ENERGY_SCALES) for row in rows)
    # C.18's verdict, edge by edge, is the engine's (``onward_shares`` over the pose's own tables).
    assert all(not row["carried"] or row["onward"] not in (row["momentum"][ENERGY_SCALES.index(1.0)], row["pose"])
               for row in rows)
    assert record["marginal_landings"]["released"] == sum(row["carried"] for row in rows)
    agree = np.mean([row["physics"] == row["quasi_static"] for row in rows])
    assert record["agreement"]["quasi_static"] == pytest.approx(agree, abs=1e-4)
    assert main(["--objects", str(tmp_path / "nowhere.csv")]) == 2
    assert "nowhere.csv: not 'corpus', 'heldout', a corpus list file or a directory" in capsys.readouterr().err


def test_toppledb_landing_releases_the_objects_of_a_list_file(tmp_path):
    """``--objects`` takes a corpus of one's own as toppledb play does: a standing box released over its edges."""
    import json

    from pipeline.studies.landing import main

    trimesh.creation.box(extents=(0.05, 0.08, 0.15)).export(tmp_path / "box.stl")
    (tmp_path / "mine.csv").write_text("object_id,path,mass\nbox,box.stl,0.25\n")
    out = tmp_path / "landing.json"
    assert main(["--objects", str(tmp_path / "mine.csv"), "--workers", "1", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    rows = [dict(zip(record["row_fields"], row)) for row in record["rows"]]
    assert record["objects"] == 1 and record["objects_mode"] == str(tmp_path / "mine.csv") and not record["failed"]
    assert rows and {row["object"] for row in rows} == {"box"}
