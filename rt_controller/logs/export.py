"""``hil export``: a log's tables as CSV (pandas), Parquet (pyarrow) or MATLAB ``.mat`` (scipy).

CSV and Parquet hold one table per file (``STEM.cycle.csv``, ``STEM.diagnostics.csv``,
``STEM.can.csv``, ``STEM.canopen.csv``); a ``.mat`` file holds every table, one struct per
topic (``cycle``, ``diagnostics``, ``can``, ``canopen``) whose fields are the columns, plus
a ``meta`` struct (the log's path, the recorded configuration as JSON, its digest and the
``hil.run`` metadata). Column names are valid MATLAB identifiers already (``q1``, ``f_x``,
``can_rx_accepted``, ``Tau1``).

The ``can`` table's columns have the types of ``run.can_frames``: an integer DBC signal is an
Arrow ``int64`` column with nulls in Parquet and digits with empty cells in CSV; ``.mat`` has
no missing integer, so every signal is a double with NaN there (:meth:`Run.arrays`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hal.whole_file import written_whole
from rt_controller.errors import ControllerConfigError, LogError
from rt_controller.logs.run import TOPICS, Run, identifier, require

SUFFIXES = {"csv": ".csv", "parquet": ".parquet", "mat": ".mat"}
"""File suffix per format."""
MODULES = {
    "csv": ("pandas",),
    "parquet": ("pyarrow", "pyarrow.parquet", "pandas"),  # pandas: the can table's integers
    "mat": ("scipy.io",),
}
"""What each format needs from the ``analysis`` extra."""
MATLAB_NAME_MAX = 63
"""MATLAB's ``namelengthmax``."""


@dataclass(frozen=True)
class Written:
    topic: str
    path: Path
    rows: int


def check_format(fmt: str) -> None:
    """Raise before any work if ``fmt`` is unknown or its library is not installed."""
    if fmt not in SUFFIXES:
        raise ControllerConfigError(f"unknown format {fmt!r}: choose from {', '.join(SUFFIXES)}")
    for module in MODULES[fmt]:
        require(module, f"{fmt} export")


def plan_outputs(
    log: str | Path, fmt: str, topics: Sequence[str], out: str | Path | None = None
) -> dict[str, Path]:
    """The file each topic goes to (``hil export`` checks them with the commands' output-path
    rule before any work; nothing is created here).

    ``out`` ending in the format's suffix is the file itself (one topic for CSV and Parquet;
    every topic for ``.mat``); any other ``out`` is a directory, default the log's own.
    """
    check_format(fmt)
    bad = [t for t in topics if t not in TOPICS]
    if bad or not topics:
        raise ControllerConfigError(
            f"unknown topic(s) {', '.join(bad) or '(none)'}: choose from {', '.join(TOPICS)}"
        )
    suffix, log = SUFFIXES[fmt], Path(log)
    if out is not None and str(out).lower().endswith(suffix):  # X.CSV is a CSV file too
        target = Path(out)
        if fmt != "mat" and len(topics) > 1:
            raise ControllerConfigError(
                f"--out {out}: a {suffix} file holds one topic, not {len(topics)} "
                f"({', '.join(topics)}): give a directory or one --topics"
            )
        files = dict.fromkeys(topics, target)
    else:
        directory = Path(out) if out is not None else log.parent
        name = {t: f"{log.stem}.{t}{suffix}" for t in topics}
        files = {t: directory / (f"{log.stem}.mat" if fmt == "mat" else name[t]) for t in topics}
    return files


def export(run: Run, fmt: str, files: dict[str, Path]) -> list[Written]:
    """Write ``run``'s tables to ``files`` (from :func:`plan_outputs`)."""
    check_format(fmt)
    for path in set(files.values()):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise LogError(f"cannot create {path.parent}: {exc.strerror or exc}") from None
    write = {"csv": _write_csv, "parquet": _write_parquet, "mat": _write_mat}[fmt]
    try:  # each file written whole (hal.whole_file): a full disk leaves the last export
        return write(run, files)
    except OSError as exc:  # pyarrow's text names the file itself
        text = " ".join((exc.strerror or str(exc)).split())
        where = f"{exc.filename}: " if exc.filename and str(exc.filename) not in text else ""
        raise LogError(f"cannot write the {fmt} export: {where}{text}") from None


