"""Command line: parameter precedence and one-line errors for bad input (no compute)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time

import pytest

from pipeline.build.dataset import staging_dir
from pipeline.cli import main, make_config, parser
from pipeline.model.config import Config, parameter_table


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
    assert config.topple.variant == "corrected", "the default variant"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["dataset", "--set", "topple.n_trials"], "--set expects SECTION.KEY=VALUE"),
        (["dataset", "--set", "topple.nope=1"], "unknown config key 'topple.nope'"),
        (["dataset", "--set", "bogus.key=1"],
         "unknown config section 'bogus' in 'bogus.key' (sections: contacts, mdp, mesh, poses, suction, topple)"),
        (["dataset", "--set", "topple.n_trials.x=1"], "config key 'topple.n_trials' is a value, not a section"),
        (["dataset", "--set", "topple=oops"], "config key 'topple' is a section, not a value: set one of its keys, e.g. topple."),
        (["dataset", "--set", "topple.mu_table_mean=nan"], "config key 'topple.mu_table_mean' must be a finite number, got 'nan'"),
        (["dataset", "--set", "mdp.gamma=inf"], "config key 'mdp.gamma' must be a finite number, got 'inf'"),
        (["dataset", "--set", "topple.boosted_map=nonexist"],
         ("topple.boosted_map 'nonexist': no packaged map of that name; a value ending in .json is a file's path, "
          "any other value names a packaged map (boosted_map_s41); '' sets none")),
        (["dataset", "--set", "topple.boosted_map={tmp}/maps/x.json"],
         "topple.boosted_map '{tmp}/maps/x.json': no such file {tmp}/maps/x.json; a value ending in .json"),
        (["dataset", "--set", "topple.n_trials=many"], "expects int"),
        (["dataset", "--config", "/no/such.toml"], "config file not found"),
        (["dataset", "--corpus", "/no/such/corpus", "--out", "{tmp}/out"], "corpus not found"),
        (["corpus", "--set", "suction.cup_radius=wide"], "expects float"),
        (["dataset", "--set", "contacts.n_contacts=0"], "config key 'contacts.n_contacts' must be in [1, 100000], got '0'"),
        (["dataset", "--set", "topple.mu_table_mean=-3"], "config key 'topple.mu_table_mean' must be >= 0"),
        (["dataset", "--seed", "-2"], "config key 'seed' must be >= 0"),
        (["dataset", "--contacts", "0"], "config key 'contacts.n_contacts' must be in [1, 100000], got 0"),
        (["dataset", "--trials", "0"], "config key 'topple.n_trials' must be >= 1, got 0"),
        (["dataset", "--out", "{tmp}/a_file/out"], "cannot create output directory {tmp}/a_file/out: Not a directory"),
        (["dataset", "--out", "{tmp}/a_file"], "cannot create output directory {tmp}/a_file: File exists"),
        (["dataset", "--corpus", "default", "--units", "mm", "--out", "{tmp}/out"], "apply to a directory of meshes"),
    ],
)
def test_bad_input_is_one_line_with_status_2(tmp_path, capsys, argv, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    message = message.replace("{tmp}", str(tmp_path))
    (tmp_path / "a_file").write_text("not a directory")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err
    assert err.count("\n") == 1
    assert "Errno" not in err and "presets/" not in err, "no errno text, no path inside the package"


def test_bad_toml_is_reported(tmp_path, capsys):
    toml = tmp_path / "bad.toml"
    toml.write_text("[topple\n")
    assert main(["dataset", "--config", str(toml)]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    toml.write_text("[topple]\nvariant = 'fast'\n")
    assert main(["dataset", "--config", str(toml)]) == 2
    assert "unknown variant 'fast'" in capsys.readouterr().err
    # A section that is no table is refused, not replaced by defaults (contacts.push_depth once filled it
    # with the stroke alone), and a fraction is no count of trials (int() would cut 1.5 to 1).
    toml.write_text("topple = 'whatever'\n[contacts]\npush_depth = 0.03\n")
    assert main(["dataset", "--config", str(toml)]) == 2
    assert "config section 'topple' must be a table" in capsys.readouterr().err
    for value in ("1.5", "99.99"):
        toml.write_text(f"[topple]\nn_trials = {value}\n")
        assert main(["dataset", "--config", str(toml)]) == 2
        assert f"config key 'topple.n_trials' expects int, got {value}" in capsys.readouterr().err
    toml.write_text("[topple]\nn_trials = 30.0\n")  # a whole number written as a float is still the count
    assert Config.from_toml(toml).topple.n_trials == 30


@pytest.mark.parametrize("argv", [["dataset", "--limit", "0"], ["dataset", "--variant", "best"], ["dataset", "--workers", "x"]])
def test_argparse_rejects_bad_values(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert "error:" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["dataset", "--out", ""], ["dataset", "--out", "  "], ["dataset", "--corpus", ""], ["verify", ""], ["policies", ""],
    ["add", "", "part.stl"], ["add", "data/dataset", ""], ["corpus", "--out", ""], ["heaps", "--out", ""],
    ["play", "--out", ""], ["figures", "part.stl", "--out", ""], ["serve", "--frame-id", ""],
])
def test_an_empty_path_is_refused_not_read_as_the_working_directory(argv, tmp_path, monkeypatch, capsys):
    # --out "" from an unset shell variable once built a whole dataset into the working directory.
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert "an empty " in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_verify_of_a_path_that_is_no_dataset_is_a_usage_error(tmp_path, capsys):
    """Exit 2, as every command gives a bad path; 1 is kept for a dataset that fails its checks."""
    assert main(["verify", str(tmp_path / "nothing")]) == 2
    assert f"error: {tmp_path / 'nothing'}: no such directory" in capsys.readouterr().err
    assert main(["verify", str(tmp_path)]) == 2
    assert "no manifest.json: not a toppledb dataset" in capsys.readouterr().err


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
    out = tmp_path / "new" / "out"

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), *FAST]) == 1, "every object failed"
    captured = capsys.readouterr()
    assert "error: every object failed (3)" in captured.err
    assert "2  too large for a tabletop (block, bracket); try --units mm" in captured.out
    assert "1  cannot read <file> (noise)" in captured.out, "the file name masked, and said to be one"
    # A dataset's corpus can give units in a sidecar or a list's column too: its hint says so.
    assert 'failed    block: too large for a tabletop' in captured.out
    assert 'use --units mm (or units = "mm" in corpus.toml, or a scale column)' in captured.out
    assert not (tmp_path / "new").exists(), "a run where every object failed writes nothing, not even the directories"

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), "--units", "mm", "--mass", "0.2", *FAST]) == 0
    captured = capsys.readouterr()
    assert "objects   2 (3 computed, 0 reused), failed 1" in captured.out
    assert "failed    noise: cannot read noise.obj: no triangles, not a valid OBJ file" in captured.out

    # Rebuilt with --force but without --units: every object fails, and the finished dataset stays whole.
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".lock"}
    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), "--force", *FAST]) == 1
    assert f"Nothing was written: {out} is as it was" in capsys.readouterr().err
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".lock"} == before
    assert not staging_dir(out).exists()

    assert main(["dataset", "--corpus", str(meshes), "--out", str(out), "--units", "mm", "--mass", "0.2", "--strict", *FAST]) == 1
    assert "--strict: noise:" in capsys.readouterr().err
    assert not staging_dir(out).exists(), "a failed --strict run leaves no empty staging directory beside --out"


def test_ids_derived_otherwise_than_their_file_names_are_said_before_the_build(tmp_path, capsys):
    import trimesh

    meshes = tmp_path / "parts"
    meshes.mkdir()
    for name in ("3can.STL", "part.stl", "part.obj", "lid.stl"):  # mm-sized: each fails at once, nothing computed
        trimesh.creation.box([50.0, 40.0, 90.0]).export(meshes / name)
    assert main(["dataset", "--corpus", str(meshes), "--out", str(tmp_path / "out"), *FAST]) == 1
    err = capsys.readouterr().err
    assert "ids: 2 meshes named otherwise than the file: 3can.STL -> obj_3can, part.stl -> part-2" in err
    assert "lid.stl ->" not in err and "(the manifest's corpus lists every id)" in err


def test_failures_group_by_reason_with_file_names_and_numbers_named_not_hidden():
    from pipeline.build.dataset import failure_groups

    groups = failure_groups([
        ("a", "a: cannot read a.stl: no triangles"), ("b", "b: cannot read parts/b.obj: bad header"),
        ("c", "c: found 3 bodies (glued)"), ("d", "d: found 12 bodies"), ("e", "e: nearly a sphere"),
    ])
    assert groups == {"cannot read <file>": ["a", "b"], "found <n> bodies": ["c", "d"], "nearly a sphere": ["e"]}


def test_version_prints_the_package_and_schema_versions(capsys):
    from schema.version import CODE_VERSION, SCHEMA_VERSION

    with pytest.raises(SystemExit) as exit:
        main(["--version"])
    assert exit.value.code == 0
    assert capsys.readouterr().out == f"toppledb {CODE_VERSION} (dataset schema {SCHEMA_VERSION})\n"


def test_help_shows_defaults_set_keys_and_examples(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")  # argparse wraps to the terminal width
    with pytest.raises(SystemExit):
        main(["dataset", "--help"])
    text = capsys.readouterr().out
    assert "(contacts.n_contacts, default: 1000)" in text and "(default: data/dataset)" in text
    assert "examples:" in text and "--units mm" in text and "corpus.toml" in text
    for key, value, accepted in parameter_table():
        assert key in text, f"--set key {key} missing from --help"
    assert "topple.mu_table_mean" in text and ">= 0" in text
    assert "--config FILE.toml|PRESET" in text and "a preset by name: thesis (e.g. --config thesis" in text
    assert "toppledb dataset --config thesis" in text, "an example"


SLOW_WORKERS = """\
import os
if os.environ.get("TOPPLEDB_TEST_SLOW_OBJECTS"):  # every interpreter, loky workers included
    import time
    import pipeline.model.evaluation as evaluation

    def process_object(spec, config):
        time.sleep(600)

    evaluation.process_object = process_object
