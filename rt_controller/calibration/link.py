"""The online parameters over zenoh: a queryable on ``hil/controller/parameters`` in the
controller process and the client of ``hil param``, both authenticated with the rig key.

Wire format: a request or a reply is a JSON object followed by a 32-byte HMAC-SHA256 tag with a
key derived from the rig key (:func:`hal.secoc.derive`; one label per direction). A request
carries ``op`` (``get``, ``dump``, ``set`` or ``action``), for ``set`` the ``changes`` and
``at_tick``, for ``action`` the ``action`` (:data:`~rt_controller.calibration.operator.ACTIONS`),
a ``note`` and ``at_tick``, a
``source``, a random ``nonce`` and its wall-clock time ``t_unix_ns``: the controller refuses a
request whose tag does not verify, whose time is more than :data:`FRESHNESS_S` away from its
own, or whose nonce it has seen (a replayed request). Such attempts change nothing and are
counted (``unauthenticated`` in the ``parameters`` component of ``/diagnostics``; a request
the controller itself failed on, ``failed``). A reply
repeats the request's nonce under the reply tag, so the client knows the rig answered *its*
request.

``get`` and ``dump`` are answered on zenoh's thread from the configuration in force (an
immutable snapshot); ``set`` is queued
(:class:`~rt_controller.calibration.parameters.ParameterService`)
and answered by the control thread at the tick it was judged; so is ``action`` (its answer's
``event`` is the ``/controller/events`` record). An action's note (a mark's text) holds at most
:data:`MAX_NOTE` characters: a longer one is refused at the next tick boundary with that
reason (its record keeps the first :data:`MAX_NOTE`) and counted (``oversized``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from hal.secoc import Mac, derive
from hal.zenoh_session import KEY_CONTROLLER_PARAMETERS
from rt_controller.calibration.operator import Action
from rt_controller.calibration.parameters import (
    Outcome,
    ParameterService,
    Request,
    parse_tick,
    tunable_values,
)
from rt_controller.config_rules import config_toml
from rt_controller.errors import ControllerError

log = logging.getLogger(__name__)

TAG_SIZE = 32
FRESHNESS_S = 30.0
"""How far a request's time may be from the controller's (both on this host's wall clock)."""
REQUEST_LABEL, REPLY_LABEL = "hil-param-request", "hil-param-reply"
OPS = ("get", "dump", "set", "action")
ANSWER_TIMEOUT_S = 10.0
"""How long a client waits for an answer the controller gives at once (get, dump, a set now)."""
MAX_NOTE = 1000
"""The longest note of an action (a mark's text), in characters: a longer one is refused."""
SHOWN_NOTE = 80
"""An action's line shows at most this many characters of its note (the record holds it)."""
SCHEDULED_TIMEOUT_S = 600.0
"""How long a client waits for a set or an action with an ``at_tick``: the controller answers
when that tick comes, which a lockstep run on a loaded host may reach minutes later."""


class ParameterLinkError(ControllerError):
    """No answer, a refused request or an answer that does not verify."""


def seal(body: dict[str, Any], key: bytes, label: str) -> bytes:
    data = json.dumps(body, sort_keys=True).encode()
    return data + Mac(derive(key, label), TAG_SIZE).tag1(data)


def unseal(payload: bytes, key: bytes, label: str) -> dict[str, Any] | None:
    """The body of a sealed message; None when its tag does not verify or it is no object."""
    data, tag = payload[:-TAG_SIZE], payload[-TAG_SIZE:]
    if len(payload) <= TAG_SIZE or not Mac(derive(key, label), TAG_SIZE).verify(tag, data):
        return None
    try:
        body = json.loads(data)
    except ValueError:
        return None
    return body if isinstance(body, dict) else None


class ParameterServer:
    """The controller's side: :meth:`handle` one request (zenoh's thread)."""

    def __init__(
        self,
        service: ParameterService,
        key: bytes,
        *,
        wall_ns: Callable[[], int] = time.time_ns,
        seen_max: int = 4096,
    ) -> None:
        self.service, self.key, self.wall_ns = service, key, wall_ns
        self._seen: OrderedDict[str, int] = OrderedDict()
        self._seen_max = seen_max
        self._floor = 0
        """The newest time of a nonce forgotten: a request of that time or older may be a replay
        of it, so it is refused (a burst of requests must not reopen old ones to a replay)."""
        self._seen_lock = threading.Lock()  # one nonce is fresh once, whatever the thread

    @property
    def failed(self) -> int:
        """Requests whose handling raised here (a fault of the controller, not of the request):
        left unanswered, as the reply has no error form; the first one is logged. Counted in
        the service's counters, so ``/diagnostics`` reports them (``failed``)."""
        return self.service.counters.failed

    def _fresh(self, body: dict[str, Any]) -> bool:
        nonce, t = body.get("nonce"), body.get("t_unix_ns")
        if not isinstance(nonce, str) or not isinstance(t, int):
            return False
        if abs(self.wall_ns() - t) > FRESHNESS_S * 1e9:
            return False
        with self._seen_lock:
            if nonce in self._seen or t <= self._floor:
                return False
            self._seen[nonce] = t
            while len(self._seen) > self._seen_max:
                self._floor = max(self._floor, self._seen.popitem(last=False)[1])
        return True

    def handle(self, payload: bytes, reply: Callable[[bytes | None], None]) -> None:
        """Judge one request; ``reply(bytes)`` is called once (``reply(None)`` for a request
        that is not the rig's: it gets no answer it could learn from)."""
        body = unseal(payload, self.key, REQUEST_LABEL)
        if body is None or not self._fresh(body) or body.get("op") not in OPS:
            self.service.unauthenticated()
            reply(None)
            return
        nonce, op = body["nonce"], body["op"]

        def answer(out: dict[str, Any]) -> None:
            reply(seal({"nonce": nonce, "op": op, **out}, self.key, REPLY_LABEL))

        svc = self.service
        at_tick, invalid = parse_tick(body.get("at_tick"))
        if op == "get":
            answer({"param_set": svc.param_set, "values": tunable_values(svc.cfg)})
        elif op == "dump":
            header = f"hil param dump: parameter set {svc.param_set}"
            answer({"param_set": svc.param_set, "toml": config_toml(svc.cfg, header=header)})
        elif op == "action":
            note = str(body.get("note", ""))
            if len(note) > MAX_NOTE and invalid is None:  # refused, never cut silently
                svc.counters.oversized += 1
                invalid = f"the note is too long: {len(note)} characters (limit {MAX_NOTE})"
            svc.actions.submit(
                Action(
                    str(body.get("action", "")),
                    note=note[:MAX_NOTE],
                    source=str(body.get("source", "hil param"))[:200],
                    at_tick=at_tick,
                    request_id=nonce,
                    reply=lambda event: answer({"event": event}),
                    invalid=invalid,
                )
            )
        else:
            changes = body.get("changes")
            if not isinstance(changes, dict):
                changes = {}
            source = str(body.get("source", "hil param"))[:200]
            svc.submit(
                Request(
                    changes,
                    source=source,
                    at_tick=at_tick,
                    request_id=nonce,
                    reply=lambda o: answer({"outcome": o.record()}),
                    invalid=invalid,
                )
            )

    def attach(self, session: Any) -> Any:
        """Declare the queryable on an open :class:`~hal.zenoh_session.ZenohSession`."""

        def on_query(query: Any) -> None:
            def reply(data: bytes | None) -> None:
                try:
                    if data is not None:
                        query.reply(query.key_expr, data)
                finally:
                    query.drop()

            try:
                self.handle(query.payload.to_bytes() if query.payload else b"", reply)
            except Exception as exc:  # never raise into zenoh
                self._failed(exc)
                with contextlib.suppress(Exception):  # reply() may have dropped it already
                    query.drop()

        return session.session.declare_queryable(KEY_CONTROLLER_PARAMETERS, on_query)

    def _failed(self, exc: Exception) -> None:
        """Count a request this side failed on (it got no answer)."""
        self.service.counters.count_failed(
            exc, f"handling a request on {KEY_CONTROLLER_PARAMETERS} (it got no answer)"
        )


EARLY_END = 0.9
"""A query zenoh ended before this fraction of its timeout had no one to answer it (no
queryable, or the controller's refused it unanswered): said as such, not as a timeout."""


def request(
    session: Any,
    key: bytes,
    op: str,
    *,
    changes: dict[str, Any] | None = None,
    at_tick: int | None = None,
    action: str = "",
    note: str = "",
    source: str = "hil param",
    timeout_s: float | None = None,
) -> dict[str, Any]:
    """One request to the controller (``op`` in :data:`OPS`; ``changes`` for ``set``,
    ``action`` and ``note`` for ``action``); its verified answer.
    :class:`ParameterLinkError` when none comes within ``timeout_s`` (default
    :data:`SCHEDULED_TIMEOUT_S` with an ``at_tick``, else :data:`ANSWER_TIMEOUT_S`)."""
    if timeout_s is None:
        timeout_s = ANSWER_TIMEOUT_S if at_tick is None else SCHEDULED_TIMEOUT_S
    nonce = secrets.token_hex(16)
    body: dict[str, Any] = {"op": op, "nonce": nonce, "t_unix_ns": time.time_ns(), "source": source}
    if op == "set":
        body.update(changes=changes or {}, at_tick=at_tick)
    elif op == "action":
        body.update(action=action, note=note, at_tick=at_tick)
    payload = seal(body, key, REQUEST_LABEL)
    start = time.monotonic()
    for r in session.session.get(KEY_CONTROLLER_PARAMETERS, payload=payload, timeout=timeout_s):
        if r.ok is None:
            continue
        out = unseal(r.ok.payload.to_bytes(), key, REPLY_LABEL)
        if out is not None and out.get("nonce") == nonce:
            return out
    took = time.monotonic() - start
    if took < EARLY_END * timeout_s:  # zenoh ended the query: nobody answers it
        raise ParameterLinkError(
            f"no answer from the controller on {KEY_CONTROLLER_PARAMETERS}: the request ended "
            f"unanswered after {took:.1f} s (no controller on this zenoh endpoint yet, one "
            "that refused it: the same rig key?, or one that failed on it: its stderr says why)"
        )
    if at_tick is not None:  # answered when its tick comes: it may still be waiting there
        raise ParameterLinkError(
            f"no answer from the controller on {KEY_CONTROLLER_PARAMETERS} within "
            f"{timeout_s:g} s: a {op} for tick {at_tick} is answered when that tick comes, so "
            "it may still be waiting there and take effect then (the run's log, "
            "/controller/parameters or /controller/events, will say); else no controller "
            "answers on this zenoh endpoint with the same rig key"
        )
    raise ParameterLinkError(
        f"no answer from the controller on {KEY_CONTROLLER_PARAMETERS} within {timeout_s:g} s "
        "(is it running, on this zenoh endpoint, with the same rig key?)"
    )


def outcome_line(out: dict[str, Any]) -> str:
    """One line for an outcome record."""
    o = out["outcome"]
    items = ", ".join(f"{c['key']} {c['old']} -> {c['new']}" for c in o["changes"])
    if o["accepted"] and o.get("unchanged"):
        kept = ", ".join(f"{c['key']} {c['new']}" for c in o["changes"])
        return (
            f"unchanged at tick {o['tick']} (parameter set {o['param_set']} stays in force): "
            f"already {kept}"
        )
    if o["accepted"]:
        return f"accepted at tick {o['tick']} (parameter set {o['param_set']}): {items}"
    return f"refused at tick {o['tick']}: {o['reason']}"


def event_line(out: dict[str, Any]) -> str:
    """One line for an action's event record."""
    e = out["event"]
    note = e.get("note") or ""
    note = note if len(note) <= SHOWN_NOTE else note[: SHOWN_NOTE - 3] + "..."
    what = e["action"] + (f" ({note})" if note else "")
    if e["accepted"]:
        return f"{what} done at tick {e['tick']}"
    return f"{what} refused at tick {e['tick']}: {e['reason']}"


__all__ = [
    "FRESHNESS_S",
    "MAX_NOTE",
    "Outcome",
    "ParameterLinkError",
    "ParameterServer",
    "event_line",
    "outcome_line",
    "request",
    "seal",
    "unseal",
]
