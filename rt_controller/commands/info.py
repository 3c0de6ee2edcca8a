"""``hil info``: what a controller log holds, like ``mcap info`` or ``ros2 bag info``."""

from __future__ import annotations

import argparse
from typing import Any

from hal import strict_json

DESCRIPTION = """\
One controller log (MCAP) at a glance: the run (clock, law, rate, CAN, zenoh, recorder, start),
the digest of the recorded configuration, duration, ticks, the laws that ran, deadline misses,
the problems that make the run not clean and the warnings (the rules of `hil controller`'s
summary, judged on the log's final /diagnostics record, which carries the run's DSP faults,
ticks without an enabled DSP and camera outages, and the recorder counters; a log without them
has its outages rebuilt from the cycle records), and the topics with their message counts.
A log whose writer was killed is reported as truncated, with what could be read; a complete log
without the final /diagnostics record (controller killed, or a cut log made whole by `hil
recover`) has that as a problem, and a copy made by `hil recover` says where it came from. How
the run ended is judged as its summary judged it, from the final /diagnostics record: a run that
ended for another reason than its duration or a stop ("the run ended after 60 of 250 ticks: no
Sync from the DSP for 2 s") is a problem, one stopped before its duration a warning ("... 60 of
250 ticks: stopped by SIGINT": its J is of fewer ticks). Records that could not be read (not
JSON objects, or cycle records without a tick: counted per topic) are problems too.

--json prints one object: log, library, truncated (not all of it was read), damaged (the
writer finished it, but damaged chunks were skipped), run, config_digest, duration_s, time_axis,
ticks, first_tick, last_tick, laws, deadline_misses, missed_periods, planned_ticks, end_reason,
ticks_run, stop_signal (how the run ended and the signal that stopped it, e.g. SIGINT, from its
final /diagnostics record; null where none did or an older log does not say), problems (what
makes the run not clean), warnings (what a clean run's summary warns of: camera outages,
unauthenticated parameter requests refused, ...), rejected ({TOPIC: records skipped}),
recovered (null, or the hil.recovered record: from, input_bytes, kept_bytes, lost_bytes,
skipped_bytes, stopped, line), topics ({TOPIC: {messages, schema}}),
messages, run_info (all hil.run metadata), notes, parameters (the online parameter service's
requests: accepted, refused, unauthenticated; failed (in the controller, unanswered),
unchanged (a set to the values in force) and oversized (a mark's note over its limit) when
some were; {} when the run had no parameter service).
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="summarise a controller log: run, config digest, ticks, misses, problems, topics",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("log", metavar="LOG.mcap", help="controller log")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:

    from rt_controller.logs import load
    from rt_controller.logs.info import log_info
    from rt_controller.logtools.replay_out import inherited_loss

    run = load(args.log, raw=False)
    info = {**log_info(run), "parameters": parameter_counts(run)}
    if args.json:
        print(strict_json.dumps(info))
    else:
        print(render(info, partial=inherited_loss(run.log)))
    return 0


def parameter_counts(run: Any) -> dict[str, int]:
    """The parameter service's counts of the run, from its final ``/diagnostics`` record (else
    its last): accepted, refused, unauthenticated, ...; {} when the run had no service."""
    from rt_controller.logs.info import final_diagnostics
    from rt_controller.runtime.diagnostics import values_of

    return values_of(final_diagnostics(run) or {}, "parameters")


def _parameters(counts: dict[str, Any]) -> str:
    """The parameter requests in one line: ``2 accepted, 1 refused, 0 unauthenticated`` (and
    ``failed``, ``unchanged``, ``oversized`` where the run counted some)."""
    from rt_controller.logtools.report_text import PARAMETER_COUNTS, RARE_COUNTS

    names = [k for k in PARAMETER_COUNTS if k not in RARE_COUNTS or k in counts]
    return ", ".join(f"{_fmt(counts.get(k, 0))} {k}" for k in names)


def _fmt(value: Any) -> str:
    if value is None:
        return "unknown"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _state(info: dict[str, Any], partial: str | None = None) -> str:
    """``complete`` only for a whole file holding the whole run: ``partial`` (the note of
    :func:`~rt_controller.logtools.replay_out.inherited_loss`) is a copy `hil recover` made
    of a cut or damaged log, or a replay of one."""
    if info.get("damaged"):
        return "DAMAGED (chunks that could not be read were skipped)"
    if info["truncated"]:
        return "TRUNCATED (the writer did not finish it)"
    return f"PARTIAL ({partial})" if partial else "complete"


def _ended(info: dict[str, Any]) -> str:
    """How the run ended: its end reason (``stopped by SIGINT``, as ``hil up`` says it), the
    ticks run and those planned."""
    from rt_controller.rig.ending import end_words

    planned = info.get("planned_ticks")
    of = f" of {planned} planned" if planned is not None else ""
    until = "" if planned is not None else " (no duration: run until stopped)"
    return f"{end_words(info)}, after {_fmt(info.get('ticks_run'))}{of} ticks{until}"


def render(info: dict[str, Any], partial: str | None = None) -> str:
    """The text of ``hil info``: aligned ``key: value`` lines, then the topics; ``partial``:
    why a whole file holds only part of its run (see :func:`_state`)."""
    run = info["run"]
    ticks = info["ticks"]
    span = f" ({info['first_tick']} .. {info['last_tick']})" if ticks else ""
    laws = ", ".join(f"{law} {n}" for law, n in info["laws"].items()) or "none"
    rows = [
        ("log", info["log"]),
        ("library", _fmt(info["library"])),
        ("state", _state(info, partial)),
        *((key, _fmt(run[key])) for key in run),
        ("config digest", _fmt(info["config_digest"])),
        ("duration", f"{info['duration_s']:.3f} s ({info['time_axis'].removesuffix(' (s)')})"),
        ("ticks", f"{ticks}{span}"),
        ("laws", laws),
        ("deadline misses", f"{_fmt(info['deadline_misses'])} "
         f"({_fmt(info['missed_periods'])} missed periods)"),
        *((("ended", _ended(info)),) if info.get("end_reason") else ()),
        *((("parameters", _parameters(p)),) if (p := info.get("parameters")) else ()),
        ("problems", "; ".join(info["problems"]) or "none"),
        *(("warning", w) for w in info.get("warnings") or ()),
        *((("recovered", info["recovered"]["line"]),) if info.get("recovered") else ()),
        ("messages", str(info["messages"])),
    ]  # fmt: skip
    width = max(len(k) for k, _ in rows) + 2
    lines = [f"{k + ':':<{width}}{v}" for k, v in rows]
    lines.append("topics:")
    topics = info["topics"]
    if topics:
        name_w = max(len(t) for t in topics)
        count_w = max(len(str(t["messages"])) for t in topics.values())
        for topic, t in topics.items():
            lines.append(
                f"  {topic:<{name_w}}  {t['messages']:>{count_w}} msgs  {t['schema'] or ''}"
            )
    lines += [f"note: {note}" for note in info["notes"]]
    return "\n".join(lines)