"""


def loky_workers(parent) -> list:
    """Worker processes (not loky's resource tracker, which lives as long as its parent).  A child
    that exits while it is listed (a zombie until reaped, or gone) is no worker: on a busy machine the
    listing meets such children, and their command line cannot be read."""
    import psutil

    workers = []
    for child in parent.children(recursive=True):
        try:
            command = " ".join(child.cmdline())
        except (psutil.ZombieProcess, psutil.NoSuchProcess):
            continue
        if "loky" in command and "resource_tracker" not in command:
            workers.append(child)
    return workers


def test_sigterm_stops_the_workers(tmp_path):
    """SIGTERM to the parent alone (a job scheduler's stop) used to orphan the workers."""
    psutil = pytest.importorskip("psutil")
    (tmp_path / "sitecustomize.py").write_text(SLOW_WORKERS)
    corpus = tmp_path / "corpus.csv"
    corpus.write_text("".join(
        ["object_id,source,path,scale\n"]
        + [f"r{i},pybullet_data/random_urdfs,random_urdfs/00{i}/00{i}.obj,0.015\n" for i in range(3)]
    ))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]),
           "TOPPLEDB_TEST_SLOW_OBJECTS": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "dataset", "--corpus", str(corpus), "--out", str(tmp_path / "out"),
         "--workers", "2", "--no-progress"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True,
    )
    try:
        parent = psutil.Process(process.pid)
        deadline = time.monotonic() + 120
        workers = []
        while len(workers) < 2 and process.poll() is None and time.monotonic() < deadline:
            workers = loky_workers(parent)
            time.sleep(0.1)
        assert len(workers) >= 2, "the loky workers never started"
        time.sleep(1.0)  # let them pick up their tasks
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 130
        gone, alive = psutil.wait_procs(workers, timeout=20)
        assert not alive, f"workers left running: {[p.pid for p in alive]}"
        stderr = process.stderr.read()
        assert "interrupted; workers stopped" in stderr and "Traceback" not in stderr, stderr[-2000:]
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        process.stderr.close()


