"""Packaging: the console command, the distributions each extra declares against what its
modules import (the server's and the client's), the wheel, and an install with only the service extra.

The slow tests build the wheel once from a copy of the source tree (what ``pip install .``
builds; the copy keeps build/ and *.egg-info out of the working tree), check what it ships,
then install it with only ``[service]`` into a fresh venv and run the HTTP service there on a
tiny dataset built here by the full install: the service must work without the geometry
stack, and the geometry stack must not come in with it.

Needs PyPI (or the pip index configured for this machine) to resolve the service's
dependencies.  The fresh venv is made without pip (``--without-pip``) and filled by this
venv's pip (``pip --python``), which saves bootstrapping a second pip.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
import zipfile
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.build.corpus import read_list
from pipeline.build.dataset import build_dataset
from pipeline.cli import COMMANDS
from pipeline.model.config import Config

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
PACKAGES = ("pipeline", "schema", "clutter", "service")
"""Top-level packages of the distribution (pyproject ``packages.find``)."""
GEOMETRY_STACK = ("trimesh", "fcl", "embreex", "scipy", "h5py", "pybullet", "dask", "joblib")
"""Import names of the ``pipeline`` extra that a service-only install must not have."""
SOURCE_SKIP_TOP = {".venv", "data", ".git", "build", "dist"}
"""Top-level entries of a checkout that are not source (pipeline/build/ is source: only the root's)."""
SOURCE_SKIP_ANY = {"__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache"}
PIP_TIMEOUT = 900
"""s; a cold install downloads pyarrow and numpy (~75 MB)."""
SERVER_START_TIMEOUT = 90
"""s for the server to answer /health: a fresh venv imports pyarrow and fastapi cold."""


def run(argv: list, timeout: float, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in argv], check=False, capture_output=True, text=True, timeout=timeout, **kwargs)
    assert result.returncode == 0, f"{' '.join(map(str, argv))} exited {result.returncode}:\n{result.stderr[-3000:]}"
    return result


def isolated_env() -> dict:
    """Environment for the fresh venv: nothing that would put this checkout or venv on its path."""
    drop = {"PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP"}
    return {k: v for k, v in os.environ.items() if k not in drop and not k.startswith("TOPPLEDB_")}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the console command (the project's own venv) ----------------------------------


def test_toppledb_console_script_lists_every_command():
    script = BIN / "toppledb"
    assert script.is_file() and os.access(script, os.X_OK), f"no console script {script}: reinstall with make venv"
    out = run([script, "--help"], timeout=60).stdout
    missing = [c for c in COMMANDS if c not in out]
    assert not missing, f"toppledb --help does not list {missing}:\n{out}"


def test_toppledb_bench_help_is_the_bench_parser():
    from pipeline.studies import bench

    out = run([BIN / "toppledb", "bench", "--help"], timeout=120).stdout
    assert out.startswith("usage: toppledb bench"), out
    description = " ".join(bench.__doc__.split("\n\n")[0].split())
    assert description in " ".join(out.split()), "toppledb bench --help is not the bench module's own help"
    assert "{dataset" not in out, "the top-level parser answered instead of the bench module"


# --- what each extra declares against what its modules import ------------------------

SERVICE_TOOLS = {"service/bench.py"}
"""service/ modules run on the full install only: the load generator of ``make bench-service``
(psutil, and a dataset it builds with the pipeline when there is none)."""


def third_party_imports(path: Path) -> set[str]:
    """Top-level names of the absolute imports in ``path`` outside the standard library and this project."""
    import ast

    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in PACKAGES}


