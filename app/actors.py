"""Who makes a request: :class:`Actor`, an API client or a logged-in browser user.

The audit trail records actors and the authentication layer (:mod:`app.auth`)
creates them; both import them from here, so neither imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from app.apikeys import AUDIT_READ, DATA_SCOPES, SCOPES

ADMIN_SCOPE = "admin"
# Scopes of browser users by role (API clients have their own list). Admins and auditors
# read the audit trail; an auditor (an IT or data-protection officer) reads nothing else.
ROLE_SCOPES: dict[str, frozenset[str]] = {
    "clinician": frozenset(DATA_SCOPES),
    "admin": frozenset((*SCOPES, ADMIN_SCOPE)),
    "auditor": frozenset((AUDIT_READ,)),
}


@dataclass(frozen=True)
class Actor:
    """Who makes a request: an API client or a logged-in browser user.

    Attributes
    ----------
    type : {"api_client", "user"}
    id : int
        ``ApiClient.id`` or ``User.id``.
    name : str
        Client name or user e-mail (for logs; never shown to other users).
    scopes : frozenset of str
    role : str or None
        The user's role (``clinician``/``admin``); ``None`` for API clients.
    csrf_token : str or None
        The browser session's CSRF token (``None`` for API clients).
    """

    type: Literal["api_client", "user"]
    id: int
    name: str
    scopes: frozenset[str] = field(default_factory=frozenset)
    role: str | None = None
    csrf_token: str | None = None

    def has_scope(self, scope: str) -> bool:
        return scope in self.scopes or ADMIN_SCOPE in self.scopes

    @property
    def user_id(self) -> int | None:
        """The user's id for ``created_by_user_id`` columns (``None`` for API clients)."""
        return self.id if self.type == "user" else None
