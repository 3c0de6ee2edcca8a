"""A sweep's results folder: one row per run, kept as the runs finish.

* ``rows.jsonl``: the journal, one JSON row appended and flushed to disk as each run finishes
  (the truth for resuming; a torn last line of a killed sweep is ignored);
* ``results.parquet`` (pyarrow) and ``results.csv``: every run once (deduplicated by run key,
  the newest row winning), sorted by point and repetition, rewritten atomically from the
  journal while the sweep runs, at most every ``FLUSH_S`` seconds and every
  ``FLUSH_RATIO`` times the last rewrite's duration (a rewrite of 20k rows takes about a
  second: the client spends at most ~1/``FLUSH_RATIO`` of its time on them), and always
  once at its end;
* ``sweep.json``: the spec's hash, name and axes (a folder holds one study).

Columns: ``run_key``, ``spec_hash``, ``point``, ``rep``, ``seed``, one per axis (named by its
config key; a list value as JSON text), ``engine``, ``status`` (ok | failed), ``error``,
``problems`` (why a finished run is not clean), the figures of
:data:`rt_controller.sweep.engines.METRICS`, ``wall_s`` and ``version``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hal.whole_file import written_whole
from rt_controller.errors import ControllerConfigError
from rt_controller.sweep.engines import METRICS
from rt_controller.sweep.spec import Spec

FLUSH_S = 1.0
FLUSH_RATIO = 10.0
"""Wait at least this many times the last rewrite's duration before the next one."""
JOURNAL = "rows.jsonl"
PARQUET = "results.parquet"
CSV = "results.csv"
META = "sweep.json"
OWN_NAMES = (JOURNAL, PARQUET, CSV, "report.md", "plots", "logs")
"""What a sweep writes in its folder besides :data:`META` (replaced or appended to)."""

_FIXED_HEAD = [("run_key", "string"), ("spec_hash", "string"), ("point", "int64"),
               ("rep", "int64"), ("seed", "int64")]  # fmt: skip
_FIXED_TAIL = [
    ("engine", "string"),
    ("status", "string"),
    ("error", "string"),
    ("problems", "string"),
    *((m, "float64") for m in METRICS[:4]),
    *((m, "int64") for m in METRICS[4:]),
    ("wall_s", "float64"),
    ("version", "string"),
]


def axis_type(values: list[Any]) -> str:
    """The column type of an axis: bool, int64, float64, else string (lists as JSON text)."""
    if all(isinstance(v, bool) for v in values):
        return "bool"
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return "int64"
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return "float64"
    return "string"


def columns(spec: Spec) -> list[tuple[str, str]]:
    axes = [(k, axis_type([p[k] for p in spec.points])) for k in spec.axis_keys]
    return [*_FIXED_HEAD, *axes, *_FIXED_TAIL]


def _cell(value: Any, typ: str) -> Any:
    if typ == "string" and not isinstance(value, str):
        return json.dumps(value)
    if typ == "float64" and value is not None:
        return float(value)
    return value


