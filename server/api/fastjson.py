"""A JSON response rendered by orjson, for the REST API's large answers (``GET /v1/objects``).

Starlette's ``JSONResponse`` renders with the standard library's ``json.dumps``: about 1 ms of
each answer of ~40 objects (cProfile of the ASGI app). orjson writes the same compact UTF-8 JSON
(same keys in the same order, shortest round-trip floats); with it the radius query's p99 went
from 6.00 to 4.03-4.11 ms (``bench/api.py``, BENCHMARKS.md). numpy scalars and arrays are
serialized as numbers and lists.
"""

from __future__ import annotations

from typing import Any

import orjson
from fastapi.responses import JSONResponse

__all__ = ["FastJSONResponse"]


class FastJSONResponse(JSONResponse):
    """``JSONResponse`` rendered with ``orjson.dumps`` (``OPT_SERIALIZE_NUMPY``)."""

    def render(self, content: Any) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)
