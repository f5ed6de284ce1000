"""Password hashing with argon2id (argon2-cffi), shared by the CLI and the web login.

>>> h = hash_password("correct horse battery staple")
>>> verify_password(h, "correct horse battery staple")
True
"""

from __future__ import annotations

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

from app.errors import InvalidRequestError

MIN_PASSWORD_LENGTH = 8
_hasher = PasswordHasher()  # argon2id with the library's current recommended parameters


def check_password_strength(password: str) -> None:
    """Raise :class:`InvalidRequestError` if ``password`` is too short to be accepted."""
    if len(password) < MIN_PASSWORD_LENGTH:
        raise InvalidRequestError(
            f"the password has {len(password)} characters; use at least {MIN_PASSWORD_LENGTH}."
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


# A hash of a random password: verify against it when the user does not exist, so that
# a login for an unknown e-mail takes as long as one with a wrong password.
DUMMY_HASH = _hasher.hash("bradyscope-no-such-user-timing-guard")
