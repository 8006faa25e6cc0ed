"""Lock out a client that keeps failing to log in, so passwords cannot be guessed fast.

An OPC UA client can open sessions as fast as the handshakes allow (about 7 a
second on loopback), and each one is a password guess. The throttle keeps, for
each *key* — a user name, and a remote address — the failed logins of the last
``window_s``:

* a user name is locked by the ``max_failures``-th failure within that window,
  from whatever addresses (a client cannot rotate addresses to keep guessing one
  account);
* an address is locked only when its failures within that window name
  ``max_failures`` different users (one client trying password after password on
  account after account). One person mistyping their own password at a shared
  terminal locks their account, not the terminal: a colleague at the same address
  still logs in with theirs.

A lock lasts ``lockout_s``; every further lockout of the same key doubles, up to
``max_lockout_s``. While a key is locked, every login through it is refused without
looking at the password, the right one included, so guesses made during a lockout
teach nothing. A key that has failed nothing for ``forget_s`` starts over. A
successful login clears its user's failures, also from its address's count, and
leaves the other users' failures from that address counted.

Locking per user name means anyone who can reach the server can lock an account out
for a while; the lockout is bounded and every lockout is logged, and the shift can log
in again when it ends.

The throttle is pure bookkeeping on an injected clock (``now``, seconds); the SCADA
server and the web console call it with the keys of one login, ``[("address", …),
("user", …)]``.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from gateway.limits import LoginLimits

#: The lockout policy (its one definition: :class:`gateway.limits.LoginLimits`).
ThrottlePolicy = LoginLimits

Key = tuple[str, str]  # ("address", "10.0.0.7") or ("user", "alice")

MAX_KEYS = 10_000  # a flood of made-up user names cannot grow the table without bound


@dataclass
class _KeyState:
    failures: deque[tuple[float, str]] = field(default_factory=deque)  # (time, user name)
    locked_until_s: float = 0.0
    lockouts: int = 0
    last_failure_s: float = 0.0


@dataclass(frozen=True)
class Lockout:
    """A lockout that has just started (for the one log line it deserves)."""

    key: Key
    duration_s: float
    failures: int


class LoginThrottle:
    def __init__(self, policy: ThrottlePolicy, now: Callable[[], float] = time.monotonic) -> None:
        self.policy = policy
        self._now = now
        self._keys: dict[Key, _KeyState] = {}
        self.checked = 0  # logins whose password was compared
        self.refused_locked = 0  # logins refused unchecked because a key was locked

    def locked_for_s(self, keys: Iterable[Key]) -> float:
        """Seconds until every one of ``keys`` is unlocked (0: the login may be checked)."""
        now = self._now()
        remaining = 0.0
        for key in keys:
            state = self._keys.get(key)
            if state is not None:
                remaining = max(remaining, state.locked_until_s - now)
        return remaining

    def refuse_locked(self, keys: Iterable[Key]) -> bool:
        """True (and counted) if the login must be refused unchecked."""
        if self.locked_for_s(keys) > 0:
            self.refused_locked += 1
            return True
        self.checked += 1
        return False

    def failed(self, keys: Iterable[Key]) -> list[Lockout]:
        """Record a failed login through ``keys``; the lockouts it started."""
        now = self._now()
        self._forget_idle(now)
        keys = list(keys)
        user = next((value for kind, value in keys if kind == "user"), "")
        started = []
        for key in keys:
            state = self._keys.setdefault(key, _KeyState())
            if now - state.last_failure_s > self.policy.forget_s:
                state.lockouts = 0
            state.last_failure_s = now
            state.failures.append((now, user))
            while state.failures and now - state.failures[0][0] > self.policy.window_s:
                state.failures.popleft()
            if self._count(key, state) >= self.policy.max_failures:
                duration = self.policy.lockout_for(state.lockouts)
                state.locked_until_s = now + duration
                state.lockouts += 1
                started.append(Lockout(key, duration, len(state.failures)))
                state.failures.clear()
        return started

    @staticmethod
    def _count(key: Key, state: _KeyState) -> int:
        """What locks a key: a user's failures; the different users an address failed."""
        if key[0] == "address":
            return len({user for _, user in state.failures})
        return len(state.failures)

    def succeeded(self, keys: Iterable[Key]) -> None:
        """A right password: its user starts over, and so do its failures at the address."""
        keys = list(keys)
        user = next((value for kind, value in keys if kind == "user"), "")
        for key in keys:
            state = self._keys.get(key)
            if state is None:
                continue
            if key[0] == "address":
                state.failures = deque(f for f in state.failures if f[1] != user)
            else:
                del self._keys[key]

    def _forget_idle(self, now: float) -> None:
        if len(self._keys) < MAX_KEYS:
            return
        idle = [
            key
            for key, state in self._keys.items()
            if state.locked_until_s <= now and now - state.last_failure_s > self.policy.window_s
        ]
        for key in idle:
            del self._keys[key]
        if len(self._keys) >= MAX_KEYS:  # all busy: drop the longest idle
            oldest = sorted(self._keys, key=lambda k: self._keys[k].last_failure_s)
            for key in oldest[: len(self._keys) - MAX_KEYS + 1]:
                del self._keys[key]
