"""Authenticated frames of one rig, in the manner of AUTOSAR SecOC: a per-rig key, a freshness
value per sender and message, a truncated MAC (HMAC-SHA256, standard library ``hmac``).

Keys
----
A rig key is 32 random bytes, stored as one line of 64 hex digits in a file of mode 0600
(:func:`write_key_file`, ``hil keygen FILE``). :func:`load_key_file` refuses a missing or
unreadable file, a file readable or writable by group or others, and a malformed one, each with
one line saying what to do (:class:`HalKeyError`, which the ``hil`` CLI turns into exit 2). Every
use gets its own derived key (:func:`derive`: HMAC-SHA256 of the rig key over a label), so a MAC
of one kind (a controller's CAN frame, a DSP's CAN frame, a features message, a camera pose)
never verifies as another kind.

Processes of a rig name the key with ``transport.key_file`` (``--key-file``), or the
environment variable ``HIL_KEY_FILE`` when the config names none; :func:`rig_key` loads it.
Every object of the HAL that signs or verifies (:class:`~hal.can_codec.CanEndpoint`,
:class:`~hal.vision_codec.FeatureDecoder`, ...) takes a ``key`` and defaults to
:func:`rig_key`. Without a configured key a process uses :func:`ephemeral_key`, a random key of
this process only: objects talking to each other inside one process (tests, benchmarks) still
work, and nothing outside the process can speak to them. The rig's entry points (``hil
controller``, ``hil emulator``, ``hil vision``, ``hil replay --republish``) require a configured
key (:func:`require_rig_key`).

CAN frames (see ``docs/concepts/secoc.md`` for the table)
---------------------------------------------------------
Each protected message is a 16-byte CAN FD frame: bytes 0..7 are the E2E-protected payload of
:mod:`hal.e2e` (CRC, counter, signals), bytes 8..11 the low 32 bits of the freshness value,
bytes 12..15 the MAC::

    MAC = HMAC-SHA256(K_node, data_id (u16 LE) || FV (u64 LE) || bytes 0..7)[:4]

``K_node = derive(rig key, "hil/can/" + sending node)``. The freshness value ``FV`` is a 64-bit
counter per (sender, message): the wall clock in microseconds, but always at least the last one
sent plus one (:class:`FreshnessCounter`), so it never repeats, survives a restart of the sender
without persisted state, and a receiver can rebuild the 32 high bits it does not see from its
own clock (the value nearest to its clock with the transmitted low 32 bits, a ±35 minute
window). The receiver (:class:`SecOCVerifier`) accepts a frame only if

1. the MAC over the rebuilt FV verifies (else ``bad_mac``),
2. FV is newer than the last accepted FV of that message (else ``stale_freshness``: a replayed
   or repeated authentic frame) and not older than ``max_age_us`` behind its clock (else
   ``stale_freshness`` too: an old frame replayed to a receiver that just started),
3. FV is at most ``max_skew_us`` ahead of its clock (else ``future_freshness``).

Only the frames of one host's rig carry a wall-clock FV that both ends read from the same
clock; across hosts the clocks must agree within ``max_skew_us`` (PTP/NTP).
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import os
import secrets
import stat
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

from hal.errors import HalConfigError
from hal.whole_file import written_whole

KEY_BYTES = 32
MAC_BYTES = 4
"""CAN: truncated MAC length (32 bits, the usual SecOC profile size)."""
FV_TX_BYTES = 4
"""CAN: transmitted (truncated) freshness bytes."""
TRAILER_BYTES = FV_TX_BYTES + MAC_BYTES
FV_TX_MASK = (1 << (8 * FV_TX_BYTES)) - 1
FV_TX_MODULO = FV_TX_MASK + 1
DEFAULT_MAX_AGE_US = 2_000_000
"""A frame whose freshness is older than this (wall clock) is stale even for a receiver that
saw nothing of that message yet."""
DEFAULT_MAX_SKEW_US = 1_000_000
"""How far a freshness value may run ahead of the receiver's clock."""
VISION_MAC_BYTES = 16
"""zenoh messages: truncated HMAC-SHA256 tag (128 bits; size is no constraint there)."""

