"""schemathesis over every operation of the service's OpenAPI document, on the tiny
dataset of tests/test_service.py: generated valid and invalid requests must never get a
5xx, and every response must match the document (status, content type, body schema).

Derandomised (fixed hypothesis seed), so a failure reproduces; ``FUZZ_EXAMPLES`` per
operation keeps the whole module under a minute on 2 cores.
"""

# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
from __future__ import annotations

import copy

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.generation import GenerationMode
from schemathesis.specs.openapi.checks import positive_data_acceptance

from service import create_app
from service.settings import Settings
from tests.test_service import dataset  # noqa: F401 (fixture)

FUZZ_EXAMPLES = 25

SEMANTIC = {"POST /plan", "POST /batch/plan", "POST /heaps/plan"}
"""Operations whose bodies have rules JSON Schema cannot state (a rotation block, a unit
quaternion), so a schema-valid body may rightly be a 422: schemathesis's "valid data must be
accepted" check is off for them; every other check (5xx, status, content type, body schema) stays."""


def contract(document: dict) -> dict:
    """The service's OpenAPI document as schemathesis checks it:

    - without the ``x-toppledb-build`` request header: a generated build is refused (412) before the rest of
      the request is read, so it would leave most requests untested; the 412 has its own tests
      (tests/test_service_client.py);
    - every object of an answer closed (``additionalProperties: false``): a client ignores fields it does not
      know (docs/SERVICE.md, "Versions"), but this service sends none that its document does not declare.
    """
    document = copy.deepcopy(document)
    for operations_of_path in document["paths"].values():
        for operation in operations_of_path.values():
            operation["parameters"] = [p for p in operation.get("parameters", []) if p["name"] != "x-toppledb-build"]
    stack = list(document["components"]["schemas"].values())
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            if "properties" in node:
                node.setdefault("additionalProperties", False)  # requests' are false already
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return document


def operations(app) -> list:
    schema = schemathesis.openapi.from_dict(contract(app.openapi()))
    schema.app = app
    return [result.ok() for result in schema.get_all_operations()]


def contract_test(operation, mode: GenerationMode):
    """A hypothesis test sending ``FUZZ_EXAMPLES`` generated requests to one operation."""
    excluded = [positive_data_acceptance] if operation.label in SEMANTIC else None

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), database=None)
    def answers_within_contract(case):
        case.call_and_validate(excluded_checks=excluded)

    return answers_within_contract


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_every_operation_answers_within_its_contract(dataset, mode):
    app = create_app(dataset, settings=Settings(watch_seconds=0))
    found = operations(app)
    documented = sum(len(methods) for methods in app.openapi()["paths"].values())
    assert len(found) == documented >= 11, [o.label for o in found]
    fuzzed = 0
    for operation in found:
        try:
            contract_test(operation, mode)()
            fuzzed += 1
        except Unsatisfiable:
            # Every request is valid (no parameters, or any string is an object id): nothing negative to send.
            assert mode is GenerationMode.NEGATIVE, operation.label
    assert fuzzed >= (len(found) if mode is GenerationMode.POSITIVE else 5)
