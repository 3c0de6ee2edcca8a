"""Online parameters: which configuration keys may change while the rig runs, how a change set
is judged, and the hand-over from any thread to the control thread at a tick boundary.

The interface every calibration front-end uses (``hil param`` over zenoh today; a Foxglove
server or an XCP slave tomorrow) is small:

- :data:`TUNABLE` names the online-tunable keys; :func:`refusal` says why any other key is not;
- :func:`judge` applies a change set to a :class:`~hal.config.RigConfig` by the TOML's own rules
  (``cfg.with_overrides``: types, ranges, alpha and K positive definite) or refuses it whole;
- :class:`ParameterService` takes :class:`Request` objects from any thread (:meth:`submit`) and,
  in the control thread, hands the loop at each tick boundary the configuration to run with
  (:meth:`due`). Each request gives one :class:`Outcome` (the ``/controller/parameters``
  record): accepted with the tick at which it took effect, or refused with the reason. A set
  that asks for the values already in force is accepted as ``unchanged``: logged like any
  other, but no new parameter set, no reconfiguration and counted apart (``unchanged``).

Pure apart from the thread-safe queue: no I/O, no clocks.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from hal.config import RigConfig
from hal.errors import HalConfigError
from rt_controller.calibration.handover import DueQueue, beyond_end, run_ended
from rt_controller.calibration.operator import ActionQueue
from rt_controller.errors import ControllerConfigError

log = logging.getLogger(__name__)
_FAILED_LOCK = threading.Lock()
"""Guards ``failed``: zenoh's threads and the control thread both count."""

TUNABLE: dict[str, str] = {
    "gains.kp": "kp of eq. (34)",
    "gains.alpha": "alpha of eq. (34), positive definite",
    "gains.K": "K of eq. (34), positive definite",
    "controller.law": "the law (pbc, ioc, rhc); a switch re-initialises it",
    "controller.feature_timeout_s": "features older than this mean hold",
    "controller.state_timeout_s": "a joint state older than this means no state (realtime)",
    "controller.predict_state": "compensate the joint state's age",
    "controller.predict_features": "compensate the features' age",
    "rhc.horizon": "the horizon T_f (re-initialises C/GMRES)",
    "rhc.steps": "the steps N (re-initialises C/GMRES)",
    "rhc.kmax": "GMRES iterations per update",
    "rhc.zeta": "continuation stabilisation gain",
    "rhc.horizon_growth": "a in T(t) = T_f (1 - exp(-a t))",
    "rhc.u_max": "the input bounds of the horizon problem",
}
"""The keys a running controller accepts, with what each is. They change only what the per-tick
rule computes (``Controller.reconfigure``), so ``hil replay`` repeats a tuned run exactly."""

LAW_KEYS = frozenset(k for k in TUNABLE if k.startswith(("gains.", "rhc.")) or k.endswith(".law"))
"""Keys whose change rebuilds the law (the others leave its state alone)."""

SECTION_REASONS: dict[str, str] = {
    "robot": "the robot's geometry and inertia are the rig's, not a gain",
    "camera": "the camera belongs to the vision process",
    "scenario": "the scenario is fixed for a run (the emulator and vision process run it)",
    "rates": "rates fix the cadence, the DSP's watchdog and the physics step: restart to change",
    "transport": "transports and keys are opened at start: restart to change",
    "dsp": "the DSP's settings belong to the DSP",
    "plant": "the emulated plant belongs to the emulator",
    "controller": "fixed for the run (the loop's wiring and real-time settings): restart",
    "rhc": "a solver internal, fixed for the run: restart",
    "vision": "the camera model and detector belong to the vision process",
    "cia402": "the CiA 402 drives are configured at start: restart to change",
    "hardware": "the hardware profile is chosen at start: restart to change",
}
"""Why the keys of a section outside :data:`TUNABLE` are refused."""


def refusal(key: str) -> str | None:
    """Why ``key`` may not change online (None when it may)."""
    if key in TUNABLE:
        return None
    section, _, name = key.partition(".")
    known = RigConfig().to_dict()
    if section not in known or name not in known[section]:
        return f"unknown config key {key!r}"
    why = SECTION_REASONS.get(section, "fixed for the run: restart with --config to change it")
    return f"{key} is not online-tunable: {why}"


class ParameterRefused(ControllerConfigError):
    """A change set that may not be applied; ``str()`` is the reason (a ``ValueError`` too)."""


