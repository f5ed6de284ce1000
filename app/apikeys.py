"""API keys for hospital systems: format, generation, hashing and verification.

Format: ``bsk_<prefix>_<secret>``

- ``prefix``: 12 lower-case hex characters, random, stored in clear in
  ``ApiClient.key_prefix`` (UNIQUE) to find the client without scanning.
- ``secret``: 43 URL-safe base64 characters (32 random bytes).
- Only ``hash_api_key(key)`` = SHA-256 hex of the **whole key** is stored
  (``ApiClient.key_hash``). A key has 256 bits of entropy, so a fast hash is
  appropriate (no argon2 per request); comparison is constant-time.

Verifying a request (what the REST API does)::

    prefix = parse_api_key(token)          # None if malformed -> 401
    client = db.scalar(select(ApiClient).where(ApiClient.key_prefix == prefix))
    if client is None or client.revoked_at is not None or not verify_api_key(token, client.key_hash):
        -> 401

The key is shown once (``bradyscope admin create-api-key``) and never stored.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets

KEY_PREFIX = "bsk"
_KEY_RE = re.compile(r"^bsk_([0-9a-f]{12})_([A-Za-z0-9_-]{43})$")

# Scopes an API client may hold. The REST API decides which route needs which.
DATA_SCOPES = ("patients:read", "patients:write", "recordings:write", "results:read", "rigs:write")
AUDIT_READ = "audit:read"
"""Reading the audit trail (``GET /audit``): never given by default."""
SCOPES = (*DATA_SCOPES, AUDIT_READ)
DEFAULT_SCOPES = DATA_SCOPES


def generate_api_key() -> tuple[str, str]:
    """A new random key and its lookup prefix: ``(key, prefix)``."""
    prefix = secrets.token_hex(6)
    secret = secrets.token_urlsafe(32)
    key = f"{KEY_PREFIX}_{prefix}_{secret}"
    return key, prefix


def parse_api_key(key: str) -> str | None:
    """The prefix of a well-formed key, or None if ``key`` is not in the bradyscope format."""
    match = _KEY_RE.match(key.strip()) if isinstance(key, str) else None
    return match.group(1) if match else None


def hash_api_key(key: str) -> str:
    """SHA-256 (hex, 64 characters) of the whole key, as stored in ``ApiClient.key_hash``."""
    return hashlib.sha256(key.strip().encode("utf-8")).hexdigest()


def verify_api_key(key: str, key_hash: str) -> bool:
    """True when ``key`` hashes to ``key_hash`` (constant-time comparison)."""
    return hmac.compare_digest(hash_api_key(key), key_hash)
