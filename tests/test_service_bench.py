# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
"""``make bench-service`` runs end to end (briefly) on the test dataset: every phase, one JSON line, no errors."""

from __future__ import annotations

import json

from service import bench
from tests.test_service import dataset  # noqa: F401 (fixture)


def test_bench_service_runs_every_phase_without_errors(dataset, capsys):
    code = bench.main(["--dataset", str(dataset), "--seconds", "0.3", "--connections", "4"])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and line["errors"] == 0
    assert line["plan_rps"] > 0 and line["startup_s"] <= line["api_s"] <= line["ready_s"] + 1e-9
    assert line["batch_items_per_s"] > 0 and line["oversized_bodies_refused"] > 0
    assert line["heap_plans_per_s"] > 0, "a heap of the test objects fits the default bin"
    assert line["memory"]["rss_mb"], "the server's processes were measured"