def _write_csv(run: Run, files: dict[str, Path]) -> list[Written]:
    out = []
    for topic, path in files.items():
        df = run.frame(topic)
        with written_whole(path) as tmp:
            df.to_csv(tmp, index=df.index.name is not None)
        out.append(Written(topic, path, len(df)))
    return out


def _write_parquet(run: Run, files: dict[str, Path]) -> list[Written]:
    pa, pq = require("pyarrow", "parquet export"), require("pyarrow.parquet", "parquet export")
    meta = {"hil.log": str(run.path), "hil.config": run.config_json or ""}
    out = []
    for topic, path in files.items():
        ints = _integer_columns(run, topic)
        cols = run.arrays(topic)
        table = pa.table(
            {k: ints[k] if k in ints else pa.array(_as_list(v)) for k, v in cols.items()}
        )
        with written_whole(path) as tmp:
            pq.write_table(table.replace_schema_metadata({**meta, "hil.topic": topic}), tmp)
        out.append(Written(topic, path, table.num_rows))
    return out


def _integer_columns(run: Run, topic: str) -> dict[str, Any]:
    """The pandas nullable integer columns of ``run.can_frames`` and ``run.canopen_frames``
    (the integer DBC signals, a ``cia402`` log's whole-number CANopen fields: ``Int64`` with
    ``<NA>`` where a frame lacks them) as Arrow integer arrays with nulls, exact; empty for
    the other tables, whose DataFrames are their NumPy columns as they are."""
    if topic not in ("can", "canopen"):
        return {}
    pa, pd = require("pyarrow", "parquet export"), require("pandas", "parquet export")
    df = run.frame(topic)
    return {
        k: pa.array(df[k])
        for k in df.columns
        if pd.api.types.is_extension_array_dtype(df[k]) and pd.api.types.is_integer_dtype(df[k])
    }


def _as_list(col: np.ndarray) -> Any:
    """A column pyarrow takes as it is: numbers as arrays, objects (strings, None) as lists."""
    return col.tolist() if col.dtype == object else col


def matlab_names(names: Sequence[str]) -> dict[str, str]:
    """Each name as a distinct valid MATLAB identifier: letters, digits and ``_``, starting
    with a letter, at most :data:`MATLAB_NAME_MAX` characters."""
    out: dict[str, str] = {}
    taken: set[str] = set()
    for name in names:
        base = identifier(name)
        if not base[0].isalpha():
            base = "x_" + base
        candidate, n = base[:MATLAB_NAME_MAX], 1
        while candidate in taken:
            n += 1
            tail = f"_{n}"
            candidate = base[: MATLAB_NAME_MAX - len(tail)] + tail
        taken.add(candidate)
        out[name] = candidate
    return out


def _mat_column(col: np.ndarray) -> np.ndarray:
    """Strings (and None, as '') become a cell array; numbers and logicals stay arrays."""
    if col.dtype != object:
        return col
    cells = np.empty(len(col), dtype=object)
    cells[:] = ["" if v is None else str(v) for v in col]
    return cells


def _write_mat(run: Run, files: dict[str, Path]) -> list[Written]:
    sio = require("scipy.io", "mat export")
    by_file: dict[Path, dict[str, Any]] = {}
    out = []
    for topic, path in files.items():
        cols = run.arrays(topic)
        names = matlab_names(list(cols))
        struct = {names[k]: _mat_column(v) for k, v in cols.items()}
        by_file.setdefault(path, {})[topic] = struct
        rows = len(next(iter(cols.values()))) if cols else 0
        out.append(Written(topic, path, rows))
    info = run.info
    meta = {
        "log": str(run.path),
        "truncated": run.truncated,
        "config_json": run.config_json or "",
        "config_digest": run.config_digest or "",
        **{v: info[k] for k, v in matlab_names(list(info)).items()},
    }
    for path, structs in by_file.items():
        # opened here: scipy hides why it could not open a path
        with written_whole(path) as tmp, open(tmp, "wb") as fh:
            sio.savemat(
                fh,
                {**structs, "meta": meta},
                long_field_names=True,
                do_compression=True,
                oned_as="column",
            )
    return out