_MAC_INPUT = struct.Struct("<HQ8s")
"""What a CAN frame's MAC covers: data id (u16 LE), full freshness value (u64 LE), bytes 0..7."""
KEY_ENV = "HIL_KEY_FILE"
"""Environment variable naming the rig key file when the config names none."""
KEYGEN_HINT = "create one with: hil keygen FILE (then --key-file FILE or transport.key_file)"


class HalKeyError(HalConfigError):
    """A rig key that cannot be used (missing, unreadable, exposed, malformed, not configured)."""


# ------------------------------------------------------------------------------------ keys


def _write_new_key(path: Path) -> None:
    """A fresh key into a new file ``path``, created 0600; nothing left if it fails."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        try:
            os.fchmod(fd, 0o600)  # exactly 0600 whatever the umask
            os.write(fd, (secrets.token_bytes(KEY_BYTES).hex() + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:  # a full disk: named by the file
        path.unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror, str(path)) from None


def write_key_file(path: str | Path, *, overwrite: bool = False) -> Path:
    """Write a fresh random rig key to ``path`` with mode 0600 (created that way, never
    widened first); refuses to replace an existing file unless ``overwrite``, and anything but
    a regular file always. A replaced key is swapped in whole (a full disk leaves the old one).
    :class:`HalKeyError` for what the path is; :class:`OSError` naming it when writing fails."""
    if not str(path):
        raise HalKeyError("rig key: the path is empty")
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise HalKeyError(f"rig key {path}: not a regular file; not replaced")
    if path.exists() and not overwrite:
        raise HalKeyError(f"rig key {path}: already exists (use --force to replace it)")
    try:  # created 0600 (O_EXCL), never widened first; a replacement beside it, swapped in
        if overwrite:
            with written_whole(path) as tmp:
                tmp.unlink(missing_ok=True)  # left by a killed run
                _write_new_key(tmp)
        else:
            _write_new_key(path)
    except FileExistsError:
        raise HalKeyError(f"rig key {path}: already exists (use --force to replace it)") from None
    return path  # any other OSError names the path: a full disk fails as every writer does


def load_key_file(path: str | Path) -> bytes:
    """The rig key in ``path``; :class:`HalKeyError` (one line) when it cannot be trusted."""
    path = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:  # non-blocking: a named pipe is refused below, not waited on for a writer
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise HalKeyError(f"rig key {path}: no such file; {KEYGEN_HINT}") from None
    except OSError as exc:
        if path.is_symlink():
            raise HalKeyError(
                f"rig key {path}: cannot read it: a symbolic link (to {os.readlink(path)}) is not "
                "followed; give the key file itself"
            ) from None
        raise HalKeyError(f"rig key {path}: cannot read it: {exc.strerror}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise HalKeyError(f"rig key {path}: not a regular file")
        if st.st_mode & 0o077:
            raise HalKeyError(
                f"rig key {path}: mode {stat.S_IMODE(st.st_mode):04o} lets group/others read "
                f"or change it; run: chmod 600 {path}"
            )
        raw = os.read(fd, 4096)
    except OSError as exc:
        raise HalKeyError(f"rig key {path}: cannot read it: {exc.strerror}") from exc
    finally:
        os.close(fd)
    lines = [ln.strip() for ln in raw.decode("ascii", "replace").splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    try:
        key = bytes.fromhex(lines[0]) if len(lines) == 1 else b""
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise HalKeyError(
            f"rig key {path}: expected one line of {2 * KEY_BYTES} hex digits; {KEYGEN_HINT}"
        )
    return key


@functools.cache
def ephemeral_key() -> bytes:
    """A random key of this process: links between objects inside one process (tests,
    benchmarks) authenticate with it; nothing outside the process knows it."""
    return secrets.token_bytes(KEY_BYTES)


def key_path(cfg: Any = None) -> str:
    """The configured key file: ``cfg.transport.key_file``, else ``$HIL_KEY_FILE``, else ""."""
    path = getattr(getattr(cfg, "transport", None), "key_file", "") if cfg is not None else ""
    return path or os.environ.get(KEY_ENV, "")


class AnotherKeyNotice:
    """Says once on stderr that ``what`` arrive signed with another rig key (their MAC does not
    verify: ``bad_mac``, every one dropped) and which options give the key: a receiver that
    only counted them would look like a broken link. Thread-safe (zenoh calls back from several
    threads)."""

    def __init__(self, prog: str, what: str, peer: str = "the emulator's") -> None:
        self.text = (
            f"{prog}: warning: {what} are signed with another rig key (bad_mac), every one is "
            f"dropped: give {prog} {peer} key (--key-file, transport.key_file or ${KEY_ENV})"
        )
        self._said = False
        self._lock = threading.Lock()

    def say(self) -> None:
        """Print :attr:`text` the first time only."""
        with self._lock:
            said, self._said = self._said, True
        if not said:
            print(self.text, file=sys.stderr, flush=True)


def bad_mac_clause(n: int) -> str:
    """An end line's clause for ``n`` messages dropped as ``bad_mac`` ("" for none)."""
    return f", {n} dropped as bad_mac (another rig key)" if n else ""


