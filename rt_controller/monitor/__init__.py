"""Watching a running rig: the controller's live cycle stream and ``hil monitor`` (Foxglove).

* :mod:`.live` — the controller side: publishes each ``/controller/cycle`` and ``/diagnostics``
  record on zenoh (``hil/controller/cycle``, ``hil/controller/diagnostics``) from the recorder's
  writer thread, never from the tick.
* :mod:`.scene` — the arm, camera, target and image features drawn with Foxglove's own schemas
  from one cycle record (written into the MCAP and sent live).
* :mod:`.bridge` — ``hil monitor``: zenoh -> a Foxglove WebSocket server (foxglove-sdk).
"""
