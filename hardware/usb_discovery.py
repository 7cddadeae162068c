"""Which cameras are plugged in: USB still-image (PTP, interface class 6) and video (UVC,
class 14) devices, each matched to the backend that drives it (PTP -> gphoto2, UVC -> opencv).

Descriptors are read without opening the device (libusb takes them from sysfs on Linux), so a
camera shows up even when the user may not talk to it; the names need the device opened, and
that is where a missing udev rule shows as errno 13. Such a device is still listed, named from
a short table of makers, with ``problem`` saying what to do.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from dataclasses import dataclass

import usb.core
import usb.util

PTP_CLASS = 6
VIDEO_CLASS = 14
BACKEND_FOR_CLASS = {PTP_CLASS: "gphoto2", VIDEO_CLASS: "opencv"}
KIND_FOR_CLASS = {PTP_CLASS: "still camera (PTP)", VIDEO_CLASS: "video camera (UVC)"}
VENDORS = {0x04A9: "Canon", 0x04B0: "Nikon", 0x054C: "Sony", 0x04CB: "Fujifilm", 0x07B4: "Olympus",
           0x04DA: "Panasonic", 0x0A17: "Pentax", 0x046D: "Logitech", 0x045E: "Microsoft",
           0x32E4: "ELP", 0x0C45: "Microdia", 0x1E4E: "Cubeternet", 0x2BDF: "Hikvision"}
PERMISSION_HINT = "see docs/hardware.md for the udev rule"


@dataclass(frozen=True)
class UsbCamera:
    vid: int
    pid: int
    bus: int | None
    address: int | None
    usb_class: int  # PTP_CLASS or VIDEO_CLASS
    name: str
    problem: str = ""  # e.g. no permission; "" when the device could be read

    @property
    def usb_id(self) -> str:
        return f"{self.vid:04x}:{self.pid:04x}"

    @property
    def backend(self) -> str:
        return BACKEND_FOR_CLASS[self.usb_class]

    @property
    def kind(self) -> str:
        return KIND_FOR_CLASS[self.usb_class]

    @property
    def key(self) -> tuple[int, int, int | None, int | None]:
        """Identity across polls: the same device on the same port (names may fail to read)."""
        return (self.vid, self.pid, self.bus, self.address)

    def describe(self) -> str:
        return f"{self.name} [{self.usb_id}] — {self.kind}"


class UsbUnavailable(Exception):
    """No libusb on this computer: discovery cannot run (the cameras may still work)."""


def camera_class(dev: usb.core.Device) -> int | None:
    """PTP or UVC when the device or one of its interfaces has that class, else None."""
    if dev.bDeviceClass in BACKEND_FOR_CLASS:
        return int(dev.bDeviceClass)
    try:
        classes = {intf.bInterfaceClass for cfg in dev for intf in cfg}
    except usb.core.USBError:
        return None
    # A webcam with a microphone has both video and audio; PTP wins over video for the odd
    # still camera that also offers a webcam mode, as gphoto2 gives it full-resolution stills.
    for cls in (PTP_CLASS, VIDEO_CLASS):
        if cls in classes:
            return cls
    return None


def describe_device(dev: usb.core.Device, usb_class: int) -> UsbCamera:
    name, problem = _read_name(dev)
    return UsbCamera(int(dev.idVendor), int(dev.idProduct), dev.bus, dev.address, usb_class, name, problem)


def _read_name(dev: usb.core.Device) -> tuple[str, str]:
    fallback = f"{VENDORS.get(int(dev.idVendor), 'Unknown maker')} device"
    try:
        # get_langids, unlike Device.langids, lets the USBError (errno 13) through.
        langids = usb.util.get_langids(dev)
        if not langids:
            return fallback, ""
        parts = [usb.util.get_string(dev, i, langids[0]) for i in (dev.iManufacturer, dev.iProduct) if i]
    except usb.core.USBError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM):
            return fallback, f"no permission to USB device {dev.idVendor:04x}:{dev.idProduct:04x} — {PERMISSION_HINT}"
        return fallback, f"USB device {dev.idVendor:04x}:{dev.idProduct:04x} did not answer ({exc})"
    finally:
        usb.util.dispose_resources(dev)  # do not keep the camera open: gphoto2/V4L2 need it
    name = " ".join(p.strip() for p in parts if p and p.strip())
    return name or fallback, ""


def discover(backend: object | None = None) -> list[UsbCamera]:
    """Every PTP and UVC device; ``backend`` is a pyusb backend (tests pass a fake one)."""
    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError:
        raise UsbUnavailable("USB discovery needs libusb-1.0, which is not installed") from None
    found = []
    for dev in devices:
        cls = camera_class(dev)
        if cls is not None:
            found.append(describe_device(dev, cls))
    return found


@dataclass(frozen=True)
class Change:
    added: tuple[UsbCamera, ...]
    removed: tuple[UsbCamera, ...]

    def __bool__(self) -> bool:
        return bool(self.added or self.removed)

    def message(self) -> str:
        parts = [f"Connected: {c.describe()}" for c in self.added]
        parts += [f"Disconnected: {c.describe()}" for c in self.removed]
        return "; ".join(parts)


class UsbWatcher:
    """Polled by the GUI (every 2 s): compares the set of cameras with the previous poll."""

    def __init__(self, backend: object | None = None,
                 discover_fn: Callable[[object | None], list[UsbCamera]] = discover) -> None:
        self._backend, self._discover = backend, discover_fn
        self.cameras: dict[tuple[int, int, int | None, int | None], UsbCamera] = {}
        self.unavailable = ""

    def poll(self) -> Change:
        if self.unavailable:
            return Change((), ())
        try:
            now = {c.key: c for c in self._discover(self._backend)}
        except UsbUnavailable as exc:
            self.unavailable = str(exc)  # stop asking: libusb will not appear while we run
            return Change((), ())
        added = tuple(c for k, c in now.items() if k not in self.cameras)
        removed = tuple(c for k, c in self.cameras.items() if k not in now)
        self.cameras = now
        return Change(added, removed)

    @property
    def problems(self) -> list[str]:
        return [c.problem for c in self.cameras.values() if c.problem]
