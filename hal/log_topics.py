"""The topic names of a run's MCAP log and of ``hil monitor``'s live channels, spelled once.

They are a contract (Foxglove layouts, ``hil vision --source log:``, analysis scripts read them;
what each carries: ``docs/concepts/logs.md``). They live in ``hal`` so that ``vision``, which
may not import ``rt_controller``, reads a log's frames under the name the recorder wrote.
"""

from __future__ import annotations

CYCLE_TOPIC = "/controller/cycle"
"""One controller tick (``hil.ControllerCycle`` JSON); also live, on ``hil/controller/cycle``."""
CAN_RX_TOPIC = "/hal/can/rx"
"""A CAN frame received by the controller (``hil.CanFrame`` JSON)."""
CAN_TX_TOPIC = "/hal/can/tx"
"""A CAN frame sent by the controller (``hil.CanFrame`` JSON)."""
CANOPEN_TOPIC = "/hal/canopen"
"""A ``cia402`` run's CAN frame decoded by the recorder (``hil.CanopenFrame`` JSON)."""
VISION_TOPIC = "/vision/features"
"""A vision message as received (``hil.VisionPayload`` JSON, raw bytes)."""
DIAGNOSTICS_TOPIC = "/diagnostics"
"""Every counter, about 1 Hz and a final record (``hil.Diagnostics`` JSON); also live."""
PARAMETERS_TOPIC = "/controller/parameters"
"""An online change set, accepted or refused (``hil.ParameterChange`` JSON)."""
EVENTS_TOPIC = "/controller/events"
"""An operator action at its tick (``hil.OperatorEvent`` JSON)."""

TF_TOPIC = "/tf"
"""world -> link1 -> link2 -> camera (``foxglove.FrameTransforms``)."""
SCENE_TOPIC = "/scene/arm"
"""The arm, the camera's frustum, the target and the ray (``foxglove.SceneUpdate``)."""
CALIBRATION_TOPIC = "/camera/calibration"
"""The image's pinhole (``foxglove.CameraCalibration``)."""
ANNOTATIONS_TOPIC = "/camera/annotations"
"""The features the controller used, on the image (``foxglove.ImageAnnotations``)."""
IMAGE_TOPIC = "/camera/image"
"""What the camera saw (``foxglove.CompressedImage``, PNG); a blank plane with no images."""
DETECTION_TOPIC = "/camera/detection"
"""The detector's result on each logged frame (``foxglove.ImageAnnotations``)."""

FEATURES_DECODED_TOPIC = "/vision/features/decoded"
"""Live only: the features message decoded (``hil.Features`` JSON)."""
CAMERA_POSE_TOPIC = "/emulator/camera_pose"
"""Live only: the emulator's camera pose (``hil.CameraPose`` JSON)."""
EMULATOR_SCENE_TOPIC = "/scene/emulator"
"""Live only: the emulator's true camera pose drawn (``foxglove.SceneUpdate``)."""