class ResultStore:
    """The rows of one study in ``out``; :meth:`add` as runs finish, :meth:`close` at the end."""

    def __init__(self, out: Path, spec: Spec, engine: str | None = None) -> None:
        self.out = Path(out)
        self.spec = spec
        self.columns = columns(spec)
        self.rows: dict[str, dict[str, Any]] = {}
        self._dirty = False
        self._last_flush = 0.0
        self._flush_every = FLUSH_S
        self.out.mkdir(parents=True, exist_ok=True)
        self._check_meta()
        self._load_journal()
        self._check_engine(engine)
        self._journal = (self.out / JOURNAL).open("a", encoding="utf-8")
        if self._journal.tell() and not (self.out / JOURNAL).read_bytes().endswith(b"\n"):
            self._journal.write("\n")  # end a line torn by a killed sweep before appending

    # -- folder --------------------------------------------------------------------------
    def _check_meta(self) -> None:
        meta = self.out / META
        doc = {
            "spec_hash": self.spec.spec_hash,
            "name": self.spec.study.name,
            "spec": str(self.spec.path),
            "axes": [a.as_dict() for a in self.spec.axes],
            "repetitions": self.spec.study.repetitions,
            "runs": self.spec.runs,
        }
        if not meta.exists():
            ours = sorted(n for n in OWN_NAMES if (self.out / n).exists())
            if ours:  # not a sweep's folder: its report.md or results.csv are someone's
                raise ControllerConfigError(
                    f"--out {self.out} has {', '.join(ours)} but no {META}: not a sweep's "
                    "results folder (a sweep would overwrite those); give another folder"
                )
        if meta.exists():
            try:
                old = json.loads(meta.read_text(encoding="utf-8"))
                if not isinstance(old, dict):
                    raise ValueError(f"not a JSON object: {str(old)[:40]}")
            except (OSError, ValueError) as exc:
                raise ControllerConfigError(f"--out {self.out}: unreadable {META}: {exc}") from None
            if old.get("spec_hash") != self.spec.spec_hash and self._kept_any():
                raise ControllerConfigError(
                    f"--out {self.out} holds another study (spec hash {old.get('spec_hash')}, "
                    f"this spec {self.spec.spec_hash}); give another folder"
                )
        with self._writing(META), written_whole(meta) as tmp:  # never a half sweep.json
            tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")

    def _kept_any(self) -> bool:
        """Whether the folder keeps a run: a study that never finished one (its cluster
        could not be reached, a bad spec stopped it) leaves only a claim, which another spec
        may take, since nothing of it would be lost."""
        path = self.out / JOURNAL
        try:
            return path.exists() and bool(path.read_bytes().strip())
        except OSError as exc:
            raise ControllerConfigError(f"--out {self.out}: unreadable {JOURNAL}: {exc}") from None

    def _load_journal(self) -> None:
        path = self.out / JOURNAL
        if not path.exists():
            return
        # bytes that are no text make a line that does not parse: that run is run again
        for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue  # a line torn by a killed sweep: that run is simply run again
            if isinstance(row, dict) and isinstance(row.get("run_key"), str):
                self.rows[row["run_key"]] = row
        self._dirty = True

    def _check_engine(self, engine: str | None) -> None:
        """Refuse to add ``engine``'s runs to a folder holding the other engine's: the spec
        hash leaves the engine out (both run the same seeds), so the report would mix them."""
        others = sorted({str(r.get("engine")) for r in self.rows.values()} - {engine})
        if engine is not None and others:
            raise ControllerConfigError(
                f"--out {self.out} holds this study's runs on the {' and '.join(others)} "
                f"engine; give another folder for the {engine} engine's"
            )

    def done(self, retry_failed: bool = False) -> set[str]:
        """Keys of the runs that need no rerun: every finished run, or with ``retry_failed``
        only the ``ok`` ones."""
        return {k for k, r in self.rows.items() if not retry_failed or r.get("status") == "ok"}

    # -- rows ----------------------------------------------------------------------------
    def add(self, row: dict[str, Any]) -> None:
        """Record a finished run (a repeated key replaces the earlier row). A Ctrl-C waits
        until the row is in both the journal and the table's rows, so the two never differ."""
        from rt_controller.rig.supervise import signals_deferred

        with signals_deferred(), self._writing(JOURNAL):
            self._journal.write(json.dumps(row, allow_nan=True) + "\n")
            self._journal.flush()
            os.fsync(self._journal.fileno())
            self.rows[row["run_key"]] = row
            self._dirty = True
        if time.monotonic() - self._last_flush >= self._flush_every:
            self.flush()

    def ordered(self, keys: set[str] | None = None) -> list[dict[str, Any]]:
        rows = [r for k, r in self.rows.items() if keys is None or k in keys]
        return sorted(rows, key=lambda r: (r.get("point", 0), r.get("rep", 0), r["run_key"]))

    def table(self, keys: set[str] | None = None) -> Any:
        import pyarrow as pa

        rows = self.ordered(keys)
        arrays = {
            name: pa.array([_cell(r.get(name), typ) for r in rows], type=getattr(pa, typ)())
            for name, typ in self.columns
        }
        return pa.table(arrays)

    def flush(self) -> None:
        """Rewrite ``results.parquet`` and ``results.csv`` (atomically) when rows changed."""
        if not self._dirty:
            return
        import pyarrow.csv as pcsv
        import pyarrow.parquet as pq

        start = time.monotonic()
        table = self.table()
        for name, write in (
            (PARQUET, lambda t, p: pq.write_table(t, p)),
            (CSV, lambda t, p: pcsv.write_csv(t, p)),
        ):
            with self._writing(name), written_whole(self.out / name) as tmp:
                write(table, str(tmp))
        self._dirty = False
        self._last_flush = time.monotonic()
        self._flush_every = max(FLUSH_S, FLUSH_RATIO * (self._last_flush - start))

    @contextlib.contextmanager
    def _writing(self, name: str) -> Iterator[None]:
        """An :class:`OSError` while writing ``name`` (a full disk) names the file and what
        is kept."""
        try:
            yield
        except OSError as exc:
            reason = exc.strerror or " ".join(str(exc).split()) or type(exc).__name__
            raise OSError(
                exc.errno,
                f"{reason} (the finished rows are kept in {self.out / JOURNAL}: "
                "the same command resumes)",
                str(self.out / name),
            ) from None

    def close(self) -> None:
        try:
            self.flush()
        finally:
            with self._writing(JOURNAL):
                self._journal.close()

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *_rest: object) -> None:
        if exc_type is None:
            self.close()
            return
        with contextlib.suppress(OSError):  # the error on its way out is the one to tell
            self.close()


def counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    ok = sum(1 for r in rows if r.get("status") == "ok")
    return {"ok": ok, "failed": len(rows) - ok}


def finite(value: Any) -> bool:
    return isinstance(value, int | float) and math.isfinite(value)
