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
