"""Signed models: an HMAC-SHA256 of a model's canonical JSON, with a key kept outside the store.

A model's ``sha256`` proves the file is whole, not who wrote it: anyone who can
write the store can change a number and recompute the checksum. With a key
configured, every model the software writes (``fit``, ``analyze --store``, a
proposal the residual monitor publishes) carries ``signature``, an HMAC-SHA256
of the same canonical bytes the checksum covers, and every model it reads (the
store's models, augmented models, proposals being promoted, the copies inside
version files) must carry a valid one; an unsigned or wrongly signed model is
refused naming the file. Without a key nothing is signed or checked.

The key is a file (64+ hex digits, or 32+ raw bytes) named by ``models.signing_key_file``
in the configuration or by the environment variable ``SPINDLE_MODEL_KEY_FILE``
(the configuration wins). A key file that others can read, or that anyone but its
owner can write, is refused: it must be readable by its owner (and group) only. See
docs/reliability/model-store.md for what this protects and what it does not.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
from pathlib import Path
from typing import Any

KEY_ENV = "SPINDLE_MODEL_KEY_FILE"
FIELD = "signature"
MIN_KEY_BYTES = 32

#: store folder (resolved) → key file named by the configuration for that store
_configured: dict[Path, Path] = {}


class SigningError(ValueError):
    """A key that cannot be used, or a model whose signature is missing or wrong."""


def load_key(path: str | Path) -> bytes:
    """The key in ``path``: hex text (64+ digits) or raw bytes (32+), refused if others read it."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
        raw = path.read_bytes()
    except OSError as exc:
        raise SigningError(f"model signing key {path}: {exc.strerror or exc}") from None
    if mode & stat.S_IROTH:
        raise SigningError(
            f"model signing key {path}: readable by every user (mode {stat.S_IMODE(mode):o}); "
            "make it chmod 600 (or 640 for a group) so only the gateway reads it"
        )
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        # Whoever may write the key may put in a key of their own and sign any model.
        who = "every user" if mode & stat.S_IWOTH else "its group"
        raise SigningError(
            f"model signing key {path}: writable by {who} (mode {stat.S_IMODE(mode):o}); "
            "make it chmod 600 (or 640 for a group) so only its owner can change it"
        )
    text = raw.strip()
    try:
        key = bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        key = raw
    if len(key) < MIN_KEY_BYTES:
        raise SigningError(
            f"model signing key {path}: {len(key)} bytes, at least {MIN_KEY_BYTES} expected "
            "(e.g. 'openssl rand -hex 32 > key')"
        )
    return key


def configure(store_dir: str | Path, key_file: str | Path | None) -> None:
    """The configuration names ``key_file`` for ``store_dir`` (None: only the env var)."""
    folder = Path(store_dir).resolve()
    if key_file is None:
        _configured.pop(folder, None)
    else:
        load_key(key_file)  # refused here, at the configuration, not at the first model
        _configured[folder] = Path(key_file)


def key_for_store(store_dir: str | Path) -> bytes | None:
    """The key for the store at ``store_dir``: configured, else ``$SPINDLE_MODEL_KEY_FILE``."""
    configured = _configured.get(Path(store_dir).resolve())
    if configured is not None:
        return load_key(configured)
    from_env = os.environ.get(KEY_ENV)
    return load_key(from_env) if from_env else None


def mac(key: bytes, canonical: bytes) -> str:
    """HMAC-SHA256 of the canonical bytes, hex."""
    return hmac.new(key, canonical, hashlib.sha256).hexdigest()


def sign(document: dict[str, Any], key: bytes | None, canonical: bytes) -> dict[str, Any]:
    """``document`` with its signature (unchanged without a key)."""
    if key is None:
        return document
    return document | {FIELD: {"alg": "hmac-sha256", "value": mac(key, canonical)}}


def verify(document: dict[str, Any], key: bytes | None, canonical: bytes, where: str) -> None:
    """Raise SigningError if a key is given and ``document`` is unsigned or wrongly signed."""
    if key is None:
        return
    signature = document.get(FIELD)
    if not isinstance(signature, dict) or "value" not in signature:
        raise SigningError(
            f"{where}: the model is not signed and a signing key is configured; "
            "refit or re-sign it with the key (docs/reliability/model-store.md)"
        )
    # Compared as bytes: compare_digest raises TypeError on a str that is not ASCII.
    given = str(signature["value"]).encode("utf-8")
    if signature.get("alg") != "hmac-sha256" or not hmac.compare_digest(
        given, mac(key, canonical).encode("ascii")
    ):
        raise SigningError(
            f"{where}: the model's signature does not match the configured key: "
            "it was changed after it was signed, or signed with another key"
        )
