"""Controller logs as data: one call turns an MCAP log into tables.

>>> from rt_controller.logs import load
>>> run = load("logs/run.mcap")
>>> run.cycles[["sim_time_s", "f_x", "f_y"]]       # pandas, one row per tick
>>> run.arrays()["f_x"]                            # the same column as NumPy, no pandas

:func:`load` reads the file once (:func:`rt_controller.logtools.reader.read_log`: robust to a
log whose writer was killed) and gives a :class:`Run`:

- ``run.cycles``: the ``/controller/cycle`` records, index ``tick``; vectors as columns
  (``q1``, ``q2``, ``dq1``, ``f_x``, ``f_y``, ``tau1``, ... :data:`VECTOR_SUFFIXES`);
- ``run.diagnostics``: the ``/diagnostics`` records, one column per component counter
  (``can_rx_accepted``, ``controller_deadline_misses``, ...);
- ``run.can_frames``: every raw CAN frame received and sent, decoded with the rig's DBC
  (``hal/hil.dbc``, cantools): time, direction, frame id, message name, one column per signal
  (a ``cia402`` log: CANopen decoded by COB-ID, :mod:`hal.cia402_frames`);
- ``run.canopen_frames``: a ``cia402`` log's ``/hal/canopen``, the frames as the recorder
  decoded them (kind, node, one column per decoded field);
- ``run.config``: the run's configuration as recorded (``hil.config`` metadata);
- ``run.arrays(topic)``: the same tables as dicts of NumPy columns, without pandas.

The DataFrames need the ``analysis`` extra (pandas); without it they raise
:class:`~rt_controller.errors.MissingExtraError` naming it, and everything else still works.
"""

from __future__ import annotations

from rt_controller.logs.run import TOPICS, VECTOR_SUFFIXES, Run, load

__all__ = ["TOPICS", "VECTOR_SUFFIXES", "Run", "load"]
