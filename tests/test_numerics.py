"""One BLAS kernel wherever the dataset job runs (pipeline.numerics): named before numpy loads,
only where it can run and nobody chose another, and recorded in the manifest."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.numerics import KERNEL_VARIABLE, NEEDS, PINNED_KERNEL, blas_kernel, cpu_flags, numpy_simd, pin_blas_kernel

ROOT = Path(__file__).resolve().parent.parent
HASWELL_FLAGS = frozenset({"sse4_2", "avx", "avx2", "fma"})
ELIGIBLE = sys.platform == "linux" and os.uname().machine == "x86_64" and NEEDS <= cpu_flags()


def test_the_kernel_is_named_on_an_x86_64_processor_with_avx2_and_fma():
    environ = {}
    assert pin_blas_kernel(environ, HASWELL_FLAGS, "x86_64", modules={}) == PINNED_KERNEL
    assert environ == {KERNEL_VARIABLE: PINNED_KERNEL}
    assert pin_blas_kernel({}, HASWELL_FLAGS, "AMD64", modules={}) == PINNED_KERNEL
    assert pin_blas_kernel({}, NEEDS, "x86_64", modules={}) == PINNED_KERNEL  # AVX2 and FMA are all it needs


@pytest.mark.parametrize("flags, machine", [
    (frozenset({"sse4_2", "avx", "fma"}), "x86_64"),  # no AVX2: Haswell's kernels would not run
    (frozenset({"sse4_2", "avx", "avx2"}), "x86_64"),  # no FMA
    (frozenset(), "x86_64"),  # no /proc/cpuinfo
    (HASWELL_FLAGS, "aarch64"),  # another instruction set: OpenBLAS's own choice
])
def test_nothing_is_named_where_the_kernel_cannot_run(flags, machine):
    environ = {}
    assert pin_blas_kernel(environ, flags, machine, modules={}) is None
    assert environ == {}


def test_a_kernel_the_user_named_stands():
    environ = {KERNEL_VARIABLE: "Sandybridge"}
    assert pin_blas_kernel(environ, HASWELL_FLAGS, "x86_64", modules={}) == "Sandybridge"
    assert environ == {KERNEL_VARIABLE: "Sandybridge"}
    # An empty value names none (OpenBLAS then chooses by itself), so it does not stop the pin.
    for empty in ("", " "):
        environ = {KERNEL_VARIABLE: empty}
        assert pin_blas_kernel(environ, HASWELL_FLAGS, "x86_64", modules={}) == PINNED_KERNEL
        assert environ == {KERNEL_VARIABLE: PINNED_KERNEL}


@pytest.mark.skipif(not ELIGIBLE, reason="needs an x86-64 processor with AVX2 and FMA")
def test_the_test_process_computes_with_the_kernel_the_command_line_does():
    # tests/conftest.py imports pipeline before any test module loads numpy, so this process (and the
    # workers it starts) computes as `python -m pipeline` does: the pinned kernel, or the one the user named.
    assert blas_kernel()["kernel"].lower() == os.environ[KERNEL_VARIABLE].lower()


def test_nothing_is_named_once_numpy_has_loaded():
    # Its OpenBLAS has chosen; naming another now would make workers started from here differ from it.
    environ = {}
    assert pin_blas_kernel(environ, HASWELL_FLAGS, "x86_64", modules={"numpy": object()}) is None
    assert environ == {}


def test_the_flags_are_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    # A model name in Latin-1 (a byte UTF-8 and ASCII cannot decode) must not stop the flags being read.
    info.write_bytes(b"processor\t: 0\nmodel name\t: Intel\xae Xeon\nflags\t\t: fpu sse4_2 avx avx2 fma\n\nprocessor\t: 1\n")
    assert cpu_flags(str(info)) == frozenset({"fpu", "sse4_2", "avx", "avx2", "fma"})
    assert cpu_flags(str(tmp_path / "missing")) == frozenset()
    if Path("/proc/cpuinfo").is_file():  # by default, this machine's
        assert cpu_flags() == cpu_flags("/proc/cpuinfo") != frozenset()


def _fresh_python(code: str, **environ: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != KERNEL_VARIABLE}
    env.update(environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120).stdout.strip()


@pytest.mark.skipif(not ELIGIBLE, reason="needs an x86-64 processor with AVX2 and FMA")
def test_importing_pipeline_first_makes_numpy_compute_with_the_pinned_kernel():
    code = "import pipeline, os; from pipeline.numerics import blas_kernel; print(os.environ['%s'], blas_kernel()['kernel'])"
    assert _fresh_python(code % KERNEL_VARIABLE).split() == [PINNED_KERNEL, PINNED_KERNEL]
    # Another kernel named by the user is the one numpy computes with: the variable reaches OpenBLAS.
    assert _fresh_python(code % KERNEL_VARIABLE, OPENBLAS_CORETYPE="Sandybridge").split() == ["Sandybridge"] * 2


def test_the_description_names_numpys_blas():
    info = blas_kernel()
    assert set(info) == {"library", "version", "kernel", "requested"}
    assert info["requested"] == os.environ.get(KERNEL_VARIABLE)
    assert info["library"] == "openblas" and info["kernel"] and info["version"]  # numpy's wheels carry OpenBLAS


def test_the_simd_targets_numpy_computes_with_are_named_and_follow_what_the_user_turns_off():
    """Recorded in the manifest (``code_version.simd``): which of numpy's dispatch targets this process uses.
    Turning one off in the environment before numpy loads removes it from the record."""
    simd = numpy_simd()
    assert simd is not None and all(isinstance(target, str) for target in simd)
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_dispatch__
    assert set(simd) <= set(__cpu_dispatch__)
    if not simd:
        pytest.skip("numpy dispatches to no SIMD target here")
    code = "import pipeline; from pipeline.numerics import numpy_simd; print(' '.join(numpy_simd()))"
    assert _fresh_python(code).split() == simd
    turned_off = simd[-1]
    assert _fresh_python(code, NPY_DISABLE_CPU_FEATURES=turned_off).split() == [t for t in simd if t != turned_off]
