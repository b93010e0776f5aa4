"""Who may call which route: bearer tokens with scopes, as one router-wide dependency.

``api/main.py`` includes every data route through a router whose dependency is
:func:`require_token`, so a new route is protected without anyone remembering to: a ``GET``
needs a ``read`` token, any other method an ``admin`` one (a route may ask for ``admin``
explicitly with :data:`AdminOnly`). Only the public router (``/healthz``, ``/readyz``, the
OpenAPI document and static assets that carry no data) goes without.

The policy is an :class:`ApiAuth` on ``app.state.auth``, set by the app's lifespan: tokens
checked against the store (the default), or none checked (``insecure-loopback``, which
:func:`~wardmap.server.app.run_server` allows only on a loopback address). A missing policy
fails closed (500), never open. Failures: 401 with ``WWW-Authenticate: Bearer`` (no, bad or
revoked token), 403 (a ``read`` token on an admin route); token handling is in
``server/tokens.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Final

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from wardmap.server.store import TokenScope, TokenStore
from wardmap.server.tokens import TokenForbiddenError, TokenInvalidError, verify

__all__ = ["AUTH_RESPONSES", "AdminOnly", "ApiAuth", "require_admin", "require_token"]

_SAFE_METHODS: Final = frozenset({"GET", "HEAD", "OPTIONS"})

_bearer = HTTPBearer(auto_error=False, description="a token from `wardmap token create` (docs/map_api.md)")

AUTH_RESPONSES: Final[dict[int | str, dict[str, object]]] = {
    401: {"description": "no token, or a malformed, unknown or revoked one"},
    403: {"description": "the token's scope does not cover this route"},
}
"""The responses every protected route may give, for the OpenAPI document."""


@dataclass(frozen=True, slots=True)
class ApiAuth:
    """The app's policy: check tokens against ``tokens``, or (None) check nothing
    (insecure-loopback mode)."""

    tokens: TokenStore | None

    def check(self, credentials: str | None, required: TokenScope) -> None:
        """Raise 401/403 unless ``credentials`` (a bearer token, or None) covers ``required``."""
        if self.tokens is None:
            return
        try:
            verify(self.tokens, credentials, required)
        except TokenInvalidError as exc:
            raise HTTPException(
                401, str(exc), headers={"WWW-Authenticate": 'Bearer error="invalid_token"'}
            ) from exc
        except TokenForbiddenError as exc:
            raise HTTPException(
                403, str(exc), headers={"WWW-Authenticate": 'Bearer error="insufficient_scope"'}
            ) from exc


def _policy(request: Request) -> ApiAuth:
    auth = getattr(request.app.state, "auth", None)
    if not isinstance(auth, ApiAuth):  # outside the lifespan: fail closed
        raise RuntimeError("the API's auth policy is not set")
    return auth


BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


# async: a plain ``def`` dependency would cost a worker-thread hop (about 1 ms) per request.
async def require_token(request: Request, bearer: BearerDep) -> None:
    """The data router's dependency: ``read`` for GET/HEAD/OPTIONS, ``admin`` otherwise."""
    required: TokenScope = "read" if request.method in _SAFE_METHODS else "admin"
    _policy(request).check(None if bearer is None else bearer.credentials, required)


async def require_admin(request: Request, bearer: BearerDep) -> None:
    """A route's dependency when it needs ``admin`` whatever its method."""
    _policy(request).check(None if bearer is None else bearer.credentials, "admin")


AdminOnly: Final = Depends(require_admin)
"""``dependencies=[AdminOnly]`` on a route that needs an ``admin`` token even for a GET."""
