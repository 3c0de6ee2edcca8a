"""The emulators' pose sink (:class:`plant_emulator.pose_link.PoseLink`): every pose reaches the
emulated camera in the process, when there is one, and zenoh (the analytic vision process
answers each lockstep pose; a tool may read the true pose of an image run)."""

from __future__ import annotations

from typing import Any

from hal.errors import HalTransportError
from plant_emulator.camera import CameraPose
from plant_emulator.pose_link import PoseLink

POSE = CameraPose(0.1, 0.2, 0.3)


class Publisher:
    """What :class:`~plant_emulator.pose_link.PosePublisher` shows the link."""

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.sent: list[tuple[Any, ...]] = []
        self.source, self.seed = 7, None

    def publish(self, *args: Any) -> None:
        if self.fail:
            raise HalTransportError("zenoh: session closed")
        self.sent.append(args)


class Camera:
    def __init__(self) -> None:
        self.offers: list[tuple[Any, ...]] = []
        self.seeds: list[int | None] = []

    def offer(self, *args: Any) -> None:
        self.offers.append(args)

    def new_run(self, seed: int | None) -> None:
        self.seeds.append(seed)


def test_every_pose_goes_to_the_camera_here_and_on_zenoh() -> None:
    pub, camera = Publisher(), Camera()
    link = PoseLink(pub)  # type: ignore[arg-type]
    link(0, 0, POSE, True)  # no camera yet: zenoh only
    link.camera = camera  # type: ignore[assignment]
    for k in range(1, 3):
        link(k, k * 20_000_000, POSE, True, 1000 + k)
    assert camera.offers == [(k, k * 20_000_000, POSE, True, 1000 + k) for k in range(1, 3)]
    assert pub.sent == [(0, 0, POSE, True, None), *camera.offers]


def test_a_broken_session_is_counted_never_raised_and_the_camera_still_gets_the_pose() -> None:
    pub, camera = Publisher(fail=True), Camera()
    link = PoseLink(pub)  # type: ignore[arg-type]
    link.camera = camera  # type: ignore[assignment]
    link(0, 0, POSE, False)
    link(1, 20_000_000, POSE, False)
    assert link.errors == 2 and len(camera.offers) == 2


def test_a_scenario_reset_names_a_new_source_and_hands_the_seed_to_the_camera() -> None:
    pub, camera = Publisher(), Camera()
    link = PoseLink(pub)  # type: ignore[arg-type]
    link.camera = camera  # type: ignore[assignment]
    link.new_run(42)
    assert pub.source != 7 and pub.seed == 42 and camera.seeds == [42]
