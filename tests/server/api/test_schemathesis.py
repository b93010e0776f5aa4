"""The REST API against its own OpenAPI document (schemathesis, property-based): over the object
scene, every operation is called in process (ASGI) with a real ``read`` token and generated
parameters, valid (positive) and invalid (negative), a bounded number of seeded examples
each. Every response must be what the document says: no server error, and a status, content
type, headers and body it declares.

Two of schemathesis's checks are left out, on purpose: ``positive_data_acceptance`` (a
schema-valid request must succeed: OpenAPI cannot say that ``radius`` needs ``near`` or what
an opaque page cursor holds, so such requests are a documented 400/422) and
``negative_data_rejection`` (unknown query parameters are ignored, as most HTTP APIs do).

``GET /v1/events`` is left out: an event stream never ends, and schemathesis's in-process
transport waits on it without end (tests/server/api/routes/test_events.py checks its status,
headers and events against a running server)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from schemathesis.generation import GenerationMode  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    negative_data_rejection,
    positive_data_acceptance,
)

from wardmap.server.app import MapServer  # noqa: E402

MAX_EXAMPLES = 25
"""Generated cases per operation and mode (seeded): every parameter's edges, a few seconds."""


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE], ids=str)
def test_every_response_is_documented(
    object_scene: Any, token_headers: Callable[..., dict[str, str]], mode: GenerationMode
) -> None:
    headers = token_headers(object_scene.url, "read")
    server = MapServer(object_scene.url)
    schema = schemathesis.openapi.from_asgi("/openapi.json", server.app)
    operations = [op for op in (result.ok() for result in schema.get_all_operations())
                  if op.path != "/v1/events"]
    assert {op.path for op in operations} >= {
        "/v1/robots", "/v1/robots/{robot_id}/trajectory", "/v1/keyframes", "/v1/objects",
        "/v1/objects/{object_id}", "/v1/categories", "/metrics", "/healthz", "/readyz",
    }
    if mode is GenerationMode.NEGATIVE:  # an operation without parameters has no invalid request
        operations = [op for op in operations if op.query or op.path_parameters]
    failures: list[str] = []
    try:
        for operation in operations:

            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def check(case: Any) -> None:
                case.call_and_validate(headers=headers,
                                       excluded_checks=[positive_data_acceptance, negative_data_rejection])

            try:
                check()
            except (Exception, BaseExceptionGroup) as exc:  # every operation's failure, then all of them
                failures.append(f"{operation.method.upper()} {operation.path}: {exc}")
    finally:
        server.stop()
    assert not failures, "\n\n".join(failures)
