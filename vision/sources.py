"""Where frames come from, behind one interface: :meth:`FrameSource.run` pushes every frame
(or the reason a payload was no frame) to the grabber until the source ends or is stopped.

=========================== ===================================================================
``--source``                frames
=========================== ===================================================================
``emulated``                the emulated camera over zenoh (``hil/camera/frame``,
                            :mod:`hal.camera_frame`, authenticated with the rig key)
``v4l2:/dev/video0``        a V4L2 device through ``cv2.VideoCapture``
``gst:PIPELINE``            a GStreamer pipeline ending in ``appsink`` (OpenCV with GStreamer)
``file:clip.mp4``           a video file or URL that ``cv2.VideoCapture`` opens, or a numbered
                            image sequence (``file:views/view-%03d.png``)
``log:run.mcap``            the camera frames of a recorded log (``/camera/image``), offline
=========================== ===================================================================

A real camera's frames are stamped with CLOCK_MONOTONIC when the grab returned (the capture
stamp is not known more closely through VideoCapture), converted to 8-bit grey, and numbered
from 0.
"""

from __future__ import annotations

import os
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from hal.camera_frame import CameraFrame, FrameDecoder, RoiRequest, encode_roi_request
from hal.durations import Durations
from hal.errors import HalConfigError, HalTransportError
from hal.log_topics import IMAGE_TOPIC
from hal.secoc import AnotherKeyNotice
from hal.signals import wait_for_stop
from vision.sequence import SequenceCapture, is_sequence, sequence_files

FrameSink = Callable[[CameraFrame], None]
"""Receives each frame."""
RejectSink = Callable[[str], None]
"""Receives the reason of each payload that was not a frame (``malformed``, ``bad_mac``)."""
SOURCE_KINDS = ("emulated", "v4l2", "gst", "file", "log")


class FrameSource(Protocol):
    """A source of frames."""

    name: str

    def run(self, on_frame: FrameSink, on_reject: RejectSink, stop: threading.Event) -> None:
        """Push frames until the source ends (a file, a log) or ``stop`` is set."""
        ...  # pragma: no cover

    def request_roi(self, req: RoiRequest) -> None:
        """Ask for a region of interest of a coming frame (a source that cannot read out a
        region ignores it and sends whole frames)."""
        ...  # pragma: no cover


def to_grey(img: np.ndarray) -> np.ndarray:
    """An 8-bit grey image of what VideoCapture or imdecode returned (grey, BGR or BGRA)."""
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    return np.ascontiguousarray(img)


def grabbed_frame(seq: int, pixels: np.ndarray, stamp_ns: int) -> CameraFrame:
    """A frame of a real camera or file: numbered ``seq``, stamped ``stamp_ns`` (also its
    simulation time: a real camera has no other clock), exposure unknown (0)."""
    return CameraFrame(seq, stamp_ns, stamp_ns, 0, seq, to_grey(pixels))


