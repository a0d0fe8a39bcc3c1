"""The data contract: documented columns, the docs in sync with the schemas, and the
HDF5 layout check that writer and verifier share."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pytest
from pydantic import ValidationError

from schema import SCHEMA_VERSION, TABLES, describe, file_schema, hdf5
from schema.tables import PARTITION_KEY, PARTITIONED, column

DOCS = Path(__file__).resolve().parents[1] / "docs" / "DATASET.md"


def test_every_column_is_documented():
    assert SCHEMA_VERSION
    for name, schema in TABLES.items():
        assert schema.field("object_id").type == "string", name
        for field in schema:
            assert field.metadata and field.metadata.get(b"description"), f"{name}.{field.name}"
    assert "object_id" not in file_schema(TABLES["actions"]).names


def test_dataset_docs_show_the_current_schemas():
    text = DOCS.read_text()
    for name, schema in TABLES.items():
        assert describe(schema) in text, f"docs/DATASET.md is out of date for table {name}"
    for spec in hdf5.OBJECT_ARRAYS + hdf5.POSE_ARRAYS:
        assert spec.name in text
    assert f"It describes schema {SCHEMA_VERSION};" in text


def test_a_column_is_nullable_exactly_where_its_description_says_null():
    """Missing values are nulls, and only where the contract says so (``tables.column`` and ``xyz`` make a
    field non-nullable unless asked): the grasp of a pose without one and an action's numbers when it is not
    ok. A reader may rely on every other column being filled."""
    nullable = {name: [field.name for field in schema if field.nullable] for name, schema in TABLES.items()}
    assert nullable == {
        "objects": [],
        "poses": [f"grasp_{vector}_{axis}" for vector in ("point", "axis") for axis in "xyz"],
        "actions": ["p_topple", "mean_force", "q", "greedy"],
        "transitions": [],
    }
    for name, schema in TABLES.items():
        for field in schema:
            assert field.nullable == ("null" in field.metadata[b"description"].decode()), f"{name}.{field.name}"


def test_a_partition_files_schema_is_its_tables_without_the_partition_column():
    """``file_schema`` drops ``object_id`` (the directory name holds it) and keeps the rest in order with
    the table's metadata; a schema without it, such as a partition file's own, is returned as it is."""
    for name in PARTITIONED:
        table = TABLES[name]
        in_file = file_schema(table)
        assert in_file.names == [n for n in table.names if n != PARTITION_KEY]
        assert in_file.metadata == table.metadata
        assert file_schema(in_file).equals(in_file, check_metadata=True)


def test_describe_renders_undocumented_fields_empty_and_escapes_pipes():
    """A field without metadata gets empty unit and description cells; a ``|`` in a cell would end it
    early in Markdown, so it is escaped."""
    schema = pa.schema([pa.field("bare", pa.int32()), column("p", pa.float64(), "P(a | b)", "m")])
    assert describe(schema).splitlines() == [
        "| column | type | unit | description |",
        "| --- | --- | --- | --- |",
        "| `bare` | int32 |  |  |",
        "| `p` | double | m | P(a \\| b) |",
    ]


def test_hdf5_specs_are_the_layout_the_dataset_docs_give():
    """Each array's dtype and shape in ``hdf5.OBJECT_ARRAYS`` and ``POSE_ARRAYS``, and the root's attributes,
    are those of docs/DATASET.md's HDF5 block (what analysts read with h5py): fixed sizes as numbers, so a
    wrong length is refused, and every attribute, object_id included, required."""
    block = DOCS.read_text().split("## HDF5 arrays")[1].split("```")[1]
    documented = {}
    for line in block.splitlines():
        if line.startswith("/") and "(" in line:
            path, rest = line.split(None, 1)
            shape, dtype = rest.split(")", 1)
            sizes = [size.strip() for size in shape.strip("( ").split(",") if size.strip()]
            documented[path] = (tuple(int(size) if size.isdigit() else size for size in sizes), dtype.split()[0])
    attributes = block.splitlines()[1].split("attrs:")[1]
    assert hdf5.ATTRIBUTES == tuple(name.strip() for name in attributes.split(","))
    specs = {"/" + spec.name: spec for spec in hdf5.OBJECT_ARRAYS}
    specs |= {f"/{hdf5.pose_group(0)}/{spec.name}": spec for spec in hdf5.POSE_ARRAYS}
    assert {path: (spec.shape, str(spec.dtype)) for path, spec in specs.items()} == documented


def test_hdf5_layout_check_names_what_is_wrong(tmp_path):
    path = tmp_path / "x.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"schema_version": SCHEMA_VERSION, "object_id": "x", "n_poses": 1, "n_trials": 4})
        f["center_mass"] = np.zeros(3)
        f["hull/vertices"] = np.zeros((8, 3))
        f["hull/faces"] = np.zeros((12, 3), dtype=np.int64)  # wrong dtype
        group = f.create_group(hdf5.pose_group(0))
        group["transform"] = np.eye(4)
        group["down"] = np.zeros(3)
        group["base_edges"] = np.zeros((4, 2, 3))
        group["edge_final_pose"] = np.zeros(5, dtype=np.int32)  # E disagrees with base_edges
        group["edge_landed_pose"] = np.zeros(4, dtype=np.int32)
        group["edge_onward_pose"] = np.zeros(4, dtype=np.int32)
        group["edge_onward_share"] = np.zeros(4)
        group["edge_blocked"] = np.zeros(4, dtype=bool)
        group["apex_angle"] = np.zeros(4)
        group["outcomes"] = np.zeros((7, 4), dtype=np.int16)
    with h5py.File(path) as f:
        problems = hdf5.check_file(f, {"object_id": "x", "A": [7]})
        assert len(problems) == 2
        assert "/hull/faces: dtype int64, expected int32" in problems[0]
        assert "/poses/000/edge_final_pose: shape (5,)" in problems[1]
        assert hdf5.check_file(f, {"object_id": "y"}) == ["attribute object_id = 'x', expected 'y'"]
        assert any("outcomes" in p for p in hdf5.check_file(f, {"A": [6]}))


def _layout_file(path, n_poses: int = 1, edges: int = 4, actions: int = 7, trials: int = 4) -> None:
    """An HDF5 file that follows the layout, every pose with the same sizes."""
    with h5py.File(path, "w") as f:
        f.attrs.update({"schema_version": SCHEMA_VERSION, "object_id": "x", "n_poses": n_poses, "n_trials": trials})
        f["center_mass"] = np.zeros(3)
        f["hull/vertices"] = np.zeros((8, 3))
        f["hull/faces"] = np.zeros((12, 3), dtype=np.int32)
        for pose in range(n_poses):
            group = f.create_group(hdf5.pose_group(pose))
            for spec in hdf5.POSE_ARRAYS:
                sizes = {"E": edges, "A": actions, "T": trials}
                group[spec.name] = np.zeros([sizes.get(n, n) for n in spec.shape], dtype=spec.dtype)


def test_hdf5_layout_check_reports_every_problem_in_words(tmp_path):
    """``check_file`` names each missing attribute, every bad object array (not only the last one checked)
    and pose groups that are not the attribute's ``n_poses``, also when there is no ``poses`` group at all."""
    path = tmp_path / "x.h5"
    _layout_file(path, n_poses=2)
    with h5py.File(path) as f:
        assert hdf5.check_file(f, {"object_id": "x", "n_poses": 2, "A": [7, 7]}) == []
    with h5py.File(path, "a") as f:
        del f.attrs["n_trials"], f.attrs["schema_version"]
    with h5py.File(path) as f:
        assert hdf5.check_file(f, {"object_id": "x"}) == ["missing attribute schema_version", "missing attribute n_trials"]

    _layout_file(path, n_poses=1)
    with h5py.File(path, "a") as f:
        del f["center_mass"]
        del f["hull/vertices"]
        f["hull/vertices"] = np.zeros((8, 2))
        f.create_group(hdf5.pose_group(1))  # a group the attribute n_poses = 1 does not count
    with h5py.File(path) as f:
        assert hdf5.check_file(f, {"A": [7]}) == [
            "missing dataset /center_mass",
            "/hull/vertices: shape (8, 2), expected ('V', 3) with {'T': 4, 'V': 8}",
            "pose groups ['000', '001'], expected ['000']",
        ]

    _layout_file(path, n_poses=1)
    with h5py.File(path, "a") as f:
        del f["poses"]
    with h5py.File(path) as f:
        problems = hdf5.check_file(f, {"A": [7]})
    assert problems == ["pose groups [], expected ['000']"] + [f"missing dataset /poses/000/{spec.name}" for spec in hdf5.POSE_ARRAYS]
    _layout_file(path, n_poses=0)  # no pose, so no group "poses" either
    with h5py.File(path) as f:
        assert "poses" not in f and hdf5.check_file(f, {"n_poses": 0}) == []


