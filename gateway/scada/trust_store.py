"""The SCADA server's trust list, read so that one bad file cannot lock every client out.

asyncua's ``TrustStore`` reads every ``*.der``/``*.pem`` of ``pki_dir/trusted`` and
``pki_dir/crl`` and raises on the first it cannot parse. The server reloads the list
at every session, so one wrong file copied there by an engineer (a private key, a
copy cut short, a text note named ``.pem``) answered *every* client, trusted or not,
with ``BadInternalError``. Here a file that does not parse is skipped and named in a
warning once (again only if it changes); every other certificate and revocation list
counts as before. A skipped revocation list is a warning, not silence: the
certificates it would revoke are still refused if they are not in ``trusted/``.

The two loaders override ``TrustStore``'s per-folder readers (asyncua 2.1); the
tests in ``tests/test_scada.py`` fail if a later asyncua stops calling them.
"""

from __future__ import annotations

import logging
from pathlib import Path

from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.uacrypto import load_certificate
from cryptography import x509

_logger = logging.getLogger("gateway.scada.server")

SUFFIXES = (".der", ".pem")


class TolerantTrustStore(TrustStore):
    """``TrustStore`` that skips unreadable files; ``warned`` is kept by the caller across
    reloads so each bad file is named once."""

    def __init__(
        self,
        trust_locations: list[Path],
        crl_locations: list[Path],
        warned: set[tuple[str, int, int]],
    ) -> None:
        super().__init__(trust_locations, crl_locations)
        self._warned = warned

    async def _load_trust_location(self, location: Path) -> list[x509.Certificate]:
        certificates: list[x509.Certificate] = []
        for path in candidates(location):
            try:
                certificates.append(await load_certificate(path))
            except (ValueError, TypeError, OSError) as exc:
                self._skip(path, "certificate", exc)
        return certificates

    async def _load_crl_location(self, location: Path) -> list[x509.RevokedCertificate]:
        revoked: list[x509.RevokedCertificate] = []
        for path in candidates(location):
            try:
                revoked.extend(await self._load_crl(path))
            except (ValueError, TypeError, OSError) as exc:
                self._skip(path, "revocation list", exc)
        return revoked

    def _skip(self, path: Path, what: str, exc: Exception) -> None:
        try:
            stat = path.stat()
            key = (str(path), stat.st_mtime_ns, stat.st_size)
        except OSError:
            key = (str(path), 0, 0)
        if key in self._warned:
            return
        self._warned.add(key)
        _logger.warning(
            "%s: not a readable %s (%s); skipped, the others still count", path, what, exc
        )


def candidates(location: Path) -> list[Path]:
    """The files of ``location`` named ``*.der`` or ``*.pem``, in name order."""
    if not location.is_dir():
        return []
    return sorted(p for p in location.iterdir() if p.suffix.lower() in SUFFIXES and p.is_file())