class EmulatedSource:
    """Frames of the emulated camera over zenoh, decoded and authenticated by
    :class:`hal.camera_frame.FrameDecoder` (its counters: :attr:`decoder`). Frames are pushed
    from zenoh's callback thread: a lockstep answer leaves without a thread hop.

    Timing, per frame handed on: :attr:`pipeline_ns`, the payload's arrival to the grabber's
    return (decode, MAC, detect, undistort, publish); :attr:`arrival_ns`, lockstep only, the
    camera pose offered (the end of the exposure, on the emulator's monotonic clock, which
    is this host's) to the payload's arrival (render, encode, zenoh).

    A frame whose MAC does not verify is rejected as ``bad_mac``; the first one is said on
    stderr: it means another rig key, not a broken camera."""

    name = "emulated"

    def __init__(self, session: object, key: bytes) -> None:
        self.session = session
        self.key = key
        self.bad_mac_notice = AnotherKeyNotice("hil vision", "camera frames")
        """Said at the first camera frame whose MAC does not verify."""
        self.decoder = FrameDecoder(key=key)
        self.pipeline_ns = Durations()
        self.arrival_ns = Durations()
        self._roi_pub: object = None

    def request_roi(self, req: RoiRequest) -> None:
        """Send the request to the camera on ``hil/camera/roi`` (while :meth:`run` runs)."""
        if self._roi_pub is not None:
            self._roi_pub.put(encode_roi_request(req, self.key))  # type: ignore[attr-defined]

    def run(self, on_frame: FrameSink, on_reject: RejectSink, stop: threading.Event) -> None:
        from hal.zenoh_session import KEY_CAMERA_FRAME, KEY_CAMERA_ROI

        self._roi_pub = self.session.publisher(KEY_CAMERA_ROI)  # type: ignore[attr-defined]

        def feed(payload: bytes) -> None:
            t0 = time.monotonic_ns()
            c = self.decoder.counts
            malformed, bad_mac = c.malformed, c.bad_mac
            frame = self.decoder.feed(payload)
            if frame is not None:
                on_frame(frame)
                self.pipeline_ns.add(time.monotonic_ns() - t0)
                if frame.lockstep:
                    self.arrival_ns.add(t0 - frame.stamp_ns - frame.exposure_ns // 2)
            elif c.bad_mac > bad_mac:  # not an out-of-order frame: no frame at all
                self.bad_mac_notice.say()
                on_reject("bad_mac")
            elif c.malformed > malformed:
                on_reject("malformed")

        sub = self.session.subscribe(KEY_CAMERA_FRAME, feed)  # type: ignore[attr-defined]
        try:
            wait_for_stop(stop)  # a stop signal may reach a zenoh thread, not this one
        finally:
            sub.undeclare()
            pub, self._roi_pub = self._roi_pub, None
            pub.undeclare()  # type: ignore[attr-defined]


class CaptureSource:
    """A camera, pipeline or file through ``cv2.VideoCapture``."""

    def __init__(self, kind: str, target: str, *, pace: bool = False) -> None:
        self.name = f"{kind}:{target}"
        self.kind, self.target = kind, target
        self.pace = pace and kind == "file"
        """A file played at its own frame rate (as if live), not as fast as it decodes."""

    def request_roi(self, req: RoiRequest) -> None:
        """VideoCapture reads whole frames: the request is ignored."""

    def open(self) -> cv2.VideoCapture:
        check_source(self.name)
        if self.kind == "file" and is_sequence(self.target):  # each image at its own size
            return SequenceCapture(sequence_files(Path(self.target), self.name))  # type: ignore[return-value]
        quiet_ffmpeg()
        api = {"v4l2": cv2.CAP_V4L2, "gst": cv2.CAP_GSTREAMER}.get(self.kind, cv2.CAP_ANY)
        logging = cv2.utils.logging
        level = logging.getLogLevel()
        logging.setLogLevel(logging.LOG_LEVEL_ERROR)  # its warnings: our one line says it
        try:
            cap = cv2.VideoCapture(self.target, api)
        finally:
            logging.setLogLevel(level)
        if not cap.isOpened():
            cap.release()
            if self.kind == "file" and "://" not in self.target:  # it exists (checked above)
                raise HalConfigError(
                    f"--source {self.name}: not a video OpenCV can open (or this OpenCV has no "
                    "decoder for it)"
                )
            if self.kind == "v4l2":
                raise HalTransportError(
                    f"--source {self.name}: OpenCV cannot open it (busy in another program, or "
                    "no capture node: a USB camera's other /dev/videoN carries metadata; "
                    "v4l2-ctl --list-devices names them)"
                )
            raise HalTransportError(
                f"--source {self.name}: OpenCV cannot open it (device busy or missing, or this "
                "OpenCV has no backend for it)"
            )
        return cap

    def run(self, on_frame: FrameSink, on_reject: RejectSink, stop: threading.Event) -> None:
        """Read frames on a thread of the capture's own (the grabber may make the thread that
        measures them SCHED_FIFO: not the caller's), until the end, an error or ``stop``."""
        cap = self.open()
        failed: list[BaseException] = []

        def body() -> None:
            try:
                self._read(cap, on_frame, on_reject, stop)
            except BaseException as exc:  # handed to the caller's thread
                failed.append(exc)

        reader = threading.Thread(target=body, name="hil-vision-capture", daemon=True)
        reader.start()
        try:
            while reader.is_alive():
                reader.join(0.5)  # a signal's handler (it sets stop) runs meanwhile
        finally:
            if reader.is_alive():  # the caller's thread was interrupted (Ctrl-C): end the reader
                stop.set()
                reader.join()
        if failed:
            raise failed[0]

    def _read(
        self,
        cap: cv2.VideoCapture,
        on_frame: FrameSink,
        on_reject: RejectSink,
        stop: threading.Event,
    ) -> None:
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0) if self.pace else 0.0
        period_ns = round(1e9 / fps) if fps > 0 else 0
        seq, t0, rejected = 0, 0, 0
        try:
            while not stop.is_set():
                if period_ns and seq:  # frame k at k periods after the first frame was read
                    stop.wait(max(0, t0 + seq * period_ns - time.monotonic_ns()) / 1e9)
                ok, img = cap.read()
                stamp = time.monotonic_ns()
                t0 = t0 or stamp  # the first read (a decoder's start-up) sets the clock
                if not ok:
                    if seq == 0 and not rejected and not stop.is_set():
                        raise HalConfigError(
                            f"--source {self.name}: OpenCV could not read a frame from it (not "
                            "a video or image it decodes, or the device gave none)"
                        )
                    break  # end of the file, or the device went away
                if img is None or img.size == 0:
                    on_reject("malformed")
                    rejected += 1
                    continue
                on_frame(grabbed_frame(seq, img, stamp))
                seq += 1
        finally:
            cap.release()


