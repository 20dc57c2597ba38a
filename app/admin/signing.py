"""Signed values for the admin dashboard's cookies, and the secret that signs them (stdlib hmac).

    secret = load_or_create_secret(settings)            # INVISIBLE_MAP_SESSION_SECRET, or the file
    signer = Signer(secret)
    token = signer.sign("login", {"sub": "key:3"}, ttl_s=3600)
    signer.unsign("login", token)                        # {"sub": "key:3", "exp": …} or None
    signer.csrf_token(nonce)                             # the CSRF token of a login's nonce

A token is ``base64url(JSON payload) "." base64url(HMAC-SHA256)``. The MAC covers a *purpose*
("login", "flash", …) as well as the payload, so a value signed for one cookie is refused as
another. Every payload carries ``exp`` (Unix time, s); an expired token is refused like a forged
one.

The secret: ``INVISIBLE_MAP_SESSION_SECRET`` when set; otherwise 32 random bytes kept in the file
``admin-session-secret`` in the data directory, created once with mode 0600 (written to a temporary
file and linked into place, so two API processes starting together agree on one secret).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import json
import logging
import os
import secrets
import time
from pathlib import Path
from typing import Any

from app.config import Settings

logger = logging.getLogger(__name__)

SECRET_FILE_NAME = "admin-session-secret"
SECRET_BYTES = 32


def load_or_create_secret(settings: Settings) -> bytes:
    """The signing secret: the setting, or the data directory's secret file (made if missing)."""
    if settings.session_secret:
        return settings.session_secret.encode()
    return _secret_file(settings.data_dir / SECRET_FILE_NAME)


def _secret_file(path: Path) -> bytes:
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(descriptor, "w") as file:
            file.write(secrets.token_hex(SECRET_BYTES) + "\n")
        try:
            os.link(temporary, path)  # fails if another process made it first: use theirs
        except FileExistsError:
            pass
        finally:
            temporary.unlink()
    if path.stat().st_mode & 0o077:
        logger.warning("%s is readable by other users: chmod 600 it", path)
    secret = path.read_text().strip()
    if len(secret) < SECRET_BYTES:
        raise ValueError(f"{path} holds no usable secret (delete it to make a new one)")
    return secret.encode()


class Signer:
    """Signs and checks the dashboard's tokens with one secret."""

    def __init__(self, secret: bytes) -> None:
        self._secret = secret

    def sign(self, purpose: str, payload: dict[str, Any], *, ttl_s: float) -> str:
        """A token of ``payload`` (plus ``exp``, now + ``ttl_s``) for ``purpose``."""
        body = {**payload, "exp": int(time.time() + ttl_s)}
        encoded = _b64(json.dumps(body, separators=(",", ":"), sort_keys=True).encode())
        return f"{encoded}.{_b64(self._mac(purpose, encoded))}"

    def unsign(self, purpose: str, token: str | None) -> dict[str, Any] | None:
        """The payload of a valid, unexpired token signed for ``purpose``; None otherwise."""
        if not token or token.count(".") != 1:
            return None
        encoded, mac = token.split(".")
        try:
            given = _unb64(mac)
            payload = json.loads(_unb64(encoded))
        except (ValueError, binascii.Error):
            return None
        if not hmac.compare_digest(given, self._mac(purpose, encoded)):
            return None
        if not isinstance(payload, dict) or not isinstance(payload.get("exp"), int):
            return None
        if payload["exp"] <= time.time():
            return None
        return payload

    def csrf_token(self, nonce: str) -> str:
        """The CSRF token that goes with a login whose cookie carries ``nonce``."""
        return _b64(self._mac("csrf", nonce))

    def fingerprint(self, credential: str) -> str:
        """A short keyed digest of a credential (e.g. the environment's admin key), to notice
        later that it changed without putting it in a cookie."""
        return _b64(self._mac("credential", credential))[:22]

    def _mac(self, purpose: str, message: str) -> bytes:
        return hmac.new(self._secret, f"{purpose}\x1f{message}".encode(), hashlib.sha256).digest()


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