def test_an_interrupted_fan_out_stops_its_workers():
    """Ctrl-C (SIGINT) reaches the parent as KeyboardInterrupt while it waits for results;
    leaving the loop must kill the workers still busy, without joblib's warning."""
    import warnings

    psutil = pytest.importorskip("psutil")
    from pipeline.build import fanout

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # joblib's "tasks ... cancelled" would fail the test
        with pytest.raises(KeyboardInterrupt):
            with contextlib.closing(fanout.map_unordered(time.sleep, [(0,), (120,), (120,)], workers=2)) as results:
                for _ in results:
                    workers = loky_workers(psutil.Process())
                    raise KeyboardInterrupt
    assert len(workers) == 2
    gone, alive = psutil.wait_procs(workers, timeout=20)
    assert not alive, f"workers left running: {[p.pid for p in alive]}"


def test_a_study_ends_with_its_text_and_its_record_or_one_line_saying_why_not(tmp_path, capsys):
    import json

    from pipeline.cli import print_and_record

    record = {"a": [1, 2], "b": None}
    assert print_and_record("the text", record, tmp_path / "r.json") == 0
    assert capsys.readouterr().out == "the text\n"
    assert json.loads((tmp_path / "r.json").read_text()) == record
    assert (tmp_path / "r.json").read_text() == json.dumps(record, indent=1) + "\n"
    assert print_and_record("again", record, None) == 0 and capsys.readouterr().out == "again\n"
    (tmp_path / "a_file").write_text("")
    assert print_and_record("text", record, tmp_path / "a_file" / "r.json") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: cannot write {tmp_path / 'a_file' / 'r.json'}: ") and len(err.strip().splitlines()) == 1