def quiet_ffmpeg() -> None:
    """Keep FFmpeg's own lines ("moov atom not found") off stderr: the source's error says it
    in one line. Effective before OpenCV's first FFmpeg capture of the process; a user's
    ``OPENCV_FFMPEG_LOGLEVEL`` or ``OPENCV_FFMPEG_DEBUG`` is kept (set one to see them)."""
    if "OPENCV_FFMPEG_DEBUG" not in os.environ:
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


class LogSource:
    """The camera frames a run recorded (``/camera/image``, PNG or JPEG), in log order; their
    stamps are the log times."""

    def __init__(
        self, path: str, topic: str = IMAGE_TOPIC, notice: Callable[[str], None] | None = None
    ) -> None:
        self.name = f"log:{path}"
        self.path, self.topic = Path(path), topic
        self.notice = notice
        """Told once when the file ends in a cut or damaged record (a killed recorder)."""

    def request_roi(self, req: RoiRequest) -> None:
        """A log holds whole frames: the request is ignored."""

    def run(self, on_frame: FrameSink, on_reject: RejectSink, stop: threading.Event) -> None:
        """Re-run the frames with mcap's stream reader, as far as the file goes: a log whose
        recorder was killed (no summary, a half-written chunk) still gives the frames of its
        complete chunks, as the other log tools read it."""
        from mcap.records import Channel, Header, Message, Metadata
        from mcap.stream_reader import StreamReader

        check_source(self.name)
        _check_mcap_magic(self.path, self.name)
        seq, seen, started, topic_ids = 0, 0, False, set()
        with self.path.open("rb") as fh:
            reader = StreamReader(
                fh, validate_crcs=True, record_size_limit=max(self.path.stat().st_size, 1)
            )
            try:
                for rec in reader.records:
                    started = started or isinstance(rec, Header)
                    if isinstance(rec, Channel) and rec.topic == self.topic:
                        topic_ids.add(rec.id)
                    if isinstance(rec, Metadata) and rec.name == "hil.config":
                        self._check_camera_model(rec.metadata.get("json", ""))
                    if not isinstance(rec, Message) or rec.channel_id not in topic_ids:
                        continue
                    if stop.is_set():
                        return
                    seen += 1
                    pixels = decode_compressed_image(rec.data)
                    if pixels is None:
                        on_reject("malformed")
                        continue
                    on_frame(grabbed_frame(seq, pixels, rec.log_time))
                    seq += 1
            except HalConfigError:
                raise
            except Exception as exc:  # a cut or damaged tail ends the frames; no header: refuse
                if not started:
                    raise HalConfigError(
                        f"--source {self.name}: not a readable MCAP log ({exc})"
                    ) from None
                if self.notice is not None:
                    self.notice(
                        f"{self.path} ends after {seq} {self.topic} frames in a cut or "
                        f"damaged record ({type(exc).__name__}: a killed recorder, a partial "
                        "copy): those frames were re-run"
                    )
        if not seen and not stop.is_set():
            raise HalConfigError(
                f"--source {self.name}: the log has no {self.topic} frames (the run recorded "
                "no camera images, or the log was cut before them)"
            )
        if seen and not seq and not stop.is_set():  # as a file OpenCV cannot read
            raise HalConfigError(
                f"--source {self.name}: none of its {seen} {self.topic} frames is an image "
                "OpenCV decodes (damaged frames, or another topic of that name)"
            )

    def _check_camera_model(self, config_json: str) -> None:
        """One line when the run's config (the ``hil.config`` metadata, before the frames)
        had the analytic camera: its ``/camera/image`` is the monitor's blank image plane."""
        import json

        try:
            model = json.loads(config_json)["camera"]["model"]
        except (ValueError, KeyError, TypeError):
            return  # not said: the frames tell
        if model == "analytic":
            raise HalConfigError(
                f"--source {self.name}: a run of the analytic camera (camera.model = analytic): "
                f"its {self.topic} is the monitor's blank image plane, no camera frames"
            )