MAX_DEPTH = 8
"""Lists in lists a value may hold (a matrix has 2): a deeper one is refused unread, as no
recursion over it (the record's JSON too) may run out of stack in the control thread."""


def _too_deep(value: Any) -> bool:
    """Whether ``value`` nests lists more than :data:`MAX_DEPTH` deep (no recursion)."""
    stack = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, list | tuple):
            if depth >= MAX_DEPTH:
                return True
            stack.extend((v, depth + 1) for v in item)
    return False


def _plain(value: Any) -> Any:
    if _too_deep(value):  # recorded as a line, never walked
        return f"(lists nested more than {MAX_DEPTH} deep)"
    return _plain_list(value)


def _plain_list(value: Any) -> Any:
    return [_plain_list(v) for v in value] if isinstance(value, list | tuple) else value


def value_of(cfg: RigConfig, key: str) -> Any:
    """The current value of ``key`` (lists for tuples, as in the TOML)."""
    section, _, name = key.partition(".")
    return _plain(getattr(getattr(cfg, section), name))


def judge(cfg: RigConfig, changes: Mapping[str, Any]) -> RigConfig:
    """``cfg`` with every change of ``changes`` applied and validated like a TOML file; raises
    :class:`ParameterRefused` (nothing applied) when any key may not change online or the
    result breaks a rule."""
    if not changes:
        raise ParameterRefused("no keys given")
    for key, value in changes.items():
        why = refusal(key) or _nested(key, value) or _out_of_range(key, value)
        if why is not None:
            raise ParameterRefused(why)
    try:
        return cfg.with_overrides(dict(changes))
    except (HalConfigError, ValueError, TypeError, ArithmeticError) as exc:
        raise ParameterRefused(_one_line(str(exc))) from None


MAX_INT = 2**63
"""No tunable value comes near it; a larger JSON integer has no float (the TOML cannot hold one)."""
MAX_REASON = 300
"""A reason echoes the value asked for: cut to this many characters, one line."""


def _out_of_range(key: str, value: Any) -> str | None:
    """Why ``value`` (a JSON value, nested lists) holds an integer no tunable key can take."""
    if isinstance(value, list | tuple):
        return next(filter(None, (_out_of_range(key, v) for v in value)), None)
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= MAX_INT:
        return f"{key}: out of range, an integer of {value.bit_length()} bits"
    return None


def _nested(key: str, value: Any) -> str | None:
    """Why ``value`` is refused unread: lists nested beyond :data:`MAX_DEPTH`."""
    if _too_deep(value):
        return f"{key}: lists nested more than {MAX_DEPTH} deep (a matrix has 2)"
    return None


def _one_line(reason: str) -> str:
    """``reason`` on one line of at most :data:`MAX_REASON` characters."""
    reason = " ".join(reason.split())
    return reason if len(reason) <= MAX_REASON else reason[: MAX_REASON - 3] + "..."


def tunable_values(cfg: RigConfig) -> dict[str, Any]:
    """Every tunable key with its value in ``cfg``."""
    return {key: value_of(cfg, key) for key in TUNABLE}


def diff(a: RigConfig, b: RigConfig) -> dict[str, tuple[Any, Any]]:
    """The keys (any key, dotted) whose values differ from ``a`` to ``b``: ``(old, new)``."""
    da, db = a.to_dict(), b.to_dict()
    return {
        f"{s}.{k}": (v, db[s][k])
        for s, body in da.items()
        for k, v in body.items()
        if db[s][k] != v
    }


@dataclass
class Request:
    """One change set from a front-end. ``at_tick``: take effect at the first tick >= it
    (None: the next tick boundary). ``reply`` is called once with the :class:`Outcome`, in the
    control thread."""

    changes: dict[str, Any]
    source: str = "unknown"
    at_tick: int | None = None
    request_id: str = ""
    reply: Callable[[Outcome], Any] | None = None
    invalid: str | None = None
    """Why it is refused whatever the tick (a malformed ``at_tick``): at the next boundary."""


@dataclass
class Outcome:
    """What became of one request: the ``/controller/parameters`` record (:meth:`record`)."""

    tick: int
    accepted: bool
    changes: list[dict[str, Any]]
    """``{"key", "old", "new"}`` for each key named."""
    source: str
    param_set: int
    """The parameter set in force from ``tick`` on (unchanged when refused)."""
    reason: str | None = None
    request_id: str = ""
    at_tick: int | None = None
    t_ns: int = 0
    unchanged: bool = False
    """Accepted, but every value asked for was already in force: no new parameter set."""

    def record(self) -> dict[str, Any]:
        """The ``/controller/parameters`` message (:data:`PARAMETERS_SCHEMA`)."""
        return dataclasses.asdict(self)


