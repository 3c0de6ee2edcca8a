"""Zenoh session factory with loopback-only defaults (the vision link of the rig).

Topology: a star on one loopback endpoint (``transport.zenoh_endpoint``, tcp/127.0.0.1:7447).

* Exactly one process is the **hub**: its session is in ``router`` mode and listens on the
  endpoint. Recommended: the plant emulator (``listen=True``) — ``hil up`` starts it first, it
  lives as long as the rig, and it never waits for anyone.
* Every other process (vision, controller, tools) opens a **client** session (``listen=False``)
  that connects to the endpoint and never listens. The hub forwards between its clients, so
  features go vision -> hub -> controller, one extra loopback hop. Any single hub works
  (``hil vision --zenoh-role hub`` runs without an emulator) at the same round trip
  (docs/benchmarks.md, "Design choices, measured"). ``listen=None`` ("auto": the hub if the
  port is free, else a client) is for ad-hoc use only: with fixed roles no start order can
  make two processes fight over the port.
* A client started before its hub keeps retrying for ``wait_s`` (interruptibly, see
  ``stop_event``); once connected, zenoh reconnects it on its own if the hub restarts.

Why not peers: with multicast *and* gossip scouting off (the rule: nothing leaves the host, nothing
is discovered), zenoh 1.x peers only talk to the nodes they are explicitly connected to: two peers
that both connect to a hub (peer or router) never see each other's publications, whereas clients
are routed by their hub.

Defaults are loopback-only: multicast and gossip scouting disabled, IPv4 ``tcp/127.x.x.x:PORT``
endpoints only (user-mode Linux test machines have no IPv6, and zenoh's own peer default listens
on ``tcp/[::]:0``). A ``config_file`` (zenoh's own json5 format, ``--zenoh-config``) replaces these
defaults verbatim; it is the only way to spread the processes over several hosts.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from hal.config import RigConfig
from hal.config.rig import read_text_file
from hal.errors import HalConfigError, HalStopped, HalTransportError
from hal.resources import release, track
from hal.zenoh_endpoint import parse_loopback_endpoint

KEY_FEATURES = "hil/vision/features"
"""Image features, vision -> controller (payload: :mod:`hal.vision_codec` features v1)."""
KEY_CAMERA_POSE = "hil/emulator/camera_pose"
"""Camera pose, emulator -> vision (payload: :mod:`hal.vision_codec` pose v1)."""
KEY_CAMERA_FRAME = "hil/camera/frame"
"""Camera frames, camera -> vision's frame grabber (payload: :mod:`hal.camera_frame` v2, raw
mono8 pixels, whole or a region of interest, with the capture stamp)."""
KEY_CAMERA_ROI = "hil/camera/roi"
"""The region of interest the frame grabber wants in the camera's next frame, vision -> camera
(payload: :mod:`hal.camera_frame` ROI request v1)."""
KEY_VISION_IMAGE = "hil/vision/image"
"""What the camera saw, vision -> log and live views: every ``camera.image_log_fps``-th second a
frame as PNG with its detection (payload: :mod:`hal.vision_image` v1)."""
KEY_CONTROLLER_CYCLE = "hil/controller/cycle"
"""Every controller tick, controller -> anyone (payload: the ``/controller/cycle`` JSON record of
the MCAP, schema ``rt_controller/runtime/cycle_schema.json``), sent off the tick's path."""
KEY_CONTROLLER_DIAGNOSTICS = "hil/controller/diagnostics"
"""The controller's ``/diagnostics`` JSON records (about 1 Hz and a final one)."""
KEY_CONTROLLER_PARAMETERS = "hil/controller/parameters"
"""Online parameters, ``hil param`` -> controller: a queryable (get, dump, set), every request
and reply signed with the rig key (:mod:`rt_controller.calibration.link`)."""
KEY_SIM_CONTROL = "hil/sim/control"
"""Simulator control, harness -> emulator: a scenario reset and the next run's camera noise
seed, signed with the rig key (:mod:`hal.sim_control`); no part of a real rig."""

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_WAIT_S = 10.0
"""How long a client waits for its hub by default."""
MODES = ("router", "peer", "client")

_ATTEMPT_S = 0.5
_POLL_S = 0.005
"""How often :meth:`ZenohSession.has_subscriber` looks again while it waits."""


