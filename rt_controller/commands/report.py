"""``hil report``: the deadline-miss report of one or more controller logs (MCAP)."""

from __future__ import annotations

import argparse
from typing import Any

from hal import strict_json
from hal.arguments import bounded_int, path_given
from rt_controller.commands.progress import Progress, add_quiet_option

DESCRIPTION = """\
Deadline-miss report of controller logs, cyclictest-style: ticks, deadline misses (count,
percentage, tick and time of each), wake-up lateness and cycle time min/median/p99/max (µs), a
log-scale lateness histogram, solve time and solver residuals, fallbacks, stale inputs, torque
saturation, final |f| and J (sum of the stage cost / rate). A log whose writer was killed is
reported as far as it goes, with a note. With several logs, one that cannot be read is named on
stderr and the others are reported (exit status 2).

--json prints one JSON object for one log, and a JSON list of such objects (in argument order,
each with its "log" path) for several logs. Keys include: log, truncated, notes, law, clock,
rate_hz, period_us, ticks, duration_s, deadline_misses, miss_pct, missed_periods, misses (list of
{tick, t_s, lateness_us, cycle_us, missed_periods}, capped by --max-list), lateness_us / cycle_us /
read_us / solve_us / write_us ({min, median, p99, max, mean}), lateness_histogram (list of
{lo_us, hi_us, count}), residual, iterations, fallbacks, stale_features, invalid_features,
stale_state, tau_saturated, f_final, f_final_norm, J, messages, recorder_dropped, outages,
diagnostics (the last /diagnostics record's counters, parameters among them), problems and
warnings (the run's verdict as `hil info` gives it: the controller's rule on the log). Values
that were not recorded are null.

The text starts with the verdict: "run not clean: ..." (the problems) or "problems: none", then
one line per warning.

--plot DIR writes PNGs named LOGSTEM_{lateness_hist,cycle_time,solve_time,f,xi,u,tau}.png,
and LOGSTEM_camera_jump.png (a contact sheet of the camera's frames around the target jump)
for a log that holds frames of it (none without a jump, or for a run that ended before it).
A log without cycle values gives no figure (said as "plots: none"). Each is written whole:
a full disk leaves the previous figure.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="deadline-miss report of controller logs (text, --json, --plot)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("logs", nargs="+", metavar="LOG.mcap", help="controller log(s)")
    p.add_argument(
        "--json", action="store_true", help="print JSON (an object, or a list for several logs)"
    )
    p.add_argument("--plot", type=path_given, metavar="DIR", help="write PNG figures into DIR")
    p.add_argument(
        "--max-list",
        type=bounded_int(0, 1_000_000_000, what="misses to list"),
        default=50,
        metavar="N",
        help="list at most N deadline misses per log (default 50)",
    )
    add_quiet_option(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import sys

    from rt_controller.commands.output import output_dir
    from rt_controller.errors import LogError
    from rt_controller.logs.info import judged_report
    from rt_controller.logtools.reader import read_hil_log
    from rt_controller.logtools.report_plots import write_plots
    from rt_controller.logtools.report_text import render_text

    plot_dir = output_dir(args.plot, "--plot") if args.plot else None
    progress = Progress.of(args, "hil report")
    logs, failed = [], []
    with progress.stage(f"reading {len(args.logs)} log(s)"):
        for path in args.logs:
            try:
                logs.append(_with_canopen_frames(read_hil_log(path, raw=False)))
            except LogError as exc:  # one bad log among several: report the others
                if len(args.logs) == 1:
                    raise
                failed.append(exc)
    for exc in failed if logs else failed[:-1]:  # each unreadable log named, in argument order
        print(f"hil report: error: {exc}", file=sys.stderr)
    if not logs:  # none could be read: the last one's error ends the command (exit status 2)
        raise failed[-1]
    reports = [judged_report(log, max_list=args.max_list) for log in logs]
    if plot_dir is not None:
        used: set[str] = set()
        stems = {log.path.stem for log in logs}
        with progress.stage(f"drawing the figures into {plot_dir}"):
            for log, rep in zip(logs, reports, strict=True):
                # a second run.mcap draws as run-2, or run-3 when a run-2.mcap is also given
                stem, k = log.path.stem, 1
                prefix = stem
                while prefix in used or (prefix != stem and prefix in stems):
                    k += 1
                    prefix = f"{stem}-{k}"
                used.add(prefix)
                rep["plots"] = [str(p) for p in write_plots(log, plot_dir, prefix)]
    if args.json:
        # the shape follows the logs asked for, not how many could be read
        payload = reports[0] if len(args.logs) == 1 else reports
        print(strict_json.dumps(payload))
        return 2 if failed else 0
    from rt_controller.commands.output import stdout_console

    console = stdout_console()
    for i, rep in enumerate(reports):
        if i:
            console.rule()
        render_text(rep, console)
        if rep.get("plots"):
            console.print(f"plots: {', '.join(rep['plots'])}", markup=False)
        elif plot_dir is not None:  # asked for, but nothing to draw: said, not left out
            console.print("plots: none (the log has no cycle values to draw)")
    return 2 if failed else 0


def _with_canopen_frames(log: Any) -> Any:
    """A cia402 log read again with its raw CAN frames (the CANopen section decodes them);
    any other log as it is (its raw frames are only counted)."""
    from rt_controller.logtools.reader import read_hil_log

    cfg = log.config
    if cfg is None or cfg.hardware.profile != "cia402":
        return log
    return read_hil_log(log.path, raw=True)
