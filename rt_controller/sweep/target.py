"""The numba compile target of a sweep's rows, kept with them so a resumed sweep matches.

A sweep's first run writes the target its local workers compile for (this process's: they
inherit its environment) to ``compile_target.json`` in its output folder. A later run of the
same command there (a resume, ``--retry-failed``) on a host that can run that target gives its
workers the environment that compiles for it (:meth:`CompileTarget.env`, and glibc's libm
narrowed to the first host's), so the new rows round as the old ones did; where the host cannot,
one line says that the new rows may differ by the cross-target spread.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from hal.whole_file import written_whole
from rt_controller import compile_target as ct

TARGET_FILE = "compile_target.json"


def worker_env(out: Path, say: Callable[[str], None]) -> dict[str, str]:
    """The environment for this sweep's local workers (empty: this process's own); writes
    ``out/compile_target.json`` on the sweep's first run."""
    path = Path(out) / TARGET_FILE
    here = ct.this_process()
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        record = {**here.as_dict(), ct.KEY_LIBM: ",".join(sorted(ct.libm_features()))}
        with written_whole(path) as tmp:  # a full disk leaves no empty file to warn of
            tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        kept = ct.CompileTarget(str(data["cpu_name"]), str(data["features"]), str(data["triple"]))
        info = {ct.KEY_LIBM: str(data[ct.KEY_LIBM])}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        say(f"warning: {path} is unreadable ({exc}); the workers compile for this host")
        return {}
    libm, _ = ct.libm_env(info)
    if kept == here and ct.libm_matches(info):
        return {}
    if not kept.runnable():
        say(
            f"warning: the sweep's rows were compiled for {kept.label()}, which cannot run here "
            f"(this CPU lacks {', '.join(kept.missing_here()[:6]) or kept.triple}); new rows "
            f"are compiled for {here.label()} and may differ by the cross-target spread"
        )
        return {}
    say(
        f"workers compile for the sweep's target {kept.label()}, as its first rows were "
        f"(numba cache {ct.cache_dir(kept)})"
    )
    return {**kept.env(), **libm}
