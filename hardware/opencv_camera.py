"""USB video (UVC) cameras through OpenCV: V4L2 on Linux, the platform default elsewhere.

Three things make a webcam usable for structured light, and each is done here:

* **Resolution negotiation.** Drivers silently substitute the nearest mode they have, so the
  size asked for is only a request; the size of the first real frame is what is reported.
* **Manual exposure.** ``CAP_PROP_AUTO_EXPOSURE`` has no portable meaning: V4L2 passes the value
  straight to ``V4L2_CID_EXPOSURE_AUTO`` (1 = manual, 3 = aperture priority, i.e. auto), while
  OpenCV's DirectShow and MSMF paths use 0.25 = manual, 0.75 = auto. ``CAP_PROP_EXPOSURE`` is in
  100 µs units on V4L2 and log2(seconds) on DirectShow/MSMF (-6 = 1/64 s).
* **Flushing.** A UVC stream keeps a queue of frames exposed before ``capture()`` was called
  (i.e. possibly before the pattern was on screen). ``capture`` discards ``flush_frames`` of
  them, or, on V4L2 where buffer timestamps are on the monotonic clock, stops as soon as a frame
  was started after the call.

Anything that makes the stream stop (unplugging, the driver failing) raises
``CameraDisconnected`` after ``fail_limit`` failed reads in a row.
"""

from __future__ import annotations

import glob
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np

from anklescan.core.errors import AnkleScanError
from anklescan.core.vocabulary import JsonObject
from anklescan.hardware.camera import Camera, CameraDisconnected, CameraInfo, Capabilities, Control, DeviceInfo

BACKEND = "opencv"
DEFAULT_API = cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY
AUTO_EXPOSURE = {cv2.CAP_V4L2: (1.0, 3.0), cv2.CAP_DSHOW: (0.25, 0.75), cv2.CAP_MSMF: (0.25, 0.75)}  # (manual, auto)
# Exposure ranges are not reported through OpenCV; these cover the usual driver ranges.
EXPOSURE_RANGE = {cv2.CAP_V4L2: (1.0, 10000.0, 1.0, "×100 µs"), cv2.CAP_DSHOW: (-13.0, 0.0, 1.0, "log2 s"),
                  cv2.CAP_MSMF: (-13.0, 0.0, 1.0, "log2 s")}
OTHER_CONTROLS = {  # name: (property, minimum, maximum, step, unit)
    "gain": (cv2.CAP_PROP_GAIN, 0.0, 255.0, 1.0, ""),
    "white_balance": (cv2.CAP_PROP_WB_TEMPERATURE, 2000.0, 10000.0, 10.0, "K"),
    "focus": (cv2.CAP_PROP_FOCUS, 0.0, 1023.0, 1.0, ""),
}
PREVIEW_WIDTH = 640
_CLOCK_SLACK_S = 10.0  # driver stamps further than this from time.monotonic() are not on its clock


def unavailable_reason() -> str:
    return ""  # OpenCV is a core dependency


