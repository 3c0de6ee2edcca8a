"""Studies of many runs (``hil sweep``): a TOML spec, run on Dask, one result row per run.

* :mod:`~rt_controller.sweep.spec` reads and validates a study spec and expands it into
  :class:`~rt_controller.sweep.spec.RunTask` objects (config, seed, run key), before any run;
* :mod:`~rt_controller.sweep.engines` runs one task (``simulate``: in-process closed loop;
  ``rig``: the lockstep processes) and returns its row, never raising;
* :mod:`~rt_controller.sweep.executor` hands the tasks to a Dask cluster (a ``LocalCluster``
  on 127.0.0.1 or ``--scheduler``) and collects rows as they finish;
* :mod:`~rt_controller.sweep.results` keeps the rows (journal, Parquet, CSV; resume, dedupe);
* :mod:`~rt_controller.sweep.report` writes ``report.md`` and its plots;
* :mod:`~rt_controller.sweep.bench` measures runs/s (``hil bench sweep``).

The package sits beside :mod:`rt_controller.rig` (it drives rigs through
:mod:`rt_controller.rig.processes`) and below :mod:`rt_controller.commands`; like ``rig`` it
never imports the commands nor :mod:`plant_emulator`: the ``simulate`` engine is handed the
plant class by ``commands/sweep.py``.
"""