def free_loopback_port() -> int:
    """A TCP port that is free on 127.0.0.1 right now (racy by nature: bind it soon)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_config_dict(
    endpoint: str, *, listen: bool, mode: str | None = None, wait_s: float = DEFAULT_WAIT_S
) -> dict[str, Any]:
    """The loopback-only zenoh configuration document of a hub (``listen``) or a client.

    ``mode`` defaults to ``router`` for a hub and ``client`` otherwise.
    """
    parse_loopback_endpoint(endpoint)
    mode = mode or ("router" if listen else "client")
    if mode not in MODES:
        raise HalConfigError(f"zenoh mode must be one of {', '.join(MODES)}, not {mode!r}")
    retry = {"period_init_ms": 50, "period_max_ms": 500, "period_increase_factor": 2}
    doc: dict[str, Any] = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "listen": {"endpoints": [endpoint] if listen else []},
        "connect": {"endpoints": [] if listen else [endpoint]},
    }
    if not listen:
        if mode == "client":
            ms = max(1, round(min(wait_s, _ATTEMPT_S) * 1000))
            doc["connect"].update(timeout_ms=ms, exit_on_failure=True, retry=retry)
        else:  # a peer connects in the background and keeps retrying
            doc["connect"].update(timeout_ms=-1, exit_on_failure=False, retry=retry)
    return doc


def _zenoh_config(doc: dict[str, Any]) -> zenoh.Config:
    try:
        return zenoh.Config.from_json5(json.dumps(doc))
    except zenoh.ZError as exc:  # pragma: no cover - our own document
        raise HalConfigError(f"internal zenoh config rejected: {exc}") from exc


TLS_FILES = (
    "root_ca_certificate",
    "listen_private_key",
    "listen_certificate",
    "connect_private_key",
    "connect_certificate",
)
"""The files a zenoh config's ``transport.link.tls`` names (zenoh 1.x's keys)."""


def load_config_file(path: str) -> zenoh.Config:
    """zenoh's own config file (JSON5 or YAML by its suffix, as zenoh reads it), checked first
    as the user's text file: a folder, a FIFO or bytes that are not UTF-8 are named in one
    line (:class:`HalConfigError`), zenoh's complaints without their Rust source locations."""
    if not Path(path).exists():
        raise HalConfigError(f"transport.zenoh_config: no such file {path!r}")
    try:
        read_text_file(path, "transport.zenoh_config file")
    except HalConfigError as exc:  # "cannot read ... file PATH: why" or "PATH: not UTF-8 ..."
        said = str(exc)
        raise HalConfigError(
            said if said.startswith("cannot") else f"transport.zenoh_config: {said}"
        ) from None
    try:
        zcfg = zenoh.Config.from_file(path)
    except zenoh.ZError as exc:
        raise HalConfigError(f"transport.zenoh_config: {path}: {_short(exc)}") from exc
    for key in TLS_FILES:  # else zenoh says only "Unable to connect", as for a hub that is down
        named = json.loads(zcfg.get_json(f"transport/link/tls/{key}") or "null")
        if isinstance(named, str) and not Path(named).is_file():
            raise HalConfigError(
                f"transport.zenoh_config: {path}: transport.link.tls.{key} {named!r} is no "
                f"file (a relative path is relative to the working directory, {os.getcwd()})"
            )
    return zcfg


def _short(exc: BaseException) -> str:
    """A zenoh error on one line, without its Rust source locations; a parser's drawing of
    where the file is wrong (``--> 1:66``, the line, a caret, ``= expected ...``) as
    "line 1, column 66: expected ..."."""
    text = re.sub(r"\s*at /\S+?:\d+\.?", "", str(exc)).strip()
    at, why = re.search(r"-->\s*(\d+):(\d+)", text), re.search(r"^\s*=\s*(.+)$", text, re.M)
    if at and why:
        return f"line {at[1]}, column {at[2]}: {why[1].strip()}"
    return " ".join(text.split())