def check_source(spec: str) -> None:
    """One line unless ``spec``'s target can be opened at all: a file or log that is a readable
    regular file, a V4L2 device that is a character device this user may open, a GStreamer
    pipeline with OpenCV's GStreamer backend. Checked before anything waits (the zenoh hub),
    so a typo is told at once, not after ``--wait``."""
    kind, target = parse_source(spec)
    if kind == "file" and is_sequence(target):
        sequence_files(Path(target), spec)
    elif kind == "file" and "://" not in target:
        _check_is_file(Path(target), spec, "a video or image file")
    elif kind == "log":
        _check_is_file(Path(target), spec, "an MCAP log")
    elif kind == "v4l2":
        _check_device(Path(target), spec)
    elif kind == "gst" and not cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER):
        raise HalConfigError(f"--source {spec}: this OpenCV was built without GStreamer")


def _check_is_file(path: Path, name: str, what: str) -> None:
    """One line unless ``path`` is a readable regular file: missing, directory and unreadable
    said apart."""
    if path.is_dir():
        raise HalConfigError(f"--source {name}: is a directory, not {what}")
    if not path.is_file():
        raise HalConfigError(f"--source {name}: no such file")
    if not os.access(path, os.R_OK):
        raise HalConfigError(f"--source {name}: not readable (permission denied)")


MCAP_MAGIC = b"\x89MCAP0\r\n"


def _check_mcap_magic(path: Path, name: str) -> None:
    """One line unless ``path`` begins as an MCAP file does (a clip, a key, a text file named
    by mistake: said as such, not as a reader's internal complaint)."""
    with path.open("rb") as fh:
        head = fh.read(len(MCAP_MAGIC))
    if not head:
        raise HalConfigError(f"--source {name}: not an MCAP log: an empty file")
    if head != MCAP_MAGIC:
        raise HalConfigError(
            f"--source {name}: not an MCAP log: does not begin with the MCAP magic"
        )


def _check_device(path: Path, name: str) -> None:
    """One line unless ``path`` is a character device this user may read and write (V4L2
    opens it read-write)."""
    try:
        mode = path.stat().st_mode
    except OSError:
        hint = f" (give its path: v4l2:/dev/video{path})" if str(path).isdigit() else ""
        raise HalConfigError(f"--source {name}: no such device{hint}") from None
    if not stat.S_ISCHR(mode):
        raise HalConfigError(f"--source {name}: not a video device (a V4L2 device is /dev/videoN)")
    if not os.access(path, os.R_OK | os.W_OK):
        raise HalConfigError(
            f"--source {name}: permission denied (is this user in the device's group, e.g. video?)"
        )


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, i
        shift += 7


def decode_compressed_image(data: bytes) -> np.ndarray | None:
    """The grey pixels of a ``foxglove.CompressedImage`` (protobuf; ``data`` is field 2), or
    None when it is no such message or no image OpenCV decodes. Five protobuf wire rules here
    instead of a protobuf runtime dependency."""
    try:
        i, image = 0, None
        while i < len(data):
            tag, i = _varint(data, i)
            wire = tag & 7
            if wire == 0:
                _, i = _varint(data, i)
            elif wire == 2:
                n, i = _varint(data, i)
                if tag >> 3 == 2:
                    image = data[i : i + n]
                i += n
            elif wire in (1, 5):
                i += 8 if wire == 1 else 4
            else:
                return None
        if image is None or i != len(data):
            return None
        return cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_GRAYSCALE)
    except (IndexError, cv2.error):
        return None


def parse_source(spec: str) -> tuple[str, str]:
    """``KIND[:TARGET]`` -> (kind, target); a one-line :class:`HalConfigError` otherwise."""
    kind, sep, target = spec.partition(":")
    if kind not in SOURCE_KINDS:
        raise HalConfigError(
            f"--source {spec!r}: unknown kind {kind!r} (one of {', '.join(SOURCE_KINDS)})"
        )
    if kind == "emulated":
        if target:
            raise HalConfigError(f"--source {spec!r}: 'emulated' takes no target")
        return kind, ""
    if not sep or not target:
        raise HalConfigError(f"--source {spec!r}: {kind} needs a target, e.g. {kind}:PATH")
    if kind != "gst" and target.startswith("~"):  # the shell expands no ~ after "log:"
        target = os.path.expanduser(target)
    return kind, target


def open_source(
    spec: str,
    *,
    session: object = None,
    key: bytes = b"",
    live: bool = False,
    notice: Callable[[str], None] | None = None,
) -> FrameSource:
    """The frame source named by ``spec`` (``emulated`` needs the zenoh ``session`` and key;
    ``live``: a file plays at its own frame rate; ``notice``: a log's cut end is told)."""
    kind, target = parse_source(spec)
    if kind == "emulated":
        return EmulatedSource(session, key)
    if kind == "log":
        return LogSource(target, notice=notice)
    return CaptureSource(kind, target, pace=live)
