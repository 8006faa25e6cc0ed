"""Who is using the console: login against the SCADA accounts, sessions, CSRF, origin.

* Accounts and roles are the SCADA server's (:class:`gateway.scada.server.ScadaUser`):
  viewers read, operators may also promote, reject and roll back models.
* Password guesses are throttled by :class:`gateway.scada.login_throttle.LoginThrottle`,
  keyed on the remote address and the user name, exactly as the SCADA server does.
* A login gives a random session id in a cookie (HttpOnly, SameSite=Strict, Secure
  under TLS); sessions live in memory and end at ``session_s`` or a restart.
* Every POST must carry the session's CSRF token (a hidden form field) and, when the
  browser sends one, an Origin (or Referer) naming this very host: a page on another
  site can neither read the token nor pass the origin check.
"""

from __future__ import annotations

import hmac
import logging
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

from aiohttp import web

from gateway.scada.login_throttle import Key, LoginThrottle, ThrottlePolicy
from gateway.scada.server import ScadaUser

log = logging.getLogger(__name__)

COOKIE = "console_session"
MAX_SESSIONS = 1000


@dataclass(frozen=True)
class Session:
    user: str
    role: str
    csrf: str
    expires_s: float

    @property
    def operator(self) -> bool:
        return self.role == "operator"


class Auth:
    """Logins, sessions and the checks every request goes through."""

    def __init__(
        self,
        users: Sequence[ScadaUser],
        policy: ThrottlePolicy,
        session_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._users = {u.username: u for u in users}
        self.throttle = LoginThrottle(policy, clock)
        self._session_s = session_s
        self._clock = clock
        self._sessions: dict[str, Session] = {}

    def login(self, username: str, password: str, address: str) -> str | None:
        """A new session id, or None (wrong password, unknown user or locked out)."""
        keys: list[Key] = [("address", address), ("user", username)]
        if self.throttle.refuse_locked(keys):
            log.warning("console login refused (locked out) for %r from %s", username, address)
            return None
        user = self._users.get(username)
        expected = (user.password if user is not None else "\0 no such user").encode()
        if user is None or not hmac.compare_digest(password.encode(), expected):
            log.warning("console login refused for user %r from %s", username, address)
            for lockout in self.throttle.failed(keys):
                log.warning(
                    "console logins through %s %s locked for %.0f s after %d failures",
                    *lockout.key,
                    lockout.duration_s,
                    lockout.failures,
                )
            return None
        self.throttle.succeeded(keys)
        self._expire()
        sid = secrets.token_urlsafe(32)
        self._sessions[sid] = Session(
            user.username, user.role, secrets.token_urlsafe(32), self._clock() + self._session_s
        )
        log.info("console login: %s (%s) from %s", user.username, user.role, address)
        return sid

    def logout(self, sid: str) -> None:
        self._sessions.pop(sid, None)

    def session(self, request: web.Request) -> Session | None:
        sid = request.cookies.get(COOKIE, "")
        session = self._sessions.get(sid)
        if session is None or session.expires_s < self._clock():
            return None
        return session

    def _expire(self) -> None:
        now = self._clock()
        for sid in [s for s, v in self._sessions.items() if v.expires_s < now]:
            del self._sessions[sid]
        while len(self._sessions) >= MAX_SESSIONS:
            del self._sessions[next(iter(self._sessions))]


#: Where the middleware keeps the request's session (None: not logged in).
SESSION = web.RequestKey[Session | None]("session")


def same_origin(request: web.Request) -> bool:
    """False when the browser says the request comes from another site."""
    source = request.headers.get("Origin") or request.headers.get("Referer")
    if source is None:
        return True  # not a browser's cross-site form (browsers send Origin on POST)
    parts = urlsplit(source)
    return parts.netloc == request.host and parts.scheme == request.scheme


def csrf_ok(session: Session, token: str) -> bool:
    return hmac.compare_digest(session.csrf.encode(), token.encode())