class ZenohSession:
    """An open zenoh session; a context manager whose :meth:`close` is safe to call twice.

    Use :meth:`publisher` and :meth:`subscribe` rather than the raw :attr:`session`, so callbacks
    never raise into zenoh and the session is tracked by :mod:`hal.resources`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        *,
        endpoint: str,
        listening: bool,
        mode: str,
        source: str,
        config: dict[str, Any] | None = None,
    ) -> None:
        self.session = session
        self.endpoint = endpoint
        self.listening = listening
        self.mode = mode
        self.source = source
        """``"loopback"`` or the path of the user's zenoh config file."""
        self.config = config
        """The loopback configuration document the session was opened with (None for a file)."""
        self.callback_errors = 0
        """Exceptions swallowed in subscriber callbacks (a bug if not zero)."""
        self._closed = False
        self._lock = threading.Lock()
        track(self, f"zenoh session {mode} {'listen' if listening else 'connect'} {endpoint}")

    @property
    def closed(self) -> bool:
        return self._closed

    def zid(self) -> str:
        return str(self.session.zid())

    def publisher(
        self, key: str, *, block: bool = True, priority: zenoh.Priority | None = None
    ) -> zenoh.Publisher:
        """Declare an express (unbatched), real-time-priority, reliable publisher.

        ``block=True`` (default) makes ``put`` wait for queue space when the link is congested;
        ``False`` drops the *new* sample instead. ``priority`` overrides ``REAL_TIME`` (monitoring
        streams use a lower one, so they never delay the rig's own messages). The rig's messages
        are tiny and at most 1 kHz, so blocking only happens while the process is starved of
        CPU, and then it delivers late rather than losing a lockstep answer (which would stall
        the run).
        """
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        try:
            return self.session.declare_publisher(
                key,
                express=True,
                priority=zenoh.Priority.REAL_TIME if priority is None else priority,
                congestion_control=cc,
            )
        except zenoh.ZError as exc:
            raise HalTransportError(
                f"zenoh: cannot declare publisher {key}: {_short(exc)}"
            ) from exc

    def subscribe(self, key: str, on_payload: Callable[[bytes], Any]) -> zenoh.Subscriber:
        """Call ``on_payload(bytes)`` for each sample on ``key`` (on zenoh's callback thread).

        Exceptions of the callback are counted in :attr:`callback_errors`, never propagated.
        """

        def _callback(sample: zenoh.Sample) -> None:
            try:
                on_payload(sample.payload.to_bytes())
            except Exception:
                with self._lock:
                    self.callback_errors += 1

        try:
            return self.session.declare_subscriber(key, _callback)
        except zenoh.ZError as exc:
            raise HalTransportError(
                f"zenoh: cannot declare subscriber {key}: {_short(exc)}"
            ) from exc

    def subscribe_ring(self, key: str, capacity: int = 16) -> PayloadRing:
        """Subscribe to ``key`` into a ring of the newest ``capacity`` samples (zenoh's
        ``RingChannel``): no Python callback runs on zenoh's threads; the owner takes the
        samples with :meth:`PayloadRing.drain` when it wants them (the control tick)."""
        try:
            sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))
        except zenoh.ZError as exc:
            raise HalTransportError(
                f"zenoh: cannot declare subscriber {key}: {_short(exc)}"
            ) from exc
        return PayloadRing(sub)

    def has_subscriber(
        self,
        publisher: zenoh.Publisher,
        timeout_s: float = 0.0,
        stop: threading.Event | None = None,
    ) -> bool:
        """Whether a subscriber matches ``publisher`` (one of this session's), waiting up to
        ``timeout_s`` for one (polled every 5 ms; False at once when ``stop`` is set). A closed
        session or an undeclared publisher has none: zenoh's ``ZError`` never escapes."""
        deadline = time.monotonic() + timeout_s
        while not self._matching(publisher):
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return False
            if stop is None:
                time.sleep(_POLL_S)
            else:
                stop.wait(_POLL_S)
        return True

    def _matching(self, publisher: zenoh.Publisher) -> bool:
        if self._closed:
            return False
        try:
            return bool(publisher.matching_status.matching)
        except zenoh.ZError:
            return False

    def close(self) -> None:
        """Close the session (undeclares its publishers and subscribers). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self.session.close()
        except zenoh.ZError:  # already closed by zenoh itself
            pass
        finally:
            release(self)

    def __enter__(self) -> ZenohSession:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        role = "listen" if self.listening else "connect"
        return f"ZenohSession({self.mode}, {role} {self.endpoint}, {state})"


def _open_hub(endpoint: str, mode: str | None) -> tuple[zenoh.Session, dict[str, Any]]:
    doc = loopback_config_dict(endpoint, listen=True, mode=mode)
    try:
        return zenoh.open(_zenoh_config(doc)), doc
    except zenoh.ZError as exc:
        text = _short(exc)
        if "in use" in text:
            raise _PortInUse(
                f"zenoh: cannot listen on {endpoint}: port in use (is another emulator or zenoh "
                "router running? choose another port with --zenoh-endpoint)"
            ) from exc
        raise HalTransportError(f"zenoh: cannot listen on {endpoint}: {text}") from exc


CONNECT_ATTEMPT_S = 0.25
"""Longest single connection attempt while waiting for the hub."""


class PayloadRing:
    """The newest samples of one subscription, taken without blocking (see
    :meth:`ZenohSession.subscribe_ring`); older samples beyond the ring's capacity are dropped by
    zenoh (the reader wants the newest measurement, not a backlog)."""

    def __init__(self, subscriber: zenoh.Subscriber) -> None:
        self.subscriber = subscriber

    def drain(self) -> list[bytes]:
        """Every sample waiting in the ring, oldest first (empty when none)."""
        out: list[bytes] = []
        while (sample := self.subscriber.try_recv()) is not None:
            out.append(sample.payload.to_bytes())
        return out

    def close(self) -> None:
        """Undeclare the subscriber (the session stays open). Idempotent."""
        with contextlib.suppress(zenoh.ZError):
            self.subscriber.undeclare()


class _PortInUse(HalTransportError):
    pass


def _open_client(
    endpoint: str, mode: str | None, wait_s: float, stop_event: threading.Event | None
) -> tuple[zenoh.Session, dict[str, Any]]:
    deadline = time.monotonic() + wait_s
    while True:
        # Short attempts, so that a stop request is seen within a fraction of a second.
        attempt_s = min(max(0.0, deadline - time.monotonic()), CONNECT_ATTEMPT_S)
        doc = loopback_config_dict(endpoint, listen=False, mode=mode, wait_s=attempt_s)
        try:
            return zenoh.open(_zenoh_config(doc)), doc
        except zenoh.ZError as exc:
            last = _short(exc)
            if "Timeout" not in last and "Unable to connect" not in last:
                raise HalTransportError(f"zenoh: cannot connect to {endpoint}: {last}") from exc
            if stop_event is not None and stop_event.is_set():
                raise HalStopped(f"zenoh: stopped while waiting for the hub at {endpoint}") from exc
            if time.monotonic() >= deadline:
                raise HalTransportError(
                    f"zenoh: no hub at {endpoint} after {wait_s:g} s (start the emulator, "
                    "`hil emulator`, or check --zenoh-endpoint)"
                ) from exc
            time.sleep(0.05)


def open_session(
    cfg: RigConfig | None = None,
    *,
    mode: str | None = None,
    listen: bool | None = False,
    endpoint: str | None = None,
    config_file: str | None = None,
    wait_s: float = DEFAULT_WAIT_S,
    stop_event: threading.Event | None = None,
) -> ZenohSession:
    """Open a zenoh session on the rig's loopback endpoint (see the module docstring).

    ``listen=True`` makes this process the hub (router listening on ``endpoint``); the default
    ``False`` a client connecting to it (waiting up to ``wait_s`` for the hub, giving up early
    when ``stop_event`` is set); ``None`` the hub if the port is free and a client otherwise
    (ad-hoc use only: two processes started together could both want the hub).
    ``mode`` overrides the zenoh mode (``router``/``peer``/``client``); note that two peers that
    only connect to a hub cannot reach each other with gossip off. ``endpoint`` and
    ``config_file`` default to ``cfg.transport``; a config file is used verbatim (mode, listen
    and endpoint arguments are then ignored). Raises :class:`HalConfigError` for a bad endpoint
    or config file and :class:`HalTransportError` when zenoh cannot open the session.
    """
    transport = (cfg or RigConfig()).transport
    config_file = config_file if config_file is not None else transport.zenoh_config
    endpoint = endpoint or transport.zenoh_endpoint or DEFAULT_ENDPOINT
    if config_file:
        zcfg = load_config_file(config_file)
        try:
            session = zenoh.open(zcfg)
        except zenoh.ZError as exc:
            raise HalTransportError(
                f"zenoh: cannot open a session with {config_file}: {_short(exc)}"
            ) from exc
        file_mode = json.loads(zcfg.get_json("mode") or "null") or "peer"
        return ZenohSession(
            session,
            endpoint=config_file,
            listening=bool(json.loads(zcfg.get_json("listen/endpoints") or "[]")),
            mode=str(file_mode),
            source=config_file,
        )
    parse_loopback_endpoint(endpoint)
    if wait_s < 0:
        raise HalConfigError(f"zenoh wait must be non-negative, got {wait_s}")
    if listen is None:
        try:
            session, doc = _open_hub(endpoint, mode)
        except _PortInUse:
            session, doc = _open_client(endpoint, mode, wait_s, stop_event)
    elif listen:
        session, doc = _open_hub(endpoint, mode)
    else:
        session, doc = _open_client(endpoint, mode, wait_s, stop_event)
    return ZenohSession(
        session,
        endpoint=endpoint,
        listening=bool(doc["listen"]["endpoints"]),
        mode=doc["mode"],
        source="loopback",
        config=doc,
    )
