"""The data contract: documented columns, the docs in sync with the schemas, and the
HDF5 layout check that writer and verifier share."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from schema import SCHEMA_VERSION, TABLES, describe, file_schema, hdf5

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