def test_a_manifest_from_before_min_direction_z_reads_as_choosing_from_every_push():
    """Datasets built before ``mdp.min_direction_z`` let the policies choose any push: their
    manifests must read as -1, in the service (``schema.manifest``) and in the pipeline's studies
    (``Config.from_dict`` of the manifest's parameters, as ``policies_physics.dataset_config``)."""
    from pipeline.model.config import Config, MDPConfig
    from schema.manifest import Parameters

    old = Config().to_dict()
    del old["mdp"]["min_direction_z"]
    for key in ("choice_radius", "choice_angle", "choice_neighbours"):  # and the choice by neighbourhood ((12.15))
        del old["mdp"][key]
    del old["mdp"]["retry_failed"]  # and value iteration without retries (MODEL.md (12.9))
    del old["mdp"]["believe_failures"]  # and value iteration that believes failures (MODEL.md (12.13))
    del old["topple"]["down_map"], old["topple"]["down_map_z"]  # it predates the down map (MODEL.md C.15) too
    parameters = Parameters.model_validate(old)
    assert parameters.mdp.min_direction_z == -1.0
    assert parameters.mdp.retry_failed is True, "built counting on retries, read so"
    assert parameters.mdp.believe_failures is False, "built with the thesis's equation, read so"
    assert Config.from_dict(parameters.model_dump()).mdp.retry_failed is True
    without = Config().with_overrides({"mdp.retry_failed": False, "mdp.believe_failures": False}).to_dict()
    assert Parameters.model_validate(without).mdp.retry_failed is False
    assert Config.from_dict(parameters.model_dump()).mdp.min_direction_z == -1.0
    side = Config().with_overrides({"mdp.min_direction_z": -0.3}).to_dict()
    del side["mdp"]["budget_min_direction_z"]  # before stop 43 the budget chose as the policies did
    assert Parameters.model_validate(side).mdp.budget_min_direction_z == side["mdp"]["min_direction_z"] == -0.3
    assert Config.from_dict(Parameters.model_validate(side).model_dump()).mdp.budget_min_direction_z == -0.3
    side["mdp"]["budget_min_direction_z"] = None
    assert Parameters.model_validate(side).mdp.budget_min_direction_z == -0.3
    del old["mdp"]["after_failure_power"]  # and the after-failure map /plan serves (schema.retry)
    parameters = Parameters.model_validate(old)
    assert parameters.mdp.after_failure_power is None, "no map: the service serves no p_topple_given_failures"
    assert Config.from_dict(parameters.model_dump()).mdp == MDPConfig(
        min_direction_z=-1.0, believe_failures=False, choice_radius=0.0), \
        "the rest reads as before (the argmax, (12.15)); the map, unused by the build, as the default"
    assert Config.from_dict(parameters.model_dump()).topple.down_map == (), "built without the down map, read without it"
    assert Parameters.model_validate(Config().to_dict()).mdp.min_direction_z == Config().mdp.min_direction_z == -1.0
    before = Config().to_dict()
    for key in ("choice_radius", "choice_angle", "choice_neighbours"):  # before stop 45: the argmax
        del before["mdp"][key]
    assert Parameters.model_validate(before).mdp.choice_radius == 0.0
    assert Parameters.model_validate(Config().to_dict()).mdp.choice_radius == Config().mdp.choice_radius == 0.02