def test_a_long_run_refuses_an_output_it_could_not_write_before_it_plays(tmp_path, capsys):
    from pipeline.cli import output_problem
    from pipeline.studies import oracle_policy, policies_physics, robust_policy

    (tmp_path / "a_file").write_text("")
    (tmp_path / "a_dir").mkdir()
    # Missing parents are fine (the atomic writers create them); an existing file may be replaced.
    assert output_problem(None, tmp_path / "r.json", tmp_path / "a_file", tmp_path / "new" / "deeper" / "r.json") is None
    assert output_problem(tmp_path / "a_dir", tmp_path / "new_dir", directory=True) is None
    in_a_file = tmp_path / "a_file" / "sub" / "r.json"
    assert output_problem(in_a_file) == f"cannot write {in_a_file}: {tmp_path / 'a_file'} is not a directory"
    assert output_problem(tmp_path / "r.json", tmp_path / "a_dir") == f"cannot write {tmp_path / 'a_dir'}: it is a directory"
    assert output_problem(tmp_path / "a_file", directory=True) == f"cannot write {tmp_path / 'a_file'}: it is not a directory"
    # The dataset does not exist either: the output is what is reported, so nothing was played first.
    missing = str(tmp_path / "no_dataset")
    bad = str(tmp_path / "a_file" / "out")
    for study, args in [(robust_policy.main, [missing, "--trials-out", bad]), (robust_policy.main, [missing, "--pushes", bad]),
                        (robust_policy.main, [missing, "--json", bad]), (oracle_policy.main, [missing, "--json", bad]),
                        (oracle_policy.main, [missing, "--log", bad]), (policies_physics.main, [missing, "--json", bad]),
                        (policies_physics.main, [missing, "--log", bad])]:
        assert study(args) == 2
        assert capsys.readouterr().err == f"error: cannot write {bad}: {tmp_path / 'a_file'} is not a directory\n"


def test_every_command_refuses_an_output_it_could_not_write_before_it_reads_anything(tmp_path, capsys):
    from pipeline.cli import main

    (tmp_path / "a_file").write_text("")
    bad = str(tmp_path / "a_file" / "x.json")
    no_log, no_dataset = str(tmp_path / "no_log"), str(tmp_path / "no_dataset")
    cases = {
        ("report", no_log, "--out", bad): f"cannot write {bad}: ",
        ("report", no_log, "--plot", str(tmp_path / "p.txt")): "no format is named 'txt'; name it .png, .pdf or .svg",
        ("report", no_log, "--plot", str(tmp_path / "p")): "no suffix names its format",
        ("calibrate", no_log, "--out", bad): f"cannot write {bad}: ",
        ("calibrate", no_log, "--json", bad): f"cannot write {bad}: ",
        ("recalibrate", no_log, "--json", bad): f"cannot write {bad}: ",
        ("recalibrate", no_log, "--boosted", "--fold-maps", str(tmp_path / "a_file")): "it is not a directory",
        ("landing", "--json", bad): f"cannot write {bad}: ",
        ("policies", no_dataset, "--plot", str(tmp_path / "p.txt")): "no format is named 'txt'",
        ("policies", no_dataset, "--plot", str(tmp_path / "a_file" / "p.png")): "is not a directory",
    }
    for argv, message in cases.items():
        assert main(list(argv)) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and len(err.strip().splitlines()) == 1, (argv, err)
    # The studies that write reports by default write them under data/, not over the committed reports/.
    for command, default in [("report", "data/reports/validation.json"), ("calibrate", "data/reports/calibration.json"),
                             ("recalibrate", "data/reports/recalibrated.toml")]:
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert default in capsys.readouterr().out.replace("\n", " ").replace("  ", " ")


def test_what_the_file_system_refuses_after_the_checks_is_one_line(monkeypatch, capsys):
    from pipeline import cli
    from pipeline.studies import landing

    def full_disk(argv):
        raise OSError(28, "No space left on device", "/data/out.json")

    monkeypatch.setattr(landing, "main", full_disk)
    assert cli.main(["landing"]) == 2
    assert capsys.readouterr().err == "error: /data/out.json: No space left on device\n"

    def no_file(argv):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(landing, "main", no_file)
    assert cli.main(["landing"]) == 2
    assert capsys.readouterr().err == "error: No space left on device\n", "no file named, none made up"