class OpenCVCamera(Camera):
    """One ``cv2.VideoCapture`` source: a device index, a /dev/video path, a video file or an
    image sequence pattern (``frame_%03d.png``) — the last two make it testable without a camera.

    ``capture_factory`` (default ``cv2.VideoCapture``) is there for tests of driver behaviour
    a file cannot show (controls, refused settings).
    """

    def __init__(self, source: int | str = 0, *, api: int | None = None, size: tuple[int, int] | None = (1920, 1080),
                 flush_frames: int = 4, fail_limit: int = 5, name: str | None = None,
                 capture_factory: Callable[..., cv2.VideoCapture] = cv2.VideoCapture,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.source = source
        self.api = _api_for(source) if api is None else api
        self.requested_size = size
        self.flush_frames = int(flush_frames)
        self.fail_limit = max(1, int(fail_limit))
        self._factory, self._clock = capture_factory, clock
        self._name = name or _default_name(source)
        self._cap: cv2.VideoCapture | None = None
        self._size = (0, 0)
        self._notes: list[str] = []
        self._controls: dict[str, tuple[int, Control]] = {}
        self._stamps_monotonic = False
        self._last: JsonObject = {}

    # ---- lifecycle --------------------------------------------------------------------------
    @property
    def info(self) -> CameraInfo:
        return CameraInfo(self._name, BACKEND, *self._size)

    @property
    def is_open(self) -> bool:
        return self._cap is not None

    def open(self) -> None:
        if self._cap is not None:
            return
        cap = self._factory(self.source, self.api)
        if not cap.isOpened():
            cap.release()
            raise CameraDisconnected(f"{self._name}: cannot open {self.source!r} (unplugged, in use by "
                                     "another program, or no permission — see docs/hardware.md)")
        self._cap = cap
        self._negotiate_size()
        first = self._read_frame()
        self._size = (first.shape[1], first.shape[0])
        self._note_size_mismatch()
        self._stamps_monotonic = self._stamp_plausible()
        self._controls = self._probe_controls()

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _negotiate_size(self) -> None:
        if self.requested_size is None:
            return
        w, h = self.requested_size
        cap = self._device()
        # Set before streaming starts: V4L2 only changes mode while the stream is stopped.
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # fewer stale frames where the driver allows it

    def _note_size_mismatch(self) -> None:
        if self.requested_size and tuple(self.requested_size) != self._size:
            rw, rh = self.requested_size
            self._notes.append(f"asked for {rw}x{rh}, the device gives {self._size[0]}x{self._size[1]}")

    # ---- frames -----------------------------------------------------------------------------
    def capture(self) -> np.ndarray:
        t0 = self._clock()
        flushed = 0
        while True:
            self._grab()
            if flushed >= self.flush_frames or self._started_after(t0):
                break
            flushed += 1
        frame = self._retrieve()
        self._last = {"requested": t0, "returned": self._clock(), "flushed": flushed,
                      "driver_stamp_ms": self._cap_get(cv2.CAP_PROP_POS_MSEC)}
        return frame

    def preview(self) -> np.ndarray:
        img = self._read_frame()
        if img.shape[1] <= PREVIEW_WIDTH:
            return img
        h = round(img.shape[0] * PREVIEW_WIDTH / img.shape[1])
        return cv2.resize(img, (PREVIEW_WIDTH, h), interpolation=cv2.INTER_AREA)

    def frame_info(self) -> JsonObject:
        return dict(self._last)

    def _read_frame(self) -> np.ndarray:
        self._grab()
        return self._retrieve()

    def _device(self) -> cv2.VideoCapture:
        if self._cap is None:
            raise CameraDisconnected(f"{self._name} is not open")
        return self._cap

    def _grab(self) -> None:
        cap = self._device()
        # A single failed grab happens on a busy USB bus; several in a row mean the device is gone.
        for _ in range(self.fail_limit):
            if cap.grab():
                return
        self._lost()

    def _retrieve(self) -> np.ndarray:
        ok, frame = self._device().retrieve()
        if not ok or frame is None or frame.size == 0:
            self._lost()
        image: np.ndarray = frame
        return image

    def _lost(self) -> NoReturn:
        self.close()
        raise CameraDisconnected(f"{self._name} stopped delivering frames (unplugged or driver error)")

    def _started_after(self, t0: float) -> bool:
        return self._stamps_monotonic and self._cap_get(cv2.CAP_PROP_POS_MSEC) / 1000.0 >= t0

    def _stamp_plausible(self) -> bool:
        # V4L2 stamps buffers with CLOCK_MONOTONIC, which is time.monotonic() on Linux; a file's
        # "stamp" is its play position, which must not be mistaken for it.
        stamp = self._cap_get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        return self.api == cv2.CAP_V4L2 and stamp > 0 and abs(stamp - time.monotonic()) < _CLOCK_SLACK_S

    def _cap_get(self, prop: int) -> float:
        return float(self._cap.get(prop)) if self._cap is not None else -1.0

    # ---- controls ---------------------------------------------------------------------------
    def _probe_controls(self) -> dict[str, tuple[int, Control]]:
        found: dict[str, tuple[int, Control]] = {}
        cap = self._device()
        for name, (prop, lo, hi, step, unit) in self._control_table().items():
            value = cap.get(prop)
            # Writing back the current value is harmless and is the only portable support test.
            if value == -1 or not cap.set(prop, value):
                continue
            found[name] = (prop, Control(name, min(lo, value), max(hi, value), step, value, value, unit))
        return found

    def _control_table(self) -> dict[str, tuple[int, float, float, float, str]]:
        lo, hi, step, unit = EXPOSURE_RANGE.get(self.api, (-13.0, 10000.0, 1.0, ""))
        return {"exposure": (cv2.CAP_PROP_EXPOSURE, lo, hi, step, unit), **OTHER_CONTROLS}

    def controls(self) -> dict[str, Control]:
        return {name: c for name, (_, c) in self._controls.items()}

    def set_control(self, name: str, value: float) -> None:
        if name not in self._controls:
            raise KeyError(f"{self._name} has no adjustable {name!r}; available: {', '.join(self._controls) or 'none'}")
        prop, control = self._controls[name]
        value = control.check(value)
        if name == "exposure":
            self._set_auto(cv2.CAP_PROP_AUTO_EXPOSURE, manual=True)
        elif name == "focus":
            self._set_auto(cv2.CAP_PROP_AUTOFOCUS, manual=True)
        cap = self._device()
        if not cap.set(prop, value):
            raise AnkleScanError(f"{self._name} refused {name} = {value:g}")
        # Drivers round to what they support; remember what they actually took.
        self._controls[name] = (prop, replace(control, value=float(cap.get(prop))))

    def _set_auto(self, prop: int, manual: bool) -> bool:
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE:
            value = AUTO_EXPOSURE.get(self.api, (0.25, 0.75))[0 if manual else 1]
        else:
            value = 0.0 if manual else 1.0
        return bool(self._cap is not None and self._cap.set(prop, value))

    def lock_settings(self) -> dict[str, bool]:
        return {"exposure": self._set_auto(cv2.CAP_PROP_AUTO_EXPOSURE, manual=True),
                "focus": self._set_auto(cv2.CAP_PROP_AUTOFOCUS, manual=True),
                "white_balance": self._set_auto(cv2.CAP_PROP_AUTO_WB, manual=True)}

    def capabilities(self) -> Capabilities:
        w, h = self._size
        pw = min(w, PREVIEW_WIDTH)
        return Capabilities((w, h), (pw, round(h * pw / w)) if w else None, tuple(self._controls),
                            manual_exposure="exposure" in self._controls, focus_lock="focus" in self._controls,
                            white_balance_lock="white_balance" in self._controls, notes=tuple(self._notes))

    def metadata(self) -> JsonObject:
        meta = super().metadata()
        meta.update(source=str(self.source), api=_api_name(self.api), flush_frames=self.flush_frames,
                    requested_size=list(self.requested_size) if self.requested_size else None,
                    notes=list(self._notes))
        return meta


# ---- devices -------------------------------------------------------------------------------


def _api_for(source: int | str) -> int:
    if isinstance(source, str) and "%" in source:
        return cv2.CAP_IMAGES
    if isinstance(source, str) and not source.startswith("/dev/video"):
        return cv2.CAP_ANY  # a video file
    return DEFAULT_API


def _api_name(api: int) -> str:
    names = {cv2.CAP_V4L2: "V4L2", cv2.CAP_ANY: "default", cv2.CAP_IMAGES: "image sequence",
             cv2.CAP_DSHOW: "DirectShow", cv2.CAP_MSMF: "Media Foundation"}
    return names.get(api, str(api))


def _default_name(source: int | str) -> str:
    if isinstance(source, int):
        return f"USB camera {source}"
    return f"Video source {Path(str(source)).name}"


def list_devices(sys_root: str = "/sys/class/video4linux", probe: int = 4) -> list[DeviceInfo]:
    """V4L2 capture nodes on Linux (from sysfs, without opening them); elsewhere the first
    ``probe`` indices that open."""
    if sys.platform.startswith("linux") or os.path.isdir(sys_root):
        return _v4l2_devices(sys_root)
    return _probed_devices(probe)


def _v4l2_devices(sys_root: str) -> list[DeviceInfo]:
    out = []
    for node in sorted(glob.glob(os.path.join(sys_root, "video*")), key=_node_number):
        # uvcvideo makes two nodes per camera; index 0 is the one that streams images.
        if _read(os.path.join(node, "index"), "0") != "0":
            continue
        name = _read(os.path.join(node, "name"), os.path.basename(node))
        usb = _usb_id(node)
        dev = f"/dev/{os.path.basename(node)}"
        out.append(DeviceInfo(BACKEND, dev, f"{name} ({dev})", usb))
    return out


def _node_number(path: str) -> int:
    digits = "".join(ch for ch in os.path.basename(path) if ch.isdigit())
    return int(digits or 0)


def _usb_id(node: str) -> str:
    # sysfs: videoN/device is the USB interface; its parent holds idVendor/idProduct.
    for up in ("device", os.path.join("device", "..")):
        vid = _read(os.path.join(node, up, "idVendor"), "")
        pid = _read(os.path.join(node, up, "idProduct"), "")
        if vid and pid:
            return f"{vid}:{pid}"
    return ""


def _read(path: str, default: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return default


def _probed_devices(probe: int) -> list[DeviceInfo]:
    out = []
    for i in range(probe):
        cap = cv2.VideoCapture(i, DEFAULT_API)
        if cap.isOpened():
            out.append(DeviceInfo(BACKEND, str(i), f"USB camera {i}"))
        cap.release()
    return out


def open_device(device: str = "") -> OpenCVCamera:
    """A camera (not yet opened) for a device id from ``list_devices``: "/dev/video2", an index
    "2", or a video file / image sequence path."""
    if not device:
        found = list_devices()
        device = found[0].id if found else "0"
    if device.isdigit():
        return OpenCVCamera(int(device))
    if device.startswith("/dev/video") and device[len("/dev/video"):].isdigit():
        # An index, not the path: OpenCV's V4L2 backend accepts both, other builds only the index.
        return OpenCVCamera(int(device[len("/dev/video"):]), name=device)
    return OpenCVCamera(device)