_loaded: dict[tuple[str, int, int, int], bytes] = {}


def rig_key(cfg: Any = None) -> bytes:
    """The configured key (:func:`key_path`, loaded and checked), else :func:`ephemeral_key`.

    A file already loaded is read again only when its inode, mode or mtime changed."""
    path = key_path(cfg)
    if not path:
        return ephemeral_key()
    try:
        st = os.stat(path)
        ident = (str(path), st.st_ino, st.st_mode, st.st_mtime_ns)
    except OSError:
        return load_key_file(path)  # raises the one-line error
    key = _loaded.get(ident)
    if key is None:
        key = _loaded[ident] = load_key_file(path)
    return key


def require_rig_key(cfg: Any, who: str) -> bytes:
    """The configured rig key of a rig process; :class:`HalKeyError` if none is configured.

    ``who`` is the command that needs it (``"hil controller"``): the message tells how to give
    that command a key; it does not start with ``who``, which the error line's prefix names."""
    path = key_path(cfg)
    if not path:
        raise HalKeyError(
            f"no rig key configured; create one with: hil keygen FILE (then {who} --key-file "
            f"FILE, ${KEY_ENV} or transport.key_file)"
        )
    return load_key_file(path)


def configure_key(cfg: Any, key_file: str | None, who: str) -> Any:
    """``cfg`` with ``transport.key_file`` set from ``--key-file`` (when given), after checking
    that the key is configured and usable (:class:`HalKeyError`, one line, otherwise)."""
    if key_file:
        cfg = cfg.with_overrides({"transport.key_file": str(key_file)})
    require_rig_key(cfg, who)
    return cfg


def derive(key: bytes, label: str) -> bytes:
    """The key for one use (``label``) of the rig key."""
    return hmac.digest(key, b"hil-secoc-v1\0" + label.encode(), "sha256")


class Mac:
    """Truncated HMAC-SHA256 with a fixed key (inner/outer state computed once)."""

    __slots__ = ("_base", "size")

    def __init__(self, key: bytes, size: int) -> None:
        if not 4 <= size <= 32:
            raise ValueError("MAC size must be 4..32 bytes")
        self._base = hmac.new(key, digestmod=hashlib.sha256)
        self.size = size

    def tag1(self, message: bytes) -> bytes:
        """The tag of one bytes object (the hot path: one update)."""
        h = self._base.copy()
        h.update(message)
        return h.digest()[: self.size]

    def tag(self, *parts: bytes | bytearray | memoryview) -> bytes:
        h = self._base.copy()
        for p in parts:
            h.update(p)
        return h.digest()[: self.size]

    def verify(self, tag: bytes | bytearray | memoryview, *parts: bytes) -> bool:
        return hmac.compare_digest(self.tag(*parts), bytes(tag))


# ------------------------------------------------------------------------------ freshness


def now_us() -> int:
    """Wall clock in microseconds (the freshness time base)."""
    return time.time_ns() // 1000


class FreshnessCounter:
    """Sender side: one strictly increasing 64-bit freshness value per message."""

    def __init__(self, clock_us: Any = now_us) -> None:
        self._last: dict[int, int] = {}
        self._clock = clock_us

    def next(self, data_id: int) -> int:
        fv = max(self._last.get(data_id, 0) + 1, self._clock())
        self._last[data_id] = fv
        return fv