def declared(*extras: str) -> set[str]:
    """Canonical distribution names of pyproject's dependencies and the given extras."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = project["dependencies"] + [r for e in extras for r in project["optional-dependencies"][e]]
    return {canonicalize_name(Requirement(r).name) for r in requirements}


def pinned(file: str = "constraints.txt") -> dict[str, str]:
    """A constraints file as {canonical name: version}; every line a comment, blank or ``name==version``, once."""
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for number, line in enumerate((ROOT / file).read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        name, equals, version = line.partition("==")
        assert equals and version and " " not in line, f"{file}:{number}: {line!r} is no name==version"
        assert canonicalize_name(name) not in pins, f"{file}:{number}: {name} pinned twice"
        pins[canonicalize_name(name)] = version
    return pins


def test_constraints_pin_every_declared_distribution_within_its_range_and_this_venv_has_them():
    """``make`` installs with ``-c constraints.txt``: a pin for each dependency pyproject declares, inside the
    range it declares, so that the versions CI and a fresh machine get are the tested ones; the tests
    run in such a venv (one made another way, or after an upgrade by hand, is named here)."""
    import itertools
    import tomllib
    from importlib.metadata import distributions

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = itertools.chain(project["dependencies"], *project["optional-dependencies"].values())
    requirements = [Requirement(r) for r in declared]
    requirements = [r for r in requirements if canonicalize_name(r.name) != "toppledb" and (r.marker is None or r.marker.evaluate())]
    pins = pinned()
    assert requirements and len(pins) > len(requirements)  # the declared ones and what they bring
    for requirement in requirements:
        name = canonicalize_name(requirement.name)
        assert name in pins, f"constraints.txt pins no {requirement.name}, which pyproject.toml declares"
        assert requirement.specifier.contains(pins[name], prereleases=True), f"{name}=={pins[name]} is outside {requirement}"
    installed = {canonicalize_name(d.metadata["Name"]): d.version for d in distributions()}
    for name, pin in pins.items():  # what the declared ones bring too (starlette, pydantic_core, ...)
        assert installed.get(name, pin) == pin, (
            f"this venv has {name} {installed[name]}, constraints.txt pins {pin}: run `make` (it reinstalls when "
            "constraints.txt changes), or refresh constraints.txt as its header says")
    assert {canonicalize_name(r.name) for r in requirements} <= set(installed)


def test_build_constraints_pin_pip_and_every_build_requirement_within_its_range():
    """``make`` upgrades pip and builds toppledb's editable install under build-constraints.txt: a pin for
    pip and for each of pyproject's ``[build-system] requires``, inside its range (else the build cannot
    resolve), none of them also in constraints.txt (whose recipe rewrites it from the venv); this venv's pip
    is the pinned one."""
    import tomllib
    from importlib.metadata import version

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins = pinned("build-constraints.txt")
    requires = [Requirement(r) for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]]
    assert requires
    for requirement in requires:
        name = canonicalize_name(requirement.name)
        assert name in pins, f"build-constraints.txt pins no {requirement.name}, which [build-system] requires"
        assert requirement.specifier.contains(pins[name]), f"{name}=={pins[name]} is outside {requirement}"
    assert "pip" in pins and not set(pins) & set(pinned())
    assert version("pip") == pins["pip"], (
        f"this venv has pip {version('pip')}, build-constraints.txt pins {pins['pip']}: run `make`")
    makefile = (ROOT / "Makefile").read_text()
    assert "-c build-constraints.txt --upgrade pip" in makefile and "--build-constraint build-constraints.txt" in makefile


@pytest.mark.parametrize(("modules", "extras"), [("server", ("service",)), ("client", ("client",))])
def test_each_install_declares_every_distribution_its_modules_import(modules, extras):
    from importlib.metadata import packages_distributions

    from packaging.utils import canonicalize_name

    client = ROOT / "service" / "client.py"
    paths = [client] if modules == "client" else [
        p for p in (ROOT / "service").rglob("*.py") if p != client and p.relative_to(ROOT).as_posix() not in SERVICE_TOOLS]
    installed, wanted = packages_distributions(), declared(*extras)
    missing = set()
    for path in paths:
        for name in third_party_imports(path):
            found = {canonicalize_name(d) for d in installed.get(name, [])}
            if not found & wanted:
                missing.add(f"{path.relative_to(ROOT)}: {name} ({', '.join(sorted(found)) or 'not installed here'})")
    assert not missing, f"imported but not in pyproject's dependencies or {extras}: {sorted(missing)}"


def test_importing_the_client_loads_nothing_of_the_server():
    # In this venv, which has them all: service/__init__ brings the store (numpy, pyarrow, the
    # framework-free errors), and nothing of the web framework, the server or the pipeline may come.
    code = ("import json, sys, service.client\n"
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'fastapi', 'starlette', 'uvicorn', 'orjson', 'prometheus_client', 'pipeline', 'trimesh'})))\n")
    loaded = json.loads(run([sys.executable, "-c", code], timeout=120, cwd=ROOT).stdout)
    assert loaded == [], f"importing service.client loaded {loaded}"


# --- the wheel ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """A copy of the checkout's source files (no venv, data, VCS or build output)."""

    def ignore(directory: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n in SOURCE_SKIP_ANY or n.endswith(".egg-info")}
        return skip | (SOURCE_SKIP_TOP & set(names) if Path(directory) == ROOT else set())

    copy = tmp_path_factory.mktemp("packaging") / "src"
    shutil.copytree(ROOT, copy, ignore=ignore)
    return copy


@pytest.fixture(scope="module")
def wheel(source, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "--wheel-dir", out, source], timeout=PIP_TIMEOUT)
    (built,) = out.glob("toppledb-*.whl")
    return built


