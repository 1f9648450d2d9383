"""Who may do what: the roles of the REST API's bearer tokens, checked in one place.

Three roles, each with its own token (``[auth]`` keys or environment variables, see
:mod:`service.config`): ``read`` (every GET, when ``[auth] read = "token"``), ``operator`` (start
and cancel measurements) and ``admin`` (everything: schedules, and any configuration, calibration or
deletion endpoint). A higher role holds every lower one. :func:`check` is used both by the route
dependencies (:mod:`service.api.deps`) and by the body guard (:mod:`service.api.guard`), which
checks the token of a POST/PUT/PATCH before its body is read.

Token values are secrets: no message here contains the token presented or the one configured.
"""

from __future__ import annotations

import secrets

from service.config import TOKEN_ENV, TOKEN_ENVS, RigConfig, Role

RANK: dict[Role, int] = {"read": 0, "operator": 1, "admin": 2}
ROLES: tuple[Role, ...] = ("read", "operator", "admin")
WWW_AUTHENTICATE = {"WWW-Authenticate": "Bearer"}


class Denied(Exception):
    """The request may not do this: ``status`` 401 (no or unknown token) or 403 (known token of a
    lower role, or no token of the needed role configured), ``detail`` for the client."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail

    @property
    def headers(self) -> dict[str, str]:
        return WWW_AUTHENTICATE if self.status == 401 else {}


def bearer(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value (scheme case-insensitive), else None."""
    if not authorization:
        return None
    scheme, _, token = authorization.strip().partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        return None
    return token


def role_of(config: RigConfig, token: str) -> Role | None:
    """The highest role whose configured token is ``token`` (every role compared, in constant time)."""
    found: Role | None = None
    presented = token.encode()
    for role in ROLES:
        expected = config.role_token(role)
        if expected is not None and secrets.compare_digest(presented, expected.encode()):
            found = role
    return found


def _where(role: Role) -> str:
    envs = TOKEN_ENVS[role] + (f" (or the deprecated {TOKEN_ENV})" if role == "operator" else "")
    return f"[auth] {role}_token or {envs}"


def check(config: RigConfig, token: str | None, need: Role) -> None:
    """Raise :class:`Denied` unless ``token`` holds role ``need`` (reads are free when ``[auth] read = "open"``)."""
    if need == "read" and config.auth.read == "open":
        return
    able = [r for r in ROLES if RANK[r] >= RANK[need]]
    if all(config.role_token(r) is None for r in able):
        what = {
            "read": 'reads need a token ([auth] read = "token")',
            "operator": "write endpoints are disabled",
            "admin": "admin endpoints are disabled",
        }[need]
        raise Denied(403, f"{what} and none is configured: set {' or '.join(_where(r) for r in able)}")
    if token is None:
        raise Denied(401, "missing bearer token (Authorization: Bearer <token>)")
    role = role_of(config, token)
    if role is None:
        raise Denied(401, "invalid bearer token")
    if RANK[role] < RANK[need]:
        article = "an" if role in ("admin", "operator") else "a"
        raise Denied(403, f"this needs the {' or '.join(able)} token; the token given is {article} {role} token")
