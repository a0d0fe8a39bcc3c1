"""Command line: parameter precedence and one-line errors for bad input (no compute)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from pipeline.cli import main, make_config, parser


def test_parameters_come_from_defaults_toml_set_then_flags(tmp_path):
    toml = tmp_path / "params.toml"
    toml.write_text("seed = 7\n[topple]\nn_trials = 50\nmu_table_mean = 0.5\n[contacts]\nn_contacts = 200\n")
    args = parser().parse_args(
        ["dataset", "--config", str(toml), "--set", "topple.n_trials=20", "--set", "mdp.gamma=0.9", "--contacts", "30"]
    )
    config = make_config(args)
    assert config.seed == 7
    assert config.topple.mu_table_mean == 0.5
    assert config.topple.n_trials == 20, "--set overrides the TOML file"
    assert config.mdp.gamma == 0.9
    assert config.contacts.n_contacts == 30, "dedicated flags override everything"
    assert config.topple.variant == "robust"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["dataset", "--set", "topple.n_trials"], "--set expects SECTION.KEY=VALUE"),
        (["dataset", "--set", "topple.nope=1"], "unknown config key 'topple.nope'"),
        (["dataset", "--set", "topple.n_trials=many"], "expects int"),
        (["dataset", "--config", "/no/such.toml"], "config file not found"),
        (["dataset", "--corpus", "/no/such/corpus", "--out", "{tmp}/out"], "corpus not found"),
        (["corpus", "--set", "suction.cup_radius=wide"], "expects float"),
    ],
)
def test_bad_input_is_one_line_with_status_2(tmp_path, capsys, argv, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err
    assert err.count("\n") == 1


def test_bad_toml_is_reported(tmp_path, capsys):
    toml = tmp_path / "bad.toml"
    toml.write_text("[topple\n")
    assert main(["dataset", "--config", str(toml)]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    toml.write_text("[topple]\nvariant = 'fast'\n")
    assert main(["dataset", "--config", str(toml)]) == 2
    assert "unknown variant 'fast'" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["dataset", "--limit", "0"], ["dataset", "--variant", "best"], ["dataset", "--workers", "x"]])
def test_argparse_rejects_bad_values(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_verify_of_a_missing_dataset_fails(tmp_path, capsys):
    assert main(["verify", str(tmp_path / "nothing")]) == 1
    assert "no such directory" in capsys.readouterr().out
    assert main(["verify", str(tmp_path)]) == 1
    assert "no manifest.json" in capsys.readouterr().out


def test_module_entry_point_prints_no_traceback(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "pipeline", "dataset", "--corpus", str(tmp_path / "missing.csv")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert run.returncode == 2
    assert run.stderr.startswith("error: corpus not found") and "Traceback" not in run.stderr


FAST = ["--contacts", "10", "--trials", "2", "--set", "suction.n_candidates=5", "--set", "suction.n_samples=3",
        "--no-progress", "--workers", "1"]


def test_millimetre_meshes_fail_with_a_unit_hint_until_units_are_given(tmp_path, capsys):
    import trimesh

    meshes = tmp_path / "cad"
    meshes.mkdir()
    for name, size in (("bracket", [120.0, 60.0, 30.0]), ("block", [50.0, 40.0, 90.0])):
        trimesh.creation.box(size).export(meshes / f"{name}.stl")
    (meshes / "noise.obj").write_bytes(bytes(range(256)) * 4)
    out = tmp_path / "out"

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), *FAST]) == 1, "every object failed"
    captured = capsys.readouterr()
    assert "error: every object failed (3)" in captured.err
    assert "2  too large for a tabletop (block, bracket); try --units mm" in captured.out
    assert "1  cannot read # (noise)" in captured.out

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), "--units", "mm", "--mass", "0.2", *FAST]) == 0
    captured = capsys.readouterr()
    assert "objects   2 (3 computed, 0 reused), failed 1" in captured.out
    assert "failed    noise: cannot read noise.obj: no triangles, not a valid OBJ file" in captured.out

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), "--units", "mm", "--mass", "0.2", "--strict", *FAST]) == 1
    assert "--strict: noise:" in capsys.readouterr().err
