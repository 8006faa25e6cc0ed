"""Signed models: an HMAC-SHA256 of a model's canonical JSON, with a key kept outside the store.

A model's ``sha256`` proves the file is whole, not who wrote it: anyone who can
write the store can change a number and recompute the checksum. Every model the
software writes (``fit``, ``analyze --store``, a proposal the residual monitor
publishes, ``models sign``) carries ``signature``, an HMAC-SHA256 of the same
canonical bytes the checksum covers, and every model it reads (the store's
models, augmented models, proposals being promoted, the copies inside version
files) must carry a valid one; an unsigned or wrongly signed model is refused
naming the file.

Signed by default. The key is a file (64+ hex digits, or 32+ raw bytes): the one
``models.signing_key_file`` of the configuration names for the store, else
``$SPINDLE_MODEL_KEY_FILE``, else :func:`default_key_file`
(``$XDG_CONFIG_HOME/spindle-gateway/model-signing.key``, ``~/.config/…`` without
the variable), as SSH keeps its keys: outside every store. A command that writes
models makes it on first use (:func:`create_key`: random, mode 600, written whole
or not at all); a reader never makes one, it refuses what it cannot check. A store
is unsigned only by the explicit setting ``models.signing: false``
(:func:`configure`): nothing is then signed or checked.

A key file that others can read, or that anyone but its owner can write, is
refused: it must be readable by its owner (and group) only. See
docs/reliability/model-store.md for what this protects and what it does not.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import stat
from pathlib import Path
from typing import Any

KEY_ENV = "SPINDLE_MODEL_KEY_FILE"
FIELD = "signature"
MIN_KEY_BYTES = 32
#: the default key's place under the user's configuration folder (XDG)
DEFAULT_KEY = Path("spindle-gateway") / "model-signing.key"

#: store folder (resolved) → key file named by the configuration for that store
_configured: dict[Path, Path] = {}
#: store folders (resolved) the configuration declares unsigned (``models.signing: false``)
_unsigned: set[Path] = set()


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


def default_key_file() -> Path:
    """The key used when neither the configuration nor ``$SPINDLE_MODEL_KEY_FILE`` names one:
    ``$XDG_CONFIG_HOME/spindle-gateway/model-signing.key`` (``~/.config`` without it)."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / DEFAULT_KEY


def configure(store_dir: str | Path, key_file: str | Path | None, enabled: bool = True) -> None:
    """The configuration names ``key_file`` for ``store_dir`` (None: the env var or the
    default), or declares it unsigned (``enabled`` False: nothing signed or checked)."""
    folder = Path(store_dir).resolve()
    _configured.pop(folder, None)
    _unsigned.discard(folder)
    if not enabled:
        _unsigned.add(folder)
    elif key_file is not None:
        load_key(key_file)  # refused here, at the configuration, not at the first model
        _configured[folder] = Path(key_file)


def key_file_for_store(store_dir: str | Path) -> Path | None:
    """Where the key for ``store_dir`` is (None: the store is declared unsigned)."""
    folder = Path(store_dir).resolve()
    if folder in _unsigned:
        return None
    configured = _configured.get(folder)
    if configured is not None:
        return configured
    from_env = os.environ.get(KEY_ENV)
    return Path(from_env) if from_env else default_key_file()


def key_for_store(store_dir: str | Path, *, create: bool = False) -> bytes | None:
    """The key for the store at ``store_dir`` (None only for a store declared unsigned).

    ``create``: a writer of models makes the key on first use (:func:`create_key`); a
    reader that finds none raises SigningError saying where it was looked for."""
    path = key_file_for_store(store_dir)
    if path is None:
        return None
    if create and not path.exists():
        create_key(path)
    elif not path.exists():
        raise SigningError(
            f"model signing key {path} does not exist: the models of {store_dir} are "
            "checked against it (models are signed by default). Sign the store's models "
            f"with 'python -m gateway models sign --store {store_dir}', which makes the key, "
            "or point models.signing_key_file (or SPINDLE_MODEL_KEY_FILE) at the key they "
            "were signed with, or set models.signing: false for an unsigned store"
        )
    return load_key(path)


def create_key(path: Path) -> Path:
    """A new random key at ``path`` (64 hex digits, mode 600, its folder 700 if made here),
    written whole or not at all; if another process made one meanwhile, that one stays."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    handle = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(handle, (os.urandom(MIN_KEY_BYTES).hex() + "\n").encode("ascii"))
        os.fsync(handle)
        os.close(handle)
        handle = -1
        with contextlib.suppress(FileExistsError):  # never over a key that exists
            os.link(tmp, path)
    finally:
        if handle >= 0:
            os.close(handle)
        tmp.unlink(missing_ok=True)
    return path


def mac(key: bytes, canonical: bytes) -> str:
    """HMAC-SHA256 of the canonical bytes, hex."""
    return hmac.new(key, canonical, hashlib.sha256).hexdigest()


def sign(document: dict[str, Any], key: bytes | None, canonical: bytes) -> dict[str, Any]:
    """``document`` with its signature (unchanged for a store declared unsigned: no key)."""
    if key is None:
        return document
    return document | {FIELD: {"alg": "hmac-sha256", "value": mac(key, canonical)}}


def verify(document: dict[str, Any], key: bytes | None, canonical: bytes, where: str) -> None:
    """Raise SigningError if a key is given and ``document`` is unsigned or wrongly signed
    (None: a store declared unsigned, nothing checked)."""
    if key is None:
        return
    signature = document.get(FIELD)
    if not isinstance(signature, dict) or "value" not in signature:
        raise SigningError(
            f"{where}: the model is not signed; models are signed by default: if it is "
            "yours, sign the store's models with 'python -m gateway models sign --store "
            "STORE' (or refit it), or set models.signing: false (docs/reliability/model-store.md)"
        )
    # Compared as bytes: compare_digest raises TypeError on a str that is not ASCII.
    given = str(signature["value"]).encode("utf-8")
    if signature.get("alg") != "hmac-sha256" or not hmac.compare_digest(
        given, mac(key, canonical).encode("ascii")
    ):
        raise SigningError(
            f"{where}: the model's signature does not match the signing key: "
            "it was changed after it was signed, or signed with another key"
        )
