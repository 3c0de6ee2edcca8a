"""Who may change the rig through ``hil monitor``: the exposure rule, the TLS identity and the
access token.

foxglove-sdk's WebSocket server (0.30) serves TLS (``wss://``, ``tls_cert``/``tls_key``) but has
no authentication hook: its handshake checks the subprotocol only, and a callback knows a client
by its id alone (unique for the server's lifetime). So the access check is in-band: a client
presents the token by setting the parameter ``hil.token``; a right token admits that connection
(its client id) to tuning, and every set and operator service of a connection not admitted is
refused with the reason. Reads are never gated.

The token is the rig key's derived key for this use (:func:`hal.secoc.derive` over
``"foxglove-tuning"``), in hex: whoever holds the rig key can print it (``hil monitor
--print-token``), and it opens nothing else (the CAN, features and parameter links use other
labels).

Modes (:func:`exposure`):

- ``open``: plain ``ws://`` on loopback; every client may change what ``--allow-tuning`` allows
  (whoever can reach the loopback port is a user of this host);
- ``token``: TLS (any host); a client must present the token first;
- ``closed``: plain ``ws://`` on another host (``--allow-remote`` alone); a read-only view: no
  client is ever admitted and no token is taken (it would cross the network in the clear).

``--allow-remote`` with ``--allow-tuning`` and no TLS is refused (:class:`ControllerConfigError`).
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import stat
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from hal.secoc import derive
from rt_controller.errors import ControllerConfigError

Mode = Literal["open", "token", "closed"]
TOKEN_LABEL = "foxglove-tuning"
"""The label of the rig key's derived key that is the access token."""
TOKEN_PARAMETER = "hil.token"
NO_TOKEN_REASON = (
    "this connection has not presented the access token: set the parameter hil.token to the "
    "output of `hil monitor --print-token` (same rig key), then retry"
)
BAD_TOKEN_REASON = "wrong access token in hil.token (see `hil monitor --print-token`)"
CLOSED_REASON = (
    "this remote view is read-only: changing the rig from another host needs TLS and the "
    "access token (hil monitor --tls-cert FILE --tls-key FILE --allow-tuning)"
)
ADMITTED_LINE = "access token accepted: this connection may change the rig"
OPEN_LINE = (
    "no access token is needed or checked here (plain ws:// on loopback): every client of this "
    "host may change the rig"
)
"""A token presented to an ``open`` monitor: not checked, so never said to be right."""


def tuning_token(key: bytes) -> str:
    """The access token of the rig key ``key`` (64 hex digits)."""
    return derive(key, TOKEN_LABEL).hex()


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def exposure(host: str, *, allow_remote: bool, allow_tuning: bool, tls: bool) -> Mode:
    """The access mode of a monitor on ``host``, or :class:`ControllerConfigError` (one line)
    for a combination that would expose the rig: another host without ``--allow-remote``, or
    remote tuning without TLS and the token."""
    if is_loopback(host):
        return "token" if tls else "open"
    if not allow_remote:
        raise ControllerConfigError(
            f"--host {host} is not a loopback address: the live view has no authentication; "
            "add --allow-remote to serve it anyway (read-only, or with TLS and the access token)"
        )
    if tls:
        return "token"
    if allow_tuning:
        raise ControllerConfigError(
            f"--allow-remote with --allow-tuning on {host} would let anyone who reaches the port "
            "arm, disarm and retune the rig: it needs TLS and the access token (--tls-cert FILE "
            "--tls-key FILE; clients set hil.token to `hil monitor --print-token`), or drop "
            "--allow-tuning for a read-only remote view"
        )
    return "closed"


@dataclass(frozen=True)
class TlsIdentity:
    """The server's PEM certificate (chain) and private key, for ``wss://``."""

    cert: bytes
    key: bytes

    @classmethod
    def load(cls, cert_file: str | Path, key_file: str | Path) -> TlsIdentity:
        """Read both files; :class:`ControllerConfigError` (one line) for a missing or
        unreadable file, one without the PEM block it should hold, or a private key that group
        or others may read."""
        cert = _read_pem(cert_file, "--tls-cert", b"-----BEGIN CERTIFICATE-----")
        key = _read_pem(key_file, "--tls-key", b"PRIVATE KEY-----")
        mode = os.stat(key_file).st_mode
        if mode & 0o077:
            raise ControllerConfigError(
                f"--tls-key {key_file}: mode {stat.S_IMODE(mode):04o} lets group/others read it; "
                f"run: chmod 600 {key_file}"
            )
        return cls(cert, key)


def _read_pem(path: str | Path, option: str, marker: bytes) -> bytes:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ControllerConfigError(f"{option} {path}: {exc.strerror or exc}") from None
    if marker not in data:
        what = "certificate" if option == "--tls-cert" else "private key"
        raise ControllerConfigError(f"{option} {path}: no PEM {what} in it")
    return data


class AccessGate:
    """Which connections may change the rig (see the module's modes). Thread-safe: the SDK calls
    its listener from its own threads. :attr:`counts`: ``admitted``, ``bad_token`` (wrong tokens
    presented) and ``refused`` (changes refused for want of the token)."""

    def __init__(self, mode: Mode, key: bytes | None = None) -> None:
        if mode == "token" and key is None:
            raise ValueError("the token mode needs the rig key")
        self.mode: Mode = mode
        self._token = tuning_token(key).encode() if key is not None else b""
        self._admitted: set[int] = set()
        self._lock = threading.Lock()
        self.counts = {"admitted": 0, "bad_token": 0, "refused": 0}

    def present(self, client_id: int, token: object) -> str:
        """A client presents ``token`` (the value it set ``hil.token`` to): the outcome line.
        A right token admits the connection; a wrong one changes nothing."""
        if self.mode == "open":
            return OPEN_LINE
        if self.mode == "closed":
            with self._lock:
                self.counts["refused"] += 1
            return f"refused: {CLOSED_REASON}"
        given = str(token).strip().encode() if isinstance(token, str) else b""
        ok = hmac.compare_digest(given, self._token)
        with self._lock:
            if ok:
                self.counts["admitted"] += client_id not in self._admitted
                self._admitted.add(client_id)
            else:
                self.counts["bad_token"] += 1
        return ADMITTED_LINE if ok else f"refused: {BAD_TOKEN_REASON}"

    def refusal(self, client_id: int) -> str | None:
        """None when ``client_id`` may change the rig, else why not (counted)."""
        if self.mode == "open":
            return None
        with self._lock:
            if self.mode == "token" and client_id in self._admitted:
                return None
            self.counts["refused"] += 1
        return NO_TOKEN_REASON if self.mode == "token" else CLOSED_REASON


__all__ = [
    "TOKEN_PARAMETER",
    "AccessGate",
    "TlsIdentity",
    "exposure",
    "is_loopback",
    "tuning_token",
]
