"""``hil monitor`` as a calibration front-end: Foxglove's Parameters and Services over the same
rig-key-signed zenoh link ``hil param`` uses (:mod:`rt_controller.calibration.link`).

Parameters (capability ``parameters``: get, set, subscribe):

- every key of :data:`~rt_controller.calibration.parameters.TUNABLE` by its own name (matrices
  as nested lists), and the diagonal entries of alpha and K as scalars (``gains.alpha_1``,
  ``gains.alpha_2``, ``gains.K_1``, ``gains.K_2``) for sliders;
- ``hil.at_tick``: the tick at which the next set takes effect (-1: the next tick boundary);
  sent with the change, or just before it (a set consumes it);
- ``hil.last_outcome`` (read-only): the last set's answer, "accepted at tick N ..." or
  "refused at tick N: reason"; ``hil.tuning`` (read-only): whether sets are allowed.

A set is one change set (all or none) and its reply carries the values in force afterwards: the
new ones when accepted, the unchanged ones when refused. Without ``allow_tuning`` every set is
refused here, before the controller, and the operator services that change things are not
advertised. Edits of one matrix compose: each starts from the value last sent to the
controller when that set got no answer in time (it may still take effect), else from the
controller's (a whole matrix brings the entries that differ from the controller's); one that
would land before such an edit sent for a later tick, and so be undone by it, is refused here,
and so is a parameter set without a value (the protocol's "unset": no key of the rig can go).
A callback that fails here is said once on stderr (later ones counted in ``failed``) and
answered with the last values known. Subscribers get fresh values whenever the cycle records'
``param_set`` moves (:meth:`TuningFrontEnd.param_set_seen`), whoever changed it.

Services (JSON): ``/hil/mark`` (a note in ``/controller/events``), and with
``allow_tuning`` ``/hil/arm``, ``/hil/disarm``, ``/hil/switch_law`` (``{"law": ...}``, a set of
``controller.law``) and ``/hil/reset_scenario`` (refused by the controller with its reason).
Each takes an optional ``at_tick`` and answers ``{"accepted", "tick", "reason", ...}``.

Who may change the rig is the :class:`~rt_controller.monitor.access.AccessGate`'s: with TLS a
connection first sets ``hil.token`` (write-only: always read as ""); every set and service call
of a connection it does not admit is refused here with the reason, before the controller (the
reply carries it in ``hil.last_outcome``, which the SDK also publishes to that parameter's
subscribers; the shared outcome and the status line are left alone). A plain remote view offers
no service at all.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from foxglove.websocket import (
    Capability,
    Client,
    MessageSchema,
    Parameter,
    ServerListener,
    Service,
    ServiceRequest,
    ServiceSchema,
    StatusLevel,
)

from foxglove import Schema
from rt_controller.calibration.link import (
    ANSWER_TIMEOUT_S,
    SCHEDULED_TIMEOUT_S,
    ParameterLinkError,
    event_line,
    outcome_line,
    request,
)
from rt_controller.calibration.parameters import TUNABLE
from rt_controller.monitor.access import ADMITTED_LINE, OPEN_LINE, TOKEN_PARAMETER, AccessGate

log = logging.getLogger(__name__)

DIAGONALS = {
    "gains.alpha_1": ("gains.alpha", 0),
    "gains.alpha_2": ("gains.alpha", 1),
    "gains.K_1": ("gains.K", 0),
    "gains.K_2": ("gains.K", 1),
}
"""Scalar parameter -> (matrix key, diagonal index)."""
MATRICES = frozenset(key for key, _ in DIAGONALS.values())
"""The matrix keys: edits of one compose (see the module's docstring)."""
AT_TICK, LAST_OUTCOME, TUNING = "hil.at_tick", "hil.last_outcome", "hil.tuning"
ADVERTISED = (*TUNABLE, *DIAGONALS, AT_TICK, LAST_OUTCOME, TUNING)
"""Every parameter the monitor advertises."""
READ_ONLY_REASON = "tuning from Foxglove is off: start hil monitor (or hil up) with --allow-tuning"
ACTION_SERVICES = {
    "/hil/arm": "arm",
    "/hil/disarm": "disarm",
    "/hil/reset_scenario": "reset_scenario",
}
MARK_SERVICE, LAW_SERVICE = "/hil/mark", "/hil/switch_law"
READ_ONLY_TOKEN_LINES = {
    OPEN_LINE: "no access token is needed or checked here (plain ws:// on loopback); the "
    "parameters are read-only (only the mark is offered): start hil monitor (or hil up) with "
    "--allow-tuning to change the rig",
    ADMITTED_LINE: "access token accepted: this connection may call the mark; the parameters "
    "are read-only: start hil monitor with --allow-tuning to change the rig",
}
"""The gate's answer to ``hil.token`` as a monitor without ``allow_tuning`` gives it."""

_SCHEMAS = Path(__file__).parent
"""``service_request_schema.json`` and ``service_response_schema.json``: the services' JSON."""


def _schema(file: str) -> MessageSchema:
    data = (_SCHEMAS / file).read_bytes()
    title = json.loads(data)["title"]
    return MessageSchema(
        encoding="json", schema=Schema(name=title, encoding="jsonschema", data=data)
    )


def _like(new: Any, old: Any) -> Any:
    """``new`` (as Foxglove sent it) in the type of ``old``: a float that is an int for an int
    key (JSON has one number type)."""
    if isinstance(old, int) and not isinstance(old, bool) and isinstance(new, float):
        return int(new) if new.is_integer() else new
    return new


def _shape(value: Any) -> list[int] | None:
    """The row lengths of a matrix as nested lists (None: not one)."""
    rows = isinstance(value, list) and all(isinstance(r, list) for r in value)
    return [len(r) for r in value] if rows else None


def _merge(start: Any, asked: Any, shown: Any) -> Any:
    """A whole matrix as asked, onto ``start``: the entries that differ from ``shown`` (the
    controller's value, which the panel shows) are the edit; the rest keep ``start``'s. Not a
    matrix of ``shown``'s shape: as asked (the controller judges it)."""
    if _shape(asked) is None or _shape(asked) != _shape(shown):
        return asked
    return [
        [a if a != was else s for a, was, s in zip(ra, rw, rs, strict=True)]
        for ra, rw, rs in zip(asked, shown, start, strict=True)
    ]


def _answer(values: dict[str, Any], names: list[str]) -> list[Parameter]:
    """The parameters ``names`` (all when empty) of ``values``."""
    everything = (*ADVERTISED, TOKEN_PARAMETER)
    return [Parameter(n, value=values[n]) for n in (names or everything) if n in values]


def _tick(value: Any) -> Any:
    """``hil.at_tick`` as set: -1 (the next boundary) for none or a negative number."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return -1 if value is None or (number and value < 0) else value


class TuningFrontEnd(ServerListener):
    """The server listener (the SDK's defaults for the callbacks it does not need) and the
    services of one monitor. ``session`` is an open
    :class:`~hal.zenoh_session.ZenohSession` (anything with ``session.get`` as zenoh's), ``key``
    the rig key, ``gate`` who may change the rig (default: every client, the plain loopback
    server's rule). ``timeout_s`` bounds the wait for an answer the controller gives at once;
    ``scheduled_timeout_s`` that for a set or an action with an ``at_tick``, which the controller
    answers when that tick comes (defaults: :func:`~rt_controller.calibration.link.request`'s)."""

    def __init__(
        self,
        session: Any,
        key: bytes,
        *,
        allow_tuning: bool = False,
        timeout_s: float = ANSWER_TIMEOUT_S,
        scheduled_timeout_s: float = SCHEDULED_TIMEOUT_S,
        gate: AccessGate | None = None,
    ) -> None:
        self.session, self.key = session, key
        self.allow_tuning = allow_tuning
        self.gate = gate or AccessGate("open")
        self.timeout_s = timeout_s
        self.scheduled_timeout_s = scheduled_timeout_s
        self.server: Any = None
        """The Foxglove server (set by the bridge) for status messages and updates."""
        self.last_outcome = "no set yet" if allow_tuning else READ_ONLY_REASON
        self._at_tick = -1
        self._subscribed: set[str] = set()
        self._param_set: int | None = None
        self._lock = threading.Lock()
        self._sent: dict[str, tuple[Any, int | None]] = {}
        """Matrix key -> (value, at_tick) of a set that got no answer in time: it may still
        take effect, so the next edit of that matrix starts from it."""
        self._known: dict[str, Any] = {}
        """The values last had from the controller: the answer when a callback fails."""
        self.failed = 0
        """Callbacks that raised here: each answered with the last values known."""
        self._failed_lock = threading.Lock()

    # --- the link ---------------------------------------------------------------------------
    def ask(self, op: str, **kw: Any) -> dict[str, Any]:
        """One signed request to the controller (:func:`rt_controller.calibration.link.request`)."""
        wait = self.timeout_s if kw.get("at_tick") is None else self.scheduled_timeout_s
        return request(
            self.session, self.key, op, source="hil monitor (Foxglove)", timeout_s=wait, **kw
        )

    def values(self) -> dict[str, Any]:
        """Every advertised parameter's value, from the controller."""
        got = self.ask("get")["values"]
        for name, (key, i) in DIAGONALS.items():
            got[name] = got[key][i][i]
        got.update({AT_TICK: self._at_tick, LAST_OUTCOME: self.last_outcome})
        got[TUNING] = self.allow_tuning
        if self.gate.mode == "token":
            got[TOKEN_PARAMETER] = ""  # write-only: a place to type the token
        self._known = dict(got)
        return got

    def _parameters(self, names: list[str], outcome: str | None = None) -> list[Parameter]:
        """The values of ``names`` (all when empty; the last known when the controller does not
        answer); ``outcome`` stands for the last outcome in this answer only."""
        try:
            values = self.values()
        except ParameterLinkError as exc:  # a silent controller: the last values known
            values = {**self._known, LAST_OUTCOME: str(exc)}
        if outcome is not None:
            values[LAST_OUTCOME] = outcome
        return _answer(values, names)

    # --- foxglove ServerListener --------------------------------------------------------------
    capabilities = (Capability.Parameters, Capability.Services)

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[Parameter]:
        try:
            return self._parameters(param_names)
        except Exception as exc:  # the SDK would log it apart and answer nothing
            return self._failed(exc, param_names)

    def on_set_parameters(
        self, client: Client, parameters: list[Parameter], request_id: str | None = None
    ) -> list[Parameter]:
        names = [p.name for p in parameters]
        names += [DIAGONALS[n][0] for n in names if n in DIAGONALS]  # the whole matrix too
        try:
            with self._lock:
                asked = {p.name: p.get_value() for p in parameters}
                outcome = None  # this connection's own answer, when the gate decides
                if TOKEN_PARAMETER in asked:
                    outcome = self.gate.present(client.id, asked.pop(TOKEN_PARAMETER))
                    if not self.allow_tuning:
                        outcome = READ_ONLY_TOKEN_LINES.get(outcome, outcome)
                if asked:  # a refused token's line stands for the change it came with
                    change = self._change(client.id, asked)
                    outcome = outcome if outcome and change else change
                return self._parameters([*names, LAST_OUTCOME], outcome)
        except Exception as exc:  # the SDK would log it apart and answer nothing
            return self._failed(exc, [*names, LAST_OUTCOME])

    def _failed(self, exc: Exception, names: list[str]) -> list[Parameter]:
        """A callback that raised here: the first is said on stderr (later ones are counted in
        :attr:`failed`); the answer is the last values known, so the panel shows them
        unchanged, with the fault as ``hil.last_outcome``."""
        with self._failed_lock:
            self.failed += 1
            first = self.failed == 1
        why = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        if first:
            log.error(
                "hil monitor: a Foxglove parameter request failed here and was answered with "
                "the last values known (further failures are counted only): %s",
                why,
            )
        with contextlib.suppress(Exception):  # the server may be what fails
            self._status(f"failed in hil monitor: {why}", ok=False)
        return _answer({**self._known, LAST_OUTCOME: f"failed in hil monitor: {why}"}, names)

    def _change(self, client_id: int, asked: dict[str, Any]) -> str | None:
        """Set ``asked`` for one connection: None when the shared outcome tells (the set was
        judged, or tuning is off), else this connection's refusal by the gate."""
        refusal = self.gate.refusal(client_id)
        if refusal is not None:
            return f"refused: {refusal}"
        if not self.allow_tuning:
            self._status(READ_ONLY_REASON, ok=False)
            self.last_outcome = READ_ONLY_REASON
            return None
        try:
            self._set(asked)
        except ParameterLinkError as exc:  # the answer says so; the values are the truth
            self.last_outcome = str(exc)
            self._status(self.last_outcome, ok=False)
        return None

    def _set(self, asked: dict[str, Any]) -> None:
        if AT_TICK in asked:  # what is no tick goes as sent: the controller refuses it
            self._at_tick = _tick(asked.pop(AT_TICK))
        read_only = [name for name in (LAST_OUTCOME, TUNING) if name in asked]
        for name in read_only:
            del asked[name]
        if read_only and not asked:  # else the reply would show an older, unrelated outcome
            self.last_outcome = f"refused here: {' and '.join(read_only)} cannot be set (read-only)"
            self._status(self.last_outcome, ok=False)
        if not asked:
            return
        unset = [name for name, value in asked.items() if value is None]
        if unset:  # the protocol's "unset": no parameter of the rig can be removed
            self._at_tick = -1  # consumed, as by any refused set
            self.last_outcome = (
                f"refused here: {', '.join(unset)} given no value (a parameter of the rig "
                "cannot be unset): set it to a value"
            )
            self._status(self.last_outcome, ok=False)
            return
        current = self.ask("get")["values"]
        self._sent = {k: v for k, v in self._sent.items() if current.get(k) != v[0]}  # landed
        changes = self._changes(asked, current)
        at_tick, self._at_tick = (None if self._at_tick == -1 else self._at_tick), -1
        clash = self._clash(changes, at_tick)
        if clash is not None:
            self.last_outcome = clash
            self._status(clash, ok=False)
            return
        try:
            out = self.ask("set", changes=changes, at_tick=at_tick)
        except ParameterLinkError:  # it may still land: the next edit of a matrix builds on it
            for key in MATRICES.intersection(changes):
                if _shape(changes[key]) == _shape(current[key]):
                    self._sent[key] = (changes[key], at_tick)
            raise
        for key in changes:
            self._sent.pop(key, None)
        self.last_outcome = outcome_line(out)
        self._status(self.last_outcome, ok=out["outcome"]["accepted"])

    def _changes(self, asked: dict[str, Any], current: dict[str, Any]) -> dict[str, Any]:
        """The change set for ``asked``: an edit of a matrix (a diagonal entry, or the entries
        of a whole one that differ from ``current``) starts from the value last sent
        unanswered, else from ``current``, so edits in quick succession compose."""
        changes: dict[str, Any] = {}
        for name, value in asked.items():
            key = DIAGONALS[name][0] if name in DIAGONALS else name
            if key not in MATRICES:
                changes[name] = _like(value, current.get(name))
                continue
            start = changes.get(key, self._sent.get(key, (current[key],))[0])
            if name in DIAGONALS:
                m, i = [list(r) for r in start], DIAGONALS[name][1]
                m[i][i] = value  # as sent: the controller judges it
                changes[key] = m
            else:
                changes[key] = _merge(start, value, current[key])
        return changes

    def _clash(self, changes: dict[str, Any], at_tick: int | None) -> str | None:
        """Why this set is refused here: it would land before the unanswered edit of the same
        matrix sent for a later tick, which would then undo it (None: it composes). Said
        once: the unanswered edit is then forgotten."""
        for key in MATRICES.intersection(changes):
            sent = self._sent.get(key)
            if sent is None or sent[1] is None or (at_tick is not None and at_tick >= sent[1]):
                continue
            del self._sent[key]
            when = "the next tick" if at_tick is None else f"tick {at_tick}"
            return (
                f"refused here: {key} has an edit sent for tick {sent[1]} that got no answer "
                f"yet and may still take effect then, undoing this one (for {when}): set it "
                f"with hil.at_tick >= {sent[1]}, or again to send it as it is"
            )
        return None

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        self._subscribed.update(param_names)

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        self._subscribed.difference_update(param_names)

    def param_set_seen(self, param_set: int) -> None:
        """A cycle record's ``param_set``: when it moved, subscribers get the new values."""
        if param_set == self._param_set:
            return
        self._param_set = param_set
        if self._subscribed and self.server is not None:
            try:
                self.server.publish_parameter_values(self._parameters(sorted(self._subscribed)))
            except Exception as exc:  # the controller may be gone; the view goes on
                log.warning("hil monitor: cannot refresh the parameters: %s", exc)

    def _status(self, line: str, *, ok: bool) -> None:
        if self.server is not None:
            level = StatusLevel.Info if ok else StatusLevel.Warning
            self.server.publish_status(line, level, id="hil.parameters")

    # --- services -------------------------------------------------------------------------
    def services(self) -> list[Service]:
        """The operator services to advertise: only the mark without ``allow_tuning``, none
        when the gate admits nobody (a plain remote view)."""
        if self.gate.mode == "closed":
            return []
        handlers: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
            MARK_SERVICE: lambda body: self._action("mark", body)
        }
        if self.allow_tuning:
            handlers[LAW_SERVICE] = self._switch_law
            for name, action in ACTION_SERVICES.items():
                handlers[name] = lambda body, a=action: self._action(a, body)
        schema = ServiceSchema(
            "hil.OperatorService",
            request=_schema("service_request_schema.json"),
            response=_schema("service_response_schema.json"),
        )

        def wrap(fn: Callable[[dict[str, Any]], dict[str, Any]]) -> Callable[..., bytes]:
            def handler(req: ServiceRequest) -> bytes:
                refusal = self.gate.refusal(req.client_id)
                if refusal is not None:
                    out = {"accepted": False, "reason": refusal, "line": f"refused: {refusal}"}
                    return json.dumps(out).encode()
                try:
                    body = json.loads(req.payload) if req.payload else {}
                except (ValueError, UnicodeDecodeError):
                    body = None
                why = _bad_request(body)
                if why is not None:  # refused here, never guessed at
                    out = {"accepted": False, "reason": why, "line": f"refused here: {why}"}
                    return json.dumps(out).encode()
                return json.dumps(fn(body)).encode()

            return handler

        return [Service(n, schema=schema, handler=wrap(fn)) for n, fn in handlers.items()]

    def _action(self, action: str, body: dict[str, Any]) -> dict[str, Any]:
        out = self.ask(
            "action", action=action, note=str(body.get("note", "")), at_tick=body.get("at_tick")
        )
        line = event_line(out)
        self._status(line, ok=out["event"]["accepted"])
        return {**out["event"], "line": line}

    def _switch_law(self, body: dict[str, Any]) -> dict[str, Any]:
        out = self.ask(
            "set", changes={"controller.law": body.get("law")}, at_tick=body.get("at_tick")
        )
        self.last_outcome = line = outcome_line(out)
        self._status(line, ok=out["outcome"]["accepted"])
        return {**out["outcome"], "line": line}


def _bad_request(body: Any) -> str | None:
    """Why a service request's body is not a ``hil.ServiceRequest`` (None: it is one as far
    as here; the controller judges the values)."""
    if not isinstance(body, dict):
        return "the request is not a JSON object (hil.ServiceRequest: at_tick, note, law)"
    bad = [k for k in ("note", "law") if k in body and not isinstance(body[k], str)]
    return f"{' and '.join(bad)} must be text" if bad else None


__all__ = ["ADVERTISED", "DIAGONALS", "READ_ONLY_REASON", "TuningFrontEnd"]