@pytest.mark.slow
def test_wheel_ships_every_module_the_default_corpus_and_type_markers(wheel, source):
    names = set(zipfile.ZipFile(wheel).namelist())
    for required in ("pipeline/build/corpus_default.csv", "pipeline/model/presets/thesis.toml",
                     "pipeline/model/presets/boosted_map_s41.json", *(f"{p}/py.typed" for p in PACKAGES)):
        assert required in names, f"{wheel.name} lacks {required}"
    with zipfile.ZipFile(wheel) as archive:
        assert archive.read("pipeline/build/corpus_default.csv") == (source / "pipeline/build/corpus_default.csv").read_bytes()
        entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        assert "toppledb = pipeline.cli:main" in archive.read(entry_points).decode()
    # Every module of the source packages is in the wheel (a subpackage left out of
    # packages.find, or a stray ignore, would drop a whole folder), and nothing else is.
    modules = {p.relative_to(source).as_posix() for package in PACKAGES for p in (source / package).rglob("*.py")}
    assert modules - names == set(), f"modules missing from the wheel: {sorted(modules - names)}"
    shipped = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert shipped == set(PACKAGES), f"unexpected top-level entries in the wheel: {sorted(shipped - set(PACKAGES))}"


# --- an install with only the service extra ------------------------------------------


@pytest.fixture(scope="module")
def service_venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv holding ``toppledb[service]`` and nothing of this venv, at the versions of constraints.txt."""
    venv = tmp_path_factory.mktemp("service_only") / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", venv], timeout=120)
    python = venv / "bin" / "python"
    started = time.monotonic()
    run(
        [sys.executable, "-m", "pip", "--python", python, "install", "--quiet", "-c", ROOT / "constraints.txt", f"{wheel}[service]"],
        timeout=PIP_TIMEOUT,
        env=isolated_env(),
    )
    print(f"pip install toppledb[service]: {time.monotonic() - started:.1f} s")
    return venv


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    """One object, built by the full install (this venv)."""
    directory = tmp_path_factory.mktemp("packaging_dataset")
    corpus = directory / "corpus.csv"
    corpus.write_text("object_id,source,path,scale,mass\nrandom_000,pybullet_data/random_urdfs,random_urdfs/000/000.obj,0.015,0.1\n")
    config = Config().with_overrides(
        {"contacts.n_contacts": 20, "topple.n_trials": 3, "suction.n_candidates": 10, "suction.n_samples": 3}
    )
    out = directory / "dataset"
    build_dataset(read_list(corpus, default_mass=0.25), config, out, workers=1, progress=False, log=lambda _: None)
    return out


@pytest.mark.slow
def test_service_extra_alone_has_no_geometry_stack(service_venv, tmp_path):
    code = (
        "import importlib.util, json, schema, service\n"
        f"print(json.dumps({{'present': [m for m in {GEOMETRY_STACK!r} if importlib.util.find_spec(m)],"
        " 'service': service.__file__, 'schema': schema.__file__}))\n"
    )
    answer = json.loads(run([service_venv / "bin" / "python", "-c", code], timeout=120, cwd=tmp_path, env=isolated_env()).stdout)
    assert answer["present"] == [], f"the service extra pulled in the geometry stack: {answer['present']}"
    for package in ("service", "schema"):
        assert Path(answer[package]).is_relative_to(service_venv), f"{package} imported from {answer[package]}, not the fresh venv"


def get_json(url: str) -> tuple[int, dict]:
    with urllib.request.urlopen(url, timeout=10) as response:
        return response.status, json.loads(response.read())


@pytest.mark.slow
def test_service_extra_alone_serves_a_dataset(service_venv, tiny_dataset, tmp_path):
    port = free_port()
    server = subprocess.Popen(
        [service_venv / "bin" / "python", "-m", "service", "--dataset", tiny_dataset, "--port", str(port), "--log-level", "warning"],
        cwd=tmp_path,  # not the checkout: ``-m service`` must find the installed package
        env={**isolated_env(), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + SERVER_START_TIMEOUT
        while True:
            try:
                status, health = get_json(f"{base}/health")
                break
            except OSError:  # refused until uvicorn listens
                if server.poll() is not None:
                    pytest.fail(f"the service exited {server.returncode}:\n{server.stderr.read()[-3000:]}")
                assert time.monotonic() < deadline, f"no answer from the service within {SERVER_START_TIMEOUT} s"
                time.sleep(0.2)
        poses = pq.read_table(tiny_dataset / "poses.parquet").to_pylist()
        assert status == 200 and health["status"] == "ok"
        assert health["counts"]["objects"] == 1 and health["counts"]["poses"] == len(poses)

        status, objects = get_json(f"{base}/objects")
        assert status == 200 and objects["count"] == 1
        (listed,) = objects["objects"]
        assert listed["object_id"] == "random_000" and listed["n_poses"] == len(poses) > 0
        assert listed["mass"] == pytest.approx(0.1)
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
        server.stderr.close()


@pytest.mark.slow
def test_toppledb_serve_works_with_only_the_service_extra(service_venv, tmp_path):
    out = run([service_venv / "bin" / "toppledb", "serve", "--help"], timeout=120, cwd=tmp_path, env=isolated_env()).stdout
    assert "--dataset" in out
