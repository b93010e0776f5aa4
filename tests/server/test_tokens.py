"""``server/tokens.py`` on a real SQLite store: the token text is never stored (only its
digest), scopes nest (admin covers read), and every way a token can be wrong raises
TokenInvalidError; revocation and bad input give clear TokenErrors."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from wardmap.server.store import open_store
from wardmap.server.tokens import (
    TokenError,
    TokenForbiddenError,
    TokenInvalidError,
    create_token,
    revoke_token,
    verify,
)


def test_only_the_digest_is_stored(tmp_path: Path) -> None:
    """The database file holds the secret's SHA-256 and never the secret; the record matches."""
    path = tmp_path / "m.db"
    with open_store(f"sqlite:///{path}") as store:
        issued = create_token(store, "read", "dashboard", now_s=100.0)
        (record,) = store.tokens()
    secret = issued.text.split("_", 2)[2]
    assert record == issued.record and record.name == "dashboard" and record.created_s == 100.0
    assert record.secret_sha256 == hashlib.sha256(secret.encode()).digest()
    raw = b"".join(p.read_bytes() for p in tmp_path.glob("m.db*"))  # the file and any WAL left
    assert secret.encode() not in raw and record.secret_sha256 in raw


def test_scopes_nest_and_wrong_tokens_are_invalid(tmp_path: Path) -> None:
    """admin covers read and admin; read covers read only (forbidden, not invalid, on admin);
    None, malformed, unknown-id, wrong-secret and revoked tokens are invalid."""
    with open_store(f"sqlite:///{tmp_path / 'm.db'}") as store:
        read, admin = create_token(store, "read"), create_token(store, "admin")
        assert verify(store, admin.text, "admin").scope == "admin"
        assert verify(store, admin.text, "read").token_id == admin.record.token_id
        assert verify(store, read.text, "read").scope == "read"
        with pytest.raises(TokenForbiddenError, match="needs admin"):
            verify(store, read.text, "admin")
        secret = read.text.split("_", 2)[2]
        for text in (None, "", "wm_", read.text + "=", "wm_000000000000_" + secret,
                     read.text[:-1] + ("a" if read.text[-1] != "a" else "b"), "wm_" + "0" * 10_000):
            with pytest.raises(TokenInvalidError):
                verify(store, text, "read")
        revoke_token(store, read.record.token_id, now_s=5.0)
        with pytest.raises(TokenInvalidError, match="revoked"):
            verify(store, read.text, "read")
        assert store.token(read.record.token_id).revoked_s == 5.0  # type: ignore[union-attr]
        assert verify(store, admin.text, "read").revoked_s is None  # the other token still works


def test_bad_scope_name_and_unknown_revocation(tmp_path: Path) -> None:
    """An unknown scope, an unprintable or overlong name, and revoking an unknown or already
    revoked id each raise TokenError naming the problem; nothing is stored."""
    with open_store(f"sqlite:///{tmp_path / 'm.db'}") as store:
        with pytest.raises(TokenError, match="unknown token scope"):
            create_token(store, "write")
        for name in ("tab\there", "x" * 201):
            with pytest.raises(TokenError, match="printable"):
                create_token(store, "read", name)
        assert store.tokens() == []
        with pytest.raises(TokenError, match="no valid token"):
            revoke_token(store, "abc")
        made = create_token(store, "read")
        revoke_token(store, made.record.token_id)
        with pytest.raises(TokenError, match="no valid token"):
            revoke_token(store, made.record.token_id)
