"""Loaded by pytest before any test module: ``import pipeline`` first, so that the test process and the
workers it starts compute with the BLAS kernel the command line pins (``pipeline.numerics``). Tests compare
datasets built in this process with datasets built by ``python -m pipeline`` in a subprocess; on a machine
whose own kernel is not the pinned one, the two would differ in their last bits."""

import pipeline  # noqa: F401