PARAMETERS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "hil.ParameterChange",
    "description": "One online parameter change set, accepted or refused (one per request).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "loop clock at the tick boundary, ns"},
        "tick": {
            "type": "integer",
            "description": "the tick at which it took effect (or was refused)",
        },
        "accepted": {"type": "boolean"},
        "param_set": {
            "type": "integer",
            "description": "the cycle records' param_set from tick on",
        },
        "source": {"type": "string", "description": "who asked (front-end and peer)"},
        "request_id": {"type": "string"},
        "at_tick": {"type": "integer", "description": "the tick asked for (null: the next)"},
        "reason": {"type": "string", "description": "why it was refused (null if accepted)"},
        "unchanged": {
            "type": "boolean",
            "description": "accepted, but the values asked for were already in force",
        },
        "changes": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"key": {"type": "string"}, "old": {}, "new": {}},
                "required": ["key", "old", "new"],
            },
        },
    },
    "required": ["tick", "accepted", "param_set", "source", "changes"],
}


@dataclass
class ParameterCounters:
    accepted: int = 0
    refused: int = 0
    unauthenticated: int = 0
    failed: int = 0
    """Requests the controller failed on: left unanswered (``ParameterServer``), or refused
    or unanswered in the control thread (:meth:`ParameterService.due`)."""
    unchanged: int = 0
    """Change sets accepted with nothing to change (the values already in force)."""
    oversized: int = 0
    """Requests refused for a text beyond its limit (a mark's note: ``ParameterServer``)."""

    def count_failed(self, exc: BaseException, doing: str) -> None:
        """Count a fault of the controller's own (any thread); the first is logged, later
        ones are counted only."""
        with _FAILED_LOCK:
            self.failed += 1
            first = self.failed == 1
        if first:
            log.error(
                "parameters: a fault of the controller's own while %s (further ones are "
                "counted only): %s: %s",
                doing,
                type(exc).__name__,
                exc,
            )

    def as_dict(self) -> dict[str, int]:
        """The counts; ``failed``, ``unchanged`` and ``oversized`` only when not 0."""
        out = dataclasses.asdict(self)
        for rare in ("failed", "unchanged", "oversized"):
            if not out[rare]:
                del out[rare]
        return out


