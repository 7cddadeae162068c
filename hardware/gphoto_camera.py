"""Tethered still cameras (Canon PowerShot/EOS, Nikon, Sony ...) through libgphoto2.

The ``gphoto2`` Python package ships libgphoto2 in its wheels and is an optional dependency
(``pip install 'anklescan[cameras]'``); without it this backend lists no devices and says why.
Every call into the library goes through the module object ``gp`` handed to the camera, so the
tests can hand it a fake that records calls and returns a JPEG.

Captures go to memory: ``capture(GP_CAPTURE_IMAGE)`` then ``file_get`` into a CameraFile, then
``cv2.imdecode``; the file is deleted from the camera afterwards so a scan of ~30 frames does
not fill the card. The camera must shoot JPEG (RAW files do not decode), which ``open`` asks for
where the camera has an ``imageformat`` setting.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, TypeAlias

import cv2
import numpy as np

from anklescan.core.errors import AnkleScanError
from anklescan.core.vocabulary import JsonObject
from anklescan.hardware.camera import Camera, CameraDisconnected, CameraInfo, Capabilities, Control, DeviceInfo

BACKEND = "gphoto2"
MISSING = "the gphoto2 package is not installed (pip install 'anklescan[cameras]')"
# Our control name -> the config names different makers use for it, in order of preference.
CONFIG_NAMES = {
    "iso": ("iso", "isospeed"),
    "shutter": ("shutterspeed", "shutterspeed2", "exposuretime"),
    "aperture": ("aperture", "f-number", "fnumber"),
    "white_balance": ("whitebalance",),
    "focus_mode": ("focusmode", "focusmode2"),
    "exposure_mode": ("autoexposuremode", "expprogram", "exposureprogram"),
}
LOCKED = {"focus_mode": ("Manual", "MF", "Manual Focus"),
          "exposure_mode": ("Manual", "M"),
          "white_balance": ("Daylight", "Fine Weather", "Sunlight")}
JPEG_FORMATS = ("Large Fine JPEG", "JPEG Fine", "Large Normal JPEG", "JPEG Normal", "JPEG")

# python-gphoto2 has no type stubs: its module (or a test's stand-in), camera and config widgets are Any
GPhoto2: TypeAlias = Any
GpObject: TypeAlias = Any


def import_gp() -> GPhoto2 | None:
    try:
        import gphoto2
    except ImportError:
        return None
    return gphoto2


def unavailable_reason(gp: GPhoto2 | None = None) -> str:
    return "" if (gp or import_gp()) is not None else MISSING


def _require(gp: GPhoto2 | None) -> GPhoto2:
    gp = gp or import_gp()
    if gp is None:
        raise AnkleScanError(f"tethered still cameras: {MISSING}")
    return gp


def list_devices(gp: GPhoto2 | None = None) -> list[DeviceInfo]:
    gp = _require(gp)
    try:
        cameras = gp.Camera.autodetect()
        found = [(cameras.get_name(i), cameras.get_value(i)) for i in range(cameras.count())]
    except gp.GPhoto2Error as exc:
        raise AnkleScanError(f"gphoto2 could not list cameras: {exc}") from None
    return [DeviceInfo(BACKEND, f"{model}@{port}", f"{model} ({port})") for model, port in found]


def open_device(device: str = "", gp: GPhoto2 | None = None) -> GPhotoCamera:
    model, _, port = device.rpartition("@") if "@" in device else ("", "", "")
    return GPhotoCamera(model, port, gp=gp)


class GPhotoCamera(Camera):
    """A libgphoto2 camera; ``model``/``port`` as ``Camera.autodetect`` reports them ("" = the
    first camera found). Controls are the camera's named settings (choices, value = index)."""

    def __init__(self, model: str = "", port: str = "", *, gp: GPhoto2 | None = None,
                 delete_after_download: bool = True) -> None:
        self.gp = _require(gp)
        self.model, self.port = model, port
        self.delete_after_download = delete_after_download
        self._cam: GpObject | None = None
        self._size = (0, 0)  # known after the first capture: the camera does not say beforehand
        self._config_names: dict[str, str] = {}
        self._controls: dict[str, Control] = {}
        self._last: JsonObject = {}

    @property
    def _name(self) -> str:
        return self.model or "Tethered camera"

    @property
    def info(self) -> CameraInfo:
        return CameraInfo(self._name, BACKEND, *self._size)

    @property
    def is_open(self) -> bool:
        return self._cam is not None

    # ---- lifecycle --------------------------------------------------------------------------
    def open(self) -> None:
        if self._cam is not None:
            return
        gp = self.gp
        cam = gp.Camera()
        try:
            self._select(cam)
            cam.init()
        except gp.GPhoto2Error as exc:
            raise CameraDisconnected(f"{self._name}: cannot open ({exc}). Is it on, in PTP/PC mode, and not "
                                     "mounted by the file manager? See docs/hardware.md") from None
        self._cam = cam
        self._read_config()
        self._prefer_jpeg()

    def _select(self, cam: GpObject) -> None:
        gp = self.gp
        if self.port:
            ports = gp.PortInfoList()
            ports.load()
            cam.set_port_info(ports[ports.lookup_path(self.port)])
        if self.model:
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            cam.set_abilities(abilities[abilities.lookup_model(self.model)])

    def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                cam.exit()
            except self.gp.GPhoto2Error:
                pass  # already gone: closing must not fail

    # ---- frames -----------------------------------------------------------------------------
    def capture(self) -> np.ndarray:
        cam, gp = self._opened(), self.gp
        try:
            path = cam.capture(gp.GP_CAPTURE_IMAGE)
            data = cam.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL).get_data_and_size()
            if self.delete_after_download:
                cam.file_delete(path.folder, path.name)
        except gp.GPhoto2Error as exc:
            self._drop()
            raise CameraDisconnected(f"{self._name}: capture failed ({exc})") from None
        image = _decode(data, f"{path.folder}/{path.name}")
        self._size = (image.shape[1], image.shape[0])
        self._last = {"camera_file": f"{path.folder}/{path.name}", "bytes": len(memoryview(data))}
        return image

    def preview(self) -> np.ndarray:
        cam, gp = self._opened(), self.gp
        try:
            data = cam.capture_preview().get_data_and_size()
        except gp.GPhoto2Error as exc:
            raise AnkleScanError(f"{self._name} gives no live view ({exc}); use Test capture") from None
        return _decode(data, "live view")

    def frame_info(self) -> JsonObject:
        return dict(self._last)

    def _opened(self) -> GpObject:
        if self._cam is None:
            raise CameraDisconnected(f"{self._name} is not open")
        return self._cam

    def _drop(self) -> None:
        # After a failed transfer the session is unusable; forget it so reopening starts clean.
        try:
            self.close()
        except Exception:
            self._cam = None

    # ---- configuration ----------------------------------------------------------------------
    def _read_config(self) -> None:
        config = self._opened().get_config()
        self._config_names.clear()
        self._controls.clear()
        for ours, names in CONFIG_NAMES.items():
            widget, found = _child(config, names, self.gp)
            if widget is None:
                continue
            choices = tuple(widget.get_choice(i) for i in range(widget.count_choices()))
            if not choices:
                continue
            value = widget.get_value()
            index = choices.index(value) if value in choices else 0
            self._config_names[ours] = found
            self._controls[ours] = Control(ours, 0, len(choices) - 1, 1, index, index, "", choices)

    def _prefer_jpeg(self) -> None:
        try:
            cam = self._opened()
            config = cam.get_config()
            widget, _ = _child(config, ("imageformat", "imagequality"), self.gp)
            if widget is None:
                return
            choices = [widget.get_choice(i) for i in range(widget.count_choices())]
            jpeg = next((c for c in JPEG_FORMATS if c in choices), None)
            if jpeg and widget.get_value() != jpeg:
                widget.set_value(jpeg)
                cam.set_config(config)
        except self.gp.GPhoto2Error:
            pass  # the first capture says so clearly if the camera still shoots RAW

    def controls(self) -> dict[str, Control]:
        return dict(self._controls)

    def set_control(self, name: str, value: float) -> None:
        if name not in self._controls:
            raise KeyError(f"{self._name} has no {name!r} setting; available: {', '.join(self._controls) or 'none'}")
        control = self._controls[name]
        index = int(round(control.check(value)))
        self.set_choice(name, control.choices[index])

    def set_choice(self, name: str, choice: str) -> None:
        """Set a named setting by its text ("400", "1/60", "f/8")."""
        control, gp = self._controls[name], self.gp
        if choice not in control.choices:
            raise AnkleScanError(f"{self._name}: {name} cannot be {choice!r}; choices: {', '.join(control.choices)}")
        cam = self._opened()
        try:
            config = cam.get_config()
            config.get_child_by_name(self._config_names[name]).set_value(choice)
            cam.set_config(config)
        except gp.GPhoto2Error as exc:
            raise AnkleScanError(f"{self._name} refused {name} = {choice} ({exc})") from None
        index = control.choices.index(choice)
        self._controls[name] = replace(control, value=index)

    def lock_settings(self) -> dict[str, bool]:
        done: dict[str, bool] = {}
        for name, wanted in LOCKED.items():
            control = self._controls.get(name)
            choice = next((c for c in wanted if control and c in control.choices), None)
            if choice is None:
                done[name] = False
                continue
            try:
                self.set_choice(name, choice)
                done[name] = True
            except AnkleScanError:
                done[name] = False
        return done

    def capabilities(self) -> Capabilities:
        names = tuple(self._controls)
        return Capabilities(self._size, None, names, manual_exposure="shutter" in names,
                            focus_lock="focus_mode" in names, white_balance_lock="white_balance" in names)

    def metadata(self) -> JsonObject:
        meta = super().metadata()
        meta.update(model=self.model, port=self.port, config_names=dict(self._config_names))
        return meta


def _child(config: GpObject, names: tuple[str, ...], gp: GPhoto2) -> tuple[GpObject | None, str]:
    for name in names:
        try:
            return config.get_child_by_name(name), name
        except gp.GPhoto2Error:
            continue
    return None, ""


def _decode(data: GpObject, what: str) -> np.ndarray:
    buf = np.frombuffer(memoryview(data), np.uint8)
    image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if image is None:
        raise AnkleScanError(f"{what} is not an image OpenCV can read: set the camera to JPEG, not RAW")
    return image