def rebuild_fv(low: int, ref: int) -> int:
    """The 64-bit value nearest ``ref`` whose low 32 bits are ``low``."""
    fv = (ref & ~FV_TX_MASK) | low
    diff = fv - ref
    if diff > FV_TX_MODULO // 2:
        fv -= FV_TX_MODULO
    elif diff < -(FV_TX_MODULO // 2):
        fv += FV_TX_MODULO
    return fv


class SecOCSigner:
    """Appends freshness and MAC to outgoing 8-byte protected payloads (one sending node)."""

    def __init__(self, key: bytes, node: str, clock_us: Any = now_us) -> None:
        self._mac = Mac(derive(key, f"hil/can/{node}"), MAC_BYTES)
        self.freshness = FreshnessCounter(clock_us)

    def sign(self, data_id: int, payload: bytes | bytearray, fv: int | None = None) -> bytearray:
        """``payload`` (8 bytes) + low FV (4 bytes LE) + MAC (4 bytes): the 16-byte frame."""
        if fv is None:
            fv = self.freshness.next(data_id)
        head = bytes(payload[:8])
        tag = self._mac.tag1(_MAC_INPUT.pack(data_id, fv, head))
        return bytearray(head + (fv & FV_TX_MASK).to_bytes(4, "little") + tag)


class SecOCVerifier:
    """Checks the trailer of incoming frames sent by ``node`` (one receiving endpoint).

    :meth:`check` returns ``None`` for an authentic, fresh frame (and records its freshness),
    else the verdict name: ``"bad_mac"``, ``"stale_freshness"`` or ``"future_freshness"``.
    ``verify=False`` skips every check (offline tools reading a log whose key is gone).
    """

    def __init__(
        self,
        key: bytes,
        node: str,
        *,
        max_age_us: int = DEFAULT_MAX_AGE_US,
        max_skew_us: int = DEFAULT_MAX_SKEW_US,
        clock_us: Any = now_us,
        verify: bool = True,
    ) -> None:
        self._mac = Mac(derive(key, f"hil/can/{node}"), MAC_BYTES)
        self.max_age_us = max_age_us
        self.max_skew_us = max_skew_us
        self.verify = verify
        self._clock = clock_us
        self._last: dict[int, int] = {}

    def reset(self) -> None:
        self._last.clear()

    def check(
        self, frame_id: int, data_id: int, data: bytes | bytearray, rx_us: int | None = None
    ) -> str | None:
        """``rx_us``: when the frame reached this host (the bus's receive timestamp, wall clock
        in microseconds). Freshness is judged at arrival, so a receiver that is busy for a while
        does not reject the authentic frames queued meanwhile; a replayed frame is judged at its
        own arrival and stays stale. A missing or implausible stamp (0, or later than the
        clock) falls back to the clock."""
        if not self.verify:
            return None
        now = self._clock()
        if rx_us is not None and 0 < rx_us < now:
            now = rx_us
        fv = rebuild_fv(int.from_bytes(data[8:12], "little"), now)
        tag = self._mac.tag1(_MAC_INPUT.pack(data_id, fv, bytes(data[:8])))
        if not hmac.compare_digest(tag, bytes(data[12:16])):
            return "bad_mac"
        if fv <= self._last.get(frame_id, -1) or fv < now - self.max_age_us:
            return "stale_freshness"
        if fv > now + self.max_skew_us:
            return "future_freshness"
        self._last[frame_id] = fv
        return None


def bench_mac(n: int = 20_000) -> dict[str, float]:
    """Mean microseconds to sign and to verify one CAN frame (for ``hil bench``)."""
    key = secrets.token_bytes(KEY_BYTES)
    signer, verifier = SecOCSigner(key, "DSP"), SecOCVerifier(key, "DSP", max_age_us=1 << 62)
    payload = bytes(range(8))
    t0 = time.perf_counter_ns()
    frames = [signer.sign(0x2002, payload) for _ in range(n)]
    sign_us = (time.perf_counter_ns() - t0) / n / 1e3
    t0 = time.perf_counter_ns()
    for f in frames:
        verifier.check(0x180, 0x2002, f)
    verify_us = (time.perf_counter_ns() - t0) / n / 1e3
    return {"secoc_sign_us": sign_us, "secoc_verify_us": verify_us}
