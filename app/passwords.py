"""Password hashing with argon2id (argon2-cffi), shared by the CLI and the web login.

>>> h = hash_password("correct horse battery staple")
>>> verify_password(h, "correct horse battery staple")
True
"""

from __future__ import annotations

import functools
import re

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

from app.errors import InvalidRequestError

MIN_PASSWORD_LENGTH = 15
"""NIST SP 800-63B-4 (2025), 3.1.1.2: at least 15 characters for a password that is
the only factor (``BRADYSCOPE_PASSWORD_MIN_LENGTH`` may lower it, never below 8)."""
MAX_PASSWORD_LENGTH = 1024
MIN_GUESSES_LOG10 = 8.0
"""A password that zxcvbn's dictionaries and patterns would find in fewer than 10^8 guesses
(score below 3) is refused: a common or breached password, a word with small changes, a
repeat, a sequence, a keyboard walk, or something built from the e-mail address."""
_ZXCVBN_MAX_LENGTH = 72  # zxcvbn's own input limit; longer passwords are judged on this prefix
_hasher = PasswordHasher()  # argon2id with the library's current recommended parameters


def check_password_strength(
    password: str, *, email: str | None = None, min_length: int = MIN_PASSWORD_LENGTH
) -> None:
    """Refuse a password that NIST SP 800-63B-4 would not let a verifier accept.

    No composition rules (NIST 3.1.1.2 forbids them): only a minimum length and a
    blocklist of guessable values, here zxcvbn's (its bundled frequency lists of
    common and breached passwords, English words, names and surnames, plus
    repeats, sequences, keyboard walks and l33t substitutions), with the
    account's e-mail address as a context-specific word.

    Raises
    ------
    InvalidRequestError
        One sentence saying why, and what would be accepted.
    """
    if not isinstance(password, str):
        raise InvalidRequestError("the password must be text.")
    if len(password) < min_length:
        raise InvalidRequestError(
            f"the password has {len(password)} characters; use at least {min_length}"
            " (a passphrase of a few unrelated words is easy to remember)."
        )
    if len(password) > MAX_PASSWORD_LENGTH:
        raise InvalidRequestError(
            f"the password is longer than {MAX_PASSWORD_LENGTH} characters; use a shorter one."
        )
    context = ["bradyscope"]
    if email:
        local = email.split("@", 1)[0]
        context += [email, local, *(part for part in re.split(r"[^a-zA-Z0-9]+", local) if part)]
    if email and email.strip().lower() in password.lower():
        raise InvalidRequestError("the password contains the e-mail address; choose another one.")
    from zxcvbn import zxcvbn  # its frequency lists take ~0.3 s to load: not at start-up

    verdict = zxcvbn(password[:_ZXCVBN_MAX_LENGTH], user_inputs=context)
    if float(verdict["guesses_log10"]) < MIN_GUESSES_LOG10:
        warning = str(verdict["feedback"].get("warning") or "").strip()
        why = f" ({warning.rstrip('.')})" if warning else ""
        raise InvalidRequestError(
            f"the password is too easy to guess{why}; use a passphrase of a few unrelated words."
        )


def hash_password(password: str) -> str:
    """The argon2id hash (PHC string, salt included) of ``password``."""
    if not isinstance(password, str) or not password:
        raise ValueError("password must be a non-empty string")
    return _hasher.hash(password)


def verify_password(password_hash: str, password: str) -> bool:
    """True when ``password`` matches ``password_hash``; False for a mismatch or a bad hash."""
    try:
        return _hasher.verify(password_hash, password)
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def needs_rehash(password_hash: str) -> bool:
    """True when the hash was made with older parameters (re-hash it after a good login)."""
    try:
        return _hasher.check_needs_rehash(password_hash)
    except InvalidHashError:
        return True


NO_PASSWORD = "!no-local-password"
"""Stored instead of a hash for accounts that log in only through single sign-on:
it is no argon2 hash, so no password ever verifies against it."""


@functools.cache
def dummy_hash() -> str:
    """A hash of a random password: verify against it when the user does not exist, so that
    a login for an unknown e-mail takes as long as one with a wrong password.

    Made on first use (an argon2 hash costs a fraction of a second), not at start-up.
    """
    return _hasher.hash("bradyscope-no-such-user-timing-guard")