@dataclass
class ParameterService:
    """The hand-over: :meth:`submit` from any thread, :meth:`due` in the control thread at each
    tick boundary. ``cfg`` is the configuration in force, ``param_set`` its number (0 at start,
    +1 per accepted change set)."""

    cfg: RigConfig
    param_set: int = 0
    counters: ParameterCounters = field(default_factory=ParameterCounters)
    actions: ActionQueue = field(default_factory=ActionQueue)
    """Operator actions (:mod:`rt_controller.calibration.operator`), taken at the same tick
    boundaries."""
    _queue: DueQueue[Request] = field(default_factory=DueQueue, repr=False)

    def submit(self, request: Request) -> None:
        """Queue ``request`` (thread-safe; never blocks)."""
        self._queue.submit(request)

    def unauthenticated(self) -> None:
        """Count a request that failed authentication (it never reaches the queue)."""
        self.counters.unauthenticated += 1

    def plan(self, end_tick: int | None) -> None:
        """The run's planned ticks (None: no planned end): a change set or an action for a tick
        at or past it is refused at the next tick boundary instead of waiting for ever."""
        self._queue.end_tick = self.actions.end_tick = end_tick

    def end(self, tick: int | None, t_ns: int = 0) -> list[Outcome]:
        """At the run's end (last tick ``tick``; None: none ran, logged as tick 0): the
        change sets still waiting, refused as not applied (each answered and counted; the
        records are for the log). Control thread only."""
        outcomes = []
        for r in self._queue.drain():
            out = self._refuse(r, tick or 0, t_ns, run_ended(r.at_tick, tick))
            self._answer(r, out)
            outcomes.append(out)
        return outcomes

    def due(self, tick: int, t_ns: int = 0) -> tuple[RigConfig | None, list[Outcome]]:
        """Judge the requests due at ``tick`` in arrival order: the new configuration (None when
        nothing was accepted) and one outcome per request judged. Control thread only."""
        now = self._queue.due(tick)
        if not now:
            return None, []
        changed, outcomes = None, []
        for r in now:
            out = self._decide(r, tick, t_ns)
            if out.accepted and not out.unchanged:
                changed = self.cfg
            outcomes.append(out)
            self._answer(r, out)
        return changed, outcomes

    def _decide(self, r: Request, tick: int, t_ns: int) -> Outcome:
        if r.invalid is not None:
            return self._refuse(r, tick, t_ns, r.invalid)
        if r.at_tick is not None and r.at_tick > tick:  # due only as never reached
            return self._refuse(r, tick, t_ns, beyond_end(r.at_tick, self._queue.end_tick))
        try:
            return self._judge(r, tick, t_ns)
        except Exception as exc:  # a fault of the controller's, not the request's: run on
            self.counters.count_failed(exc, "judging a change set")
            reason = _one_line(f"the controller failed on it: {type(exc).__name__}: {exc}")
            items = [{"key": str(k), "old": None, "new": None} for k in r.changes]
            return Outcome(
                tick, False, items, r.source, self.param_set, reason, r.request_id, r.at_tick,
                t_ns,
            )  # fmt: skip

    def _answer(self, r: Request, out: Outcome) -> None:
        """Call ``r``'s reply; one that fails (a dropped query) is counted, the outcome stands."""
        if r.reply is None:
            return
        try:
            r.reply(out)
        except Exception as exc:
            self.counters.count_failed(exc, "answering a change set")

    def _items(self, r: Request) -> list[dict[str, Any]]:
        """``{"key", "old", "new"}`` for each key of ``r`` (old None for a key that is no
        configuration key, ``robot.__class__`` say)."""
        items, known = [], self.cfg.to_dict()
        for key, new in r.changes.items():
            section, _, name = key.partition(".")
            config_key = isinstance(known.get(section), dict) and name in known[section]
            before = value_of(self.cfg, key) if config_key else None  # never an attribute
            items.append({"key": key, "old": before, "new": _plain(new)})
        return items

    def _refuse(self, r: Request, tick: int, t_ns: int, reason: str) -> Outcome:
        """``r`` refused unjudged with ``reason``: counted (the caller answers)."""
        self.counters.refused += 1
        out = Outcome(
            tick, False, self._items(r), r.source, self.param_set, reason, r.request_id,
            r.at_tick, t_ns,
        )  # fmt: skip
        return out

    def _judge(self, r: Request, tick: int, t_ns: int) -> Outcome:
        items = self._items(r)
        reason, unchanged = None, False
        try:
            cfg = judge(self.cfg, r.changes)
        except ParameterRefused as exc:
            reason = str(exc)
            self.counters.refused += 1
        else:
            for item in items:  # as validated (an int reads back as a float, a diagonal as 2x2)
                item["new"] = value_of(cfg, item["key"])
            unchanged = not diff(self.cfg, cfg)
            if unchanged:  # no change: the same set stays in force, nothing to rebuild
                self.counters.unchanged += 1
            else:
                self.cfg = cfg
                self.param_set += 1
                self.counters.accepted += 1
        ok = reason is None
        return Outcome(
            tick,
            ok,
            items,
            r.source,
            self.param_set,
            reason,
            r.request_id,
            r.at_tick,
            t_ns,
            unchanged=unchanged,
        )


def accepted_changes(records: list[dict[str, Any]]) -> list[tuple[int, dict[str, Any]]]:
    """``(tick, changes)`` of the applied records of a log's ``/controller/parameters``, in
    order (what ``hil replay`` applies): accepted and not ``unchanged``."""
    out = []
    for rec in records:
        if rec.get("accepted") and not rec.get("unchanged"):
            out.append((int(rec["tick"]), {c["key"]: c["new"] for c in rec.get("changes", [])}))
    return out


def parse_tick(value: Any) -> tuple[int | None, str | None]:
    """A request's ``at_tick`` (JSON): ``(tick, None)``, None for absent; ``(None, reason)``
    when it is no tick (a string, a fraction, NaN, a boolean, out of range), to be refused
    rather than taken at another tick."""
    if value is None:
        return None, None
    given = value  # named as sent: 1e300 is not written out as its 301 digits
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) < MAX_INT:
        return value, None
    return None, _one_line(f"at_tick: expected a tick (an integer), got {given!r}")


__all__ = [
    "LAW_KEYS",
    "PARAMETERS_SCHEMA",
    "SECTION_REASONS",
    "TUNABLE",
    "Outcome",
    "ParameterCounters",
    "ParameterRefused",
    "ParameterService",
    "Request",
    "accepted_changes",
    "diff",
    "judge",
    "refusal",
    "tunable_values",
    "value_of",
]