def test_calibrate_bench_writes_nothing_so_its_outputs_are_not_checked(tmp_path, monkeypatch, capsys):
    from pipeline import cli
    from pipeline.studies import calibrate

    monkeypatch.setattr(calibrate, "bench", lambda *args: {"timed": True})
    (tmp_path / "a_file").write_text("")
    bad = str(tmp_path / "a_file" / "x.json")
    assert cli.main(["calibrate", "--bench", "--out", bad, "--json", bad]) == 0
    assert capsys.readouterr().out == '{"timed": true}\n'
    assert cli.main(["calibrate", "--out", bad]) == 2, "without --bench the outputs are checked"


def test_an_output_without_write_permission_is_refused(tmp_path, monkeypatch):
    """Permission is judged from the owner's mode bits, as a non-root user's would be (root may write anywhere)."""
    import stat

    from pipeline import cli

    def as_owner(path, mode):
        return (os.stat(path).st_mode >> 6) & mode == mode

    monkeypatch.setattr(cli.os, "access", as_owner)
    (tmp_path / "read_only").write_text("")
    (tmp_path / "read_only").chmod(stat.S_IRUSR)
    (tmp_path / "no_search").mkdir()
    (tmp_path / "no_search").chmod(stat.S_IRUSR | stat.S_IWUSR)
    (tmp_path / "no_write").mkdir()
    (tmp_path / "no_write" / "old.json").write_text("")  # writable itself, but the atomic writer's temp file goes beside it
    (tmp_path / "no_write").chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        assert cli.output_problem(tmp_path / "r.json", tmp_path / "new" / "r.json") is None, "the writable parent is asked"
        assert as_owner(tmp_path / "no_write" / "old.json", os.W_OK)
        for path in [tmp_path / "read_only", tmp_path / "no_write" / "r.json", tmp_path / "no_write" / "new" / "r.json",
                     tmp_path / "no_write" / "old.json"]:
            assert cli.output_problem(path) == f"cannot write {path}: permission denied"
        assert cli.output_problem(tmp_path / "no_search", directory=True) == f"cannot write {tmp_path / 'no_search'}: permission denied"
        (tmp_path / "no_write").chmod(stat.S_IRWXU)
        (tmp_path / "no_write" / "log").mkdir()
        (tmp_path / "no_write").chmod(stat.S_IRUSR | stat.S_IXUSR)
        assert cli.output_problem(tmp_path / "no_write" / "log", directory=True) is None, "a directory's files go inside it"
    finally:
        for name in ("no_search", "no_write"):
            (tmp_path / name).chmod(stat.S_IRWXU)


def test_an_output_inside_a_directory_one_may_not_enter_is_one_line(tmp_path, monkeypatch):
    from pathlib import Path

    # For a user other than root, Path.exists raises PermissionError below such a directory (Python
    # 3.11) instead of answering; root, which the tests run as, is never refused, so it is simulated.
    from pipeline import cli

    real_exists = Path.exists

    def exists(self, *args, **kwargs):
        if "locked" in self.parts:
            raise PermissionError(13, "Permission denied", str(self))
        return real_exists(self, *args, **kwargs)

    monkeypatch.setattr(Path, "exists", exists)
    path = tmp_path / "locked" / "r.json"
    assert cli.output_problem(path) == f"cannot write {path}: Permission denied"
    assert cli.output_problem(tmp_path / "free.json") is None


def test_a_study_whose_reader_stopped_reading_ends_quietly(tmp_path):
    # `python -m pipeline.studies.pooled_gain ... | head -1`, made deterministic: the pipe's read end is
    # closed before the study writes, so its first line meets a broken pipe.
    import json
    import subprocess
    from pathlib import Path

    trials = tmp_path / "run.jsonl"
    trials.write_text("".join(json.dumps({"trial": t, "start": t, "object": t, "object_id": f"o{t}", "outside": False,
                                          "useful": True, "gains": {"value_iteration": 0.1 * t, "max_height": 0.0}}) + "\n"
                              for t in range(4)))
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run([sys.executable, "-m", "pipeline.studies.pooled_gain", str(trials)], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1], check=False)
    finally:
        os.close(write)
    assert done.returncode == 1 and done.stderr == "", done.stderr
