"""One BLAS kernel on every x86-64 Linux machine, so that a dataset's numbers do not depend on the processor.

numpy's matrix products go to OpenBLAS, which picks its kernels by the processor it finds when it
loads: Haswell's on an AVX2 machine, SkylakeX's on an AVX-512 one, Sandybridge's without FMA. The
kernels round differently, so the same build moves contacts, normals and forces in their last bits
from one machine to another, and the Monte Carlo thresholds turn some of those bits into other
outcomes: with Sandybridge's kernels in place of Haswell's, 40 corpus objects built again changed
P(topple) on 2,033 of 470,470 pushes, by up to 0.013, and Q_T on 59,781 (stop 63, docs/DATASET.md,
"Reproducible across machines"). numpy's own SIMD loops were not the cause: the same build with numpy held to its
SSE4.2 loops was byte-identical.

``pin_blas_kernel`` names one kernel for OpenBLAS to use, Haswell's, which every x86-64 processor
with AVX2 and FMA runs, before numpy loads. ``pipeline/__init__.py`` calls it first, so the dataset
job, its loky workers (which inherit the environment) and the studies compute with the same kernel on
any such Linux machine. A dask worker has loaded numpy before any task imports ``pipeline``: start it
with ``OPENBLAS_CORETYPE=Haswell`` in its environment. Only numpy's own OpenBLAS (the PyPI wheels)
is pinned; an MKL or system BLAS build is not. Nothing here imports numpy.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping, MutableMapping

PINNED_KERNEL = "Haswell"
"""The OpenBLAS core type every x86-64 build computes with (``OPENBLAS_CORETYPE``)."""

NEEDS = frozenset({"avx2", "fma"})
"""The processor flags ``PINNED_KERNEL`` runs on (/proc/cpuinfo's names)."""

KERNEL_VARIABLE = "OPENBLAS_CORETYPE"


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> frozenset[str]:
    """The processor's feature flags as Linux lists them; empty where there is no such file."""
    try:
        with open(cpuinfo, encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


def pin_blas_kernel(environ: MutableMapping[str, str] = os.environ, flags: frozenset[str] | None = None,
                    machine: str | None = None, modules: Mapping[str, object] = sys.modules) -> str | None:
    """Name ``PINNED_KERNEL`` in ``environ`` for OpenBLAS to load, where it can take effect.

    Nothing is set where the user has named a kernel already (theirs stands), where numpy is already
    loaded (its OpenBLAS has chosen; workers started from this process then choose as it did), on a
    processor that is not x86-64 or lacks AVX2 or FMA (``NEEDS``; Haswell's kernels would not run), or
    where the flags cannot be read (``cpu_flags`` reads Linux's /proc/cpuinfo: macOS and Windows are not pinned).
    returns : the kernel now named in ``environ``, or None where OpenBLAS chooses by itself"""
    if environ.get(KERNEL_VARIABLE, "").strip():
        return environ[KERNEL_VARIABLE]  # OpenBLAS reads an empty value as none, so an empty one does not count
    if "numpy" in modules:
        return None
    if (machine if machine is not None else platform.machine()).lower() not in ("x86_64", "amd64"):
        return None
    if not NEEDS <= (flags if flags is not None else cpu_flags()):
        return None
    environ[KERNEL_VARIABLE] = PINNED_KERNEL
    return PINNED_KERNEL


def numpy_simd() -> list[str] | None:
    """The SIMD targets numpy's own loops dispatch to in this process (its ``__cpu_dispatch__`` that the
    processor has and ``NPY_DISABLE_CPU_FEATURES`` leaves on), e.g. ["X86_V3", "X86_V4", ...]; None where
    numpy does not say.

    Not pinned, only recorded: on a processor with AVX-512 numpy's float64 exp, log, arctan2 and power take
    paths that round otherwise in the last bit, and builds and reports differ from an AVX2 machine's in the
    fourth digit (docs/DATASET.md, "Reproducible across machines"); a manifest that names them says why."""
    try:
        import numpy  # noqa: F401  (its loops must be loaded to be described)

        try:
            from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
        except ImportError:  # numpy 1.x
            from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:
        return None
    return [target for target in __cpu_dispatch__ if __cpu_features__.get(target)]


def blas_kernel() -> dict[str, str | None]:
    """What numpy's BLAS computes with in this process: library, version and kernel ("architecture"),
    as threadpoolctl reads them from the loaded library (None each where it cannot), and the kernel
    named in the environment, if any."""
    info: dict[str, str | None] = {"library": None, "version": None, "kernel": None,
                                   "requested": os.environ.get(KERNEL_VARIABLE)}
    try:
        import numpy  # noqa: F401  (its BLAS must be loaded to be described)
        from threadpoolctl import threadpool_info
    except ImportError:
        return info
    for lib in threadpool_info():
        if lib.get("user_api") == "blas" and "numpy" in str(lib.get("filepath", "")):
            info.update(library=lib.get("internal_api"), version=lib.get("version"), kernel=lib.get("architecture"))
            break
    return info
