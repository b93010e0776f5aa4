"""The REST API's bearer tokens: create, list, revoke, verify.

A token's text is ``wm_<id>_<secret>``: ``id`` is 12 hex digits (public: it names the token
in ``wardmap token list`` and ``revoke``), ``secret`` 43 URL-safe base64 characters (256 random
bits from :mod:`secrets`). The store keeps only the secret's SHA-256 digest (a fast hash is
enough for 256 random bits: there is nothing to guess, unlike a password), so a copy of the
database does not give anyone access. :func:`verify` compares digests with
:func:`hmac.compare_digest` (constant time), and hashes the presented secret even when the id
is unknown, so the time taken does not say which part was wrong.

Scopes: ``read`` passes every read route; ``admin`` passes those and the routes that change
state. The FastAPI side (which route needs which scope, 401/403) is ``server/api/auth.py``.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import time
from dataclasses import dataclass
from typing import Final

from wardmap.server.store import TokenRecord, TokenScope, TokenStore
from wardmap.shared.errors import WardmapError

__all__ = [
    "MAX_NAME_LEN",
    "SCOPES",
    "IssuedToken",
    "TokenError",
    "TokenForbiddenError",
    "TokenInvalidError",
    "create_token",
    "parse_scope",
    "revoke_token",
    "verify",
]

SCOPES: Final[tuple[TokenScope, ...]] = ("read", "admin")
MAX_NAME_LEN: Final = 200
_PREFIX: Final = "wm_"
_ID_HEX: Final = 12
_TOKEN_RE: Final = re.compile(r"wm_([0-9a-f]{12})_([A-Za-z0-9_-]{43})")
_DUMMY_DIGEST: Final = hashlib.sha256(b"no such token").digest()


class TokenError(WardmapError):
    """A token command or check failed (unknown token id, bad scope or name)."""


class TokenInvalidError(TokenError):
    """No token, a malformed one, an unknown one, a wrong secret, or a revoked token (HTTP 401)."""


class TokenForbiddenError(TokenError):
    """A valid token whose scope does not cover what was asked (HTTP 403)."""


@dataclass(frozen=True, slots=True)
class IssuedToken:
    """A token just created: ``text`` is shown once and never stored."""

    text: str
    record: TokenRecord


def parse_scope(text: str) -> TokenScope:
    """``read`` or ``admin``; TokenError otherwise."""
    if text == "read":
        return "read"
    if text == "admin":
        return "admin"
    raise TokenError(f"unknown token scope {text!r:.40}: expected read or admin")


def _digest(secret: str) -> bytes:
    return hashlib.sha256(secret.encode("ascii")).digest()


def create_token(store: TokenStore, scope: str, name: str = "", *, now_s: float | None = None) -> IssuedToken:
    """Create a token of ``scope`` and store its digest.

    Args:
        store: where the token is kept (the server's store).
        scope: ``read`` or ``admin``.
        name: what the token is for (printable, at most :data:`MAX_NAME_LEN` characters).
        now_s: creation time, wall-clock seconds (default: now).

    Raises:
        TokenError: a bad scope or name.
        StoreError: the store cannot write.
    """
    checked = parse_scope(scope)
    if len(name) > MAX_NAME_LEN or not name.isprintable():
        raise TokenError(f"token name must be printable and at most {MAX_NAME_LEN} characters")
    token_id = secrets.token_hex(_ID_HEX // 2)
    secret = secrets.token_urlsafe(32)
    record = TokenRecord(token_id, name, checked, _digest(secret), time.time() if now_s is None else now_s)
    store.add_token(record)
    return IssuedToken(f"{_PREFIX}{token_id}_{secret}", record)


def revoke_token(store: TokenStore, token_id: str, *, now_s: float | None = None) -> None:
    """Revoke ``token_id`` (it fails :func:`verify` from the next request on).

    Raises:
        TokenError: no valid token has that id.
    """
    if not store.revoke_token(token_id, time.time() if now_s is None else now_s):
        raise TokenError(f"no valid token with id {token_id!r:.40} (see wardmap token list)")


def verify(store: TokenStore, text: str | None, required: TokenScope) -> TokenRecord:
    """The stored token ``text`` names, if it is valid and its scope covers ``required``.

    Args:
        store: the tokens.
        text: the presented token (the bearer credentials), None when none came.
        required: ``read`` or ``admin``; an ``admin`` token covers ``read``.

    Raises:
        TokenInvalidError: no, malformed, unknown, wrong or revoked token.
        TokenForbiddenError: a valid ``read`` token where ``admin`` is required.
        StoreError: the store cannot be read.
    """
    if text is None:
        raise TokenInvalidError("a bearer token is required (Authorization: Bearer wm_...)")
    match = _TOKEN_RE.fullmatch(text)
    if match is None:
        raise TokenInvalidError("malformed token")
    token_id, secret = match.groups()
    record = store.token(token_id)
    ok = hmac.compare_digest(_digest(secret), _DUMMY_DIGEST if record is None else record.secret_sha256)
    if record is None or not ok or record.revoked_s is not None:
        raise TokenInvalidError("invalid or revoked token")
    if required == "admin" and record.scope != "admin":
        raise TokenForbiddenError(f"token {token_id} has scope {record.scope}; this needs admin")
    return record
