"""Prometheus metrics of one worker: requests and their latency per route.

``toppledb_requests_total{method, route, status}`` and
``toppledb_request_seconds{method, route}`` (a histogram whose buckets resolve the
control path's milliseconds as well as a 1000-item batch's tenths of a second), plus
``toppledb_dataset_info`` naming the served build.  ``route`` is the route template
(``/objects/{object_id}``), never the raw path, so label cardinality stays bounded;
requests that match no route are ``unmatched``.

Each worker process has its own registry: with several workers, a scrape reaches one of
them (the ``pid`` label says which); scrape each worker, or run one worker per port.
"""

from __future__ import annotations

import os

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
"""s: the control path lives in the first few buckets, batches in the last."""

CONTENT_TYPE = CONTENT_TYPE_LATEST


class Metrics:
    def __init__(self):
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "toppledb_requests", "HTTP requests answered", ["method", "route", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "toppledb_request_seconds", "Time from request to the end of the response", ["method", "route"],
            buckets=BUCKETS, registry=self.registry,
        )
        self.dataset = Gauge(
            "toppledb_dataset_info", "The served build (value 1)", ["manifest_sha256", "created", "pid"], registry=self.registry
        )
        self.reloads = Counter("toppledb_dataset_reloads", "Rebuilt datasets swapped in", registry=self.registry)
        self.reload_failures = Counter("toppledb_dataset_reload_failures",
                                       "Rebuilt datasets that could not be loaded (the previous build stays served)",
                                       registry=self.registry)
        self._children: dict[tuple, tuple] = {}
        """(method, route, status) -> (counter, histogram) children: ``labels()`` looks them up
        under a lock on every call, a few microseconds of every request."""

    def observe(self, method: str, route: str | None, status: int, seconds: float) -> None:
        key = (method, route, status)
        children = self._children.get(key)
        if children is None:  # bounded: routes are templates, statuses and methods few
            label = route or "unmatched"
            children = self._children[key] = (self.requests.labels(method, label, str(status)),
                                              self.latency.labels(method, label))
        children[0].inc()
        children[1].observe(seconds)

    def serving(self, manifest_sha256: str, created: str) -> None:
        self.dataset.clear()
        self.dataset.labels(manifest_sha256, created, str(os.getpid())).set(1)

    def render(self) -> bytes:
        return generate_latest(self.registry)