# --- schema.api: the request models' checks, at their limits -------------------------


def _refusal(function, *args) -> str:
    with pytest.raises(ValueError) as refused:
        function(*args)
    return str(refused.value)


def _rigid(rotation=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), translation=(0.0, 0.0, 0.0), last=(0.0, 0.0, 0.0, 1.0)):
    return [[*rotation[i], translation[i]] for i in range(3)] + [list(last)]


def test_a_rotation_is_accepted_up_to_its_tolerance_inclusive_and_huge_entries_are_refused_in_words():
    """``ROTATION_TOLERANCE`` is the largest |R^T R - I| entry accepted: exactly it passes (two columns
    whose dot product is exactly 1e-3), just past it does not; entries too large for a float (Python
    integers through the Python API) are no rotation rather than an OverflowError or a TypeError."""
    from schema.api import ROTATION_TOLERANCE, check_rigid, rotation_problem

    at_limit = [[1.0, ROTATION_TOLERANCE, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert rotation_problem(at_limit) is None
    assert check_rigid(_rigid(at_limit)) == _rigid(at_limit)
    past = [[1.0, 1.01 * ROTATION_TOLERANCE, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert rotation_problem(past) == "its columns are not orthonormal (largest |R^T R - I| entry 0.00101, at most 0.001)"
    assert rotation_problem([[10**400, 0, 0], [0, 1, 0], [0, 0, 1]]) == \
        "its columns are not orthonormal (largest |R^T R - I| entry inf, at most 0.001)"
    assert rotation_problem([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]) == "det = -1, expected +1 (a reflection?)"


def test_a_rigid_transforms_last_row_and_translation_are_refused_in_full_sentences():
    """The last row is [0, 0, 0, 1] within 1e-9 inclusive; the column-major hint only when the last
    column is [0, 0, 0, 1] (within the same 1e-9), not for any row-major matrix with a bad last row;
    the translation is bounded by ``MAX_TRANSLATION`` inclusive, its message naming the three coordinates."""
    from schema.api import MAX_TRANSLATION, check_rigid

    assert check_rigid(_rigid(translation=(0.5, 0.0, 0.0), last=(1e-9, 0.0, 0.0, 1.0)))[3] == [1e-9, 0.0, 0.0, 1.0]
    assert _refusal(check_rigid, _rigid(translation=(0.5, 0.0, 0.0), last=(2e-9, 0.0, 0.0, 1.0))) == \
        "the last row must be [0, 0, 0, 1], got [2e-09, 0.0, 0.0, 1.0]"
    hint = " (the last column is [0, 0, 0, 1]: is the matrix column-major? send it row by row)"
    # Row-major with a translation and a bad last row: no hint, the last column is not [0, 0, 0, 1].
    assert _refusal(check_rigid, _rigid(translation=(0.5, 0.0, 0.0), last=(0.0, 0.0, 0.5, 1.0))) == \
        "the last row must be [0, 0, 0, 1], got [0.0, 0.0, 0.5, 1.0]"
    # Column-major (the translation in the last row): the hint, also with a last column off by exactly 1e-9.
    assert _refusal(check_rigid, _rigid(translation=(1e-9, 0.0, 0.0), last=(0.5, 0.0, 0.0, 1.0))) == \
        "the last row must be [0, 0, 0, 1], got [0.5, 0.0, 0.0, 1.0]" + hint
    assert _refusal(check_rigid, _rigid(translation=(2e-9, 0.0, 0.0), last=(0.5, 0.0, 0.0, 1.0))) == \
        "the last row must be [0, 0, 0, 1], got [0.5, 0.0, 0.0, 1.0]"
    assert check_rigid(_rigid(translation=(MAX_TRANSLATION, -MAX_TRANSLATION, 0.0)))[0][3] == MAX_TRANSLATION
    assert _refusal(check_rigid, _rigid(translation=(0.0, 0.0, -2 * MAX_TRANSLATION))) == \
        "the translation [0.0, 0.0, -2000000.0] is beyond 1e+06 m: send metres in the table frame"


def test_request_text_with_a_lone_surrogate_is_refused_in_words():
    from schema.api import TransitionQuery, check_text

    assert check_text("random_001") == "random_001" and check_text("bo\u00eete \U0001f4e6") == "bo\u00eete \U0001f4e6"
    message = "is not Unicode text: it holds a lone UTF-16 surrogate (\\ud800-\\udfff)"
    assert _refusal(check_text, "a\ud800") == message
    with pytest.raises(ValidationError) as refused:
        TransitionQuery.model_validate({"object_id": "x\udfff", "pose": 0, "action": 0})
    assert refused.value.errors()[0]["msg"] == "Value error, " + message


def test_known_keys_drops_keys_it_does_not_know_and_leaves_other_values_to_the_type():
    """An answer's map keyed by a closed vocabulary keeps the keys it knows (a newer service's new
    policy or status is dropped); a value that is no map is refused by the type, not by the validator."""
    from typing import Annotated, Literal

    from pydantic import TypeAdapter

    from schema.api import PoseDetail, known_keys

    adapter = TypeAdapter(Annotated[dict[Literal["a", "b"], int], known_keys(("a", "b"))])
    assert adapter.validate_python({"a": 1, "c": 3, "b": 2}) == {"a": 1, "b": 2}
    assert adapter.validate_python({}) == {}
    with pytest.raises(ValidationError, match="valid dictionary"):
        adapter.validate_python([("a", 1)])
    detail = {"object_id": "o", "pose": 0, "probability": 1.0, "down": [0, 0, -1], "transform": _rigid(), "height": 0.1,
              "com_height": 0.05, "v_s": 0.5, "grasp": None, "v_t": 0.5, "n_actions": 0,
              "policies": {"greedy": {"action": None, "value": 0.5}, "a_newer_policy": {"action": 1, "value": 0.9}},
              "action_counts": {"ok": 3, "a_newer_status": 1}}
    read = PoseDetail.model_validate(detail)
    assert list(read.policies) == ["greedy"] and read.action_counts == {"ok": 3}


def test_a_quaternion_is_normalised_before_it_is_a_rotation():
    """``quaternion_matrix`` normalises first: a quaternion the request accepts within
    ``QUATERNION_TOLERANCE`` of unit, or any positive multiple, gives an orthonormal matrix."""
    from schema.api import QUATERNION_TOLERANCE, RosPose, quaternion_matrix, rotation_problem

    assert np.array_equal(quaternion_matrix(0.0, 0.0, 0.0, 2.0), np.eye(3))
    half = np.sqrt(0.5)
    assert np.allclose(quaternion_matrix(0.0, 0.0, 3 * half, 3 * half), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    scale = 1 + 0.9 * QUATERNION_TOLERANCE
    pose = RosPose.model_validate({"position": {"x": 0.4, "y": -0.1, "z": 0.02}, "frame_id": "world",
                                   "orientation": {"x": 0.1 * scale, "y": -0.2 * scale, "z": 0.3 * scale, "w": np.sqrt(0.86) * scale}})
    matrix = pose.matrix()
    assert np.allclose(matrix[:3, :3].T @ matrix[:3, :3], np.eye(3), atol=1e-15)
    assert rotation_problem(matrix[:3, :3].tolist()) is None and np.linalg.det(matrix[:3, :3]) == pytest.approx(1.0, abs=1e-14)
    assert matrix[:3, 3].tolist() == [0.4, -0.1, 0.02] and matrix[3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_a_heap_objects_observed_pose_from_either_form():
    """``HeapObject.observed``: the 4x4 as sent, or the ROS pose's matrix; exactly one of them."""
    from schema.api import HeapObject

    sent = _rigid(((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), (0.1, -0.05, 0.02))
    observed = HeapObject.model_validate({"object_id": "o", "pose": sent}).observed()
    assert observed.dtype == np.float64 and observed.tolist() == sent
    half = float(np.sqrt(0.5))
    ros = {"position": {"x": 0.1, "y": -0.05, "z": 0.02}, "orientation": {"x": 0.0, "y": 0.0, "z": half, "w": half}, "frame_id": "world"}
    assert np.allclose(HeapObject.model_validate({"object_id": "o", "ros_pose": ros}).observed(), sent, atol=1e-15)
    for both_or_neither in ({"object_id": "o"}, {"object_id": "o", "pose": sent, "ros_pose": ros}):
        with pytest.raises(ValidationError, match="give exactly one of pose"):
            HeapObject.model_validate(both_or_neither)


def test_heights_at_the_tables_edge_and_past_a_thousand_km():
    """``rests_on_table`` includes its edge, ``HEIGHT_ROUNDING`` too; ``height_in_mm`` compares the height
    with the tolerance as printed (four decimals where one would read as it), and from 1e9 mm (z at
    ``MAX_TRANSLATION``) prints four figures."""
    from schema.api import HEIGHT_ROUNDING, MAX_TRANSLATION, height_in_mm, rests_on_table

    assert rests_on_table(0.005 + HEIGHT_ROUNDING, 0.005) and rests_on_table(-(0.01 + HEIGHT_ROUNDING), 0.01)
    assert height_in_mm(0.1001, 0.1) == "100.1", "100.1 mm is not the tolerance's 100.0"
    assert height_in_mm(0.10004, 0.1) == "100.0400"
    assert height_in_mm(MAX_TRANSLATION, 0.005) == "1e+9" and height_in_mm(-MAX_TRANSLATION, 0.005) == "1e+9"
    assert height_in_mm(999_999.9, 0.005) == "999999900.0"


def _errors(model, value) -> list[tuple[tuple, str]]:
    with pytest.raises(ValidationError) as refused:
        model.model_validate(value)
    return [(error["loc"], error["msg"]) for error in refused.value.errors()]


def test_a_quaternion_is_unit_within_its_tolerance_on_either_side():
    """|q| within ``QUATERNION_TOLERANCE`` of 1, short of it as well as past it: a quaternion of norm 0.5
    is as much a client bug as one of norm 2."""
    from schema.api import Quaternion

    for w in (0.9991, 1.0009):
        assert Quaternion(x=0.0, y=0.0, z=0.0, w=w).w == w
    for w, shown in ((0.5, "0.5"), (0.9989, "0.9989"), (1.0011, "1.0011"), (-2.0, "2")):
        assert _errors(Quaternion, {"x": 0.0, "y": 0.0, "z": 0.0, "w": w}) == \
            [((), f"Value error, the orientation quaternion is not unit: |q| = {shown} (tolerance 0.001)")]


def test_a_plan_requests_combinations_are_refused_by_the_model_itself():
    """What ``PlanRequest`` refuses before the service looks at the dataset: the 422's own words, not a
    later check's (the routes refuse a bad index too, but only the model says why max_height cannot)."""
    from schema.api import MAX_FAILED_ACTIONS, MAX_PUSHES_LEFT, PlanRequest

    base = {"object_id": "o", "pose": _rigid()}
    assert _errors(PlanRequest, {**base, "failed_actions": [0], "policy": "max_height"}) == [((), (
        "Value error, max_height has one push per pose and nothing to choose after it fails; give failed_actions "
        "with greedy or value_iteration"))]
    assert _errors(PlanRequest, {**base, "failed_actions": [3, -1]}) == \
        [(("failed_actions", 1), "Input should be greater than or equal to 0")]
    assert PlanRequest.model_validate({**base, "failed_actions": [0], "policy": "greedy"}).failed_actions == [0]
    assert len(PlanRequest.model_validate({**base, "failed_actions": list(range(MAX_FAILED_ACTIONS))}).failed_actions) == MAX_FAILED_ACTIONS
    assert _errors(PlanRequest, {**base, "failed_actions": list(range(MAX_FAILED_ACTIONS + 1))})[0][0] == ("failed_actions",)
    assert _errors(PlanRequest, {**base, "pushes_left": 2, "policy": "greedy"}) == [((), (
        "Value error, pushes_left plans by value iteration for a budget; it cannot be combined with policy greedy"))]
    assert [PlanRequest.model_validate({**base, "pushes_left": n}).pushes_left for n in (1, MAX_PUSHES_LEFT)] == [1, MAX_PUSHES_LEFT]
    assert _errors(PlanRequest, {**base, "pushes_left": 0}) == [(("pushes_left",), "Input should be greater than or equal to 1")]
    assert _errors(PlanRequest, {"object_id": "o"}) == \
        [((), "Value error, give exactly one of pose (a 4x4 matrix) and ros_pose (position, orientation, frame_id)")]
    read = PlanRequest.model_validate(base)
    assert (read.policy, read.pushes_left, read.failed_actions, read.ros_pose) == ("value_iteration", None, [], None)


def test_a_ros_positions_coordinates_are_bounded_both_ways():
    """Each of x, y and z within +/- ``MAX_TRANSLATION`` m, the limit included, as the 4x4 form's translation."""
    from schema.api import MAX_TRANSLATION, Point

    assert Point(x=-MAX_TRANSLATION, y=MAX_TRANSLATION, z=-MAX_TRANSLATION).z == -MAX_TRANSLATION
    for name in "xyz":
        for value, bound in ((-1.5 * MAX_TRANSLATION, "greater than or equal to -1000000"),
                             (1.5 * MAX_TRANSLATION, "less than or equal to 1000000")):
            assert _errors(Point, {"x": 0.0, "y": 0.0, "z": 0.0, name: value}) == [((name,), f"Input should be {bound}")]


def test_a_heap_requests_defaults_and_strict_bin_lengths():
    """``HeapPlanRequest`` omitted fields: the default tote, boundary_shear (the policy that ran on the
    robot), seed 0; a bin length is a JSON number, not true or a string, and finite."""
    from schema.api import BIN_TOLERANCE, MAX_SEED, HeapBin, HeapPlanRequest

    assert BIN_TOLERANCE == 0.005, "docs/SERVICE.md: an object reaching more than 5 mm past a wall is a 409"
    # The largest seed is JavaScript's Number.MAX_SAFE_INTEGER: the float64 it reads as is its own alone (one past
    # it, 2**53, is also 2**53 + 1 read as a float64).
    assert float(MAX_SEED) == MAX_SEED and float(MAX_SEED + 1) == MAX_SEED + 1 == float(MAX_SEED + 2)
    one = {"object_id": "o", "pose": _rigid()}
    read = HeapPlanRequest.model_validate({"objects": [one]})
    assert (read.policy, read.seed, read.bin) == ("boundary_shear", 0, HeapBin(length=0.5, width=0.4, height=0.15, wall=0.01))
    assert HeapPlanRequest.model_validate({"objects": [one], "seed": MAX_SEED}).seed == MAX_SEED
    assert _errors(HeapPlanRequest, {"objects": [one], "seed": -1}) == [(("seed",), "Input should be greater than or equal to 0")]
    for value, message in ((True, "Input should be a valid number"), ("0.5", "Input should be a valid number"),
                           (float("inf"), "Input should be a finite number")):
        assert _errors(HeapBin, {"length": value}) == [(("length",), message)]
