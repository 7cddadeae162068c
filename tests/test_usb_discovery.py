"""USB discovery through the real pyusb code path (usb.core.find, Device, Configuration,
Interface, usb.util.get_string) against a fake pyusb backend presenting PTP and UVC devices."""

import array
import errno
from types import SimpleNamespace

import pytest
import usb.backend
import usb.core

from anklescan.hardware import usb_discovery as ud

IAD_CLASS = 0xEF  # "miscellaneous": what webcams report at device level; the class is per interface


def _string_descriptor(text: str) -> bytes:
    data = text.encode("utf-16-le")
    return bytes([2 + len(data), 3]) + data


class FakeDevice:
    def __init__(self, vid, pid, address, interfaces, *, device_class=0, strings=None, denied=False):
        self.vid, self.pid, self.address = vid, pid, address
        self.interfaces = interfaces  # list of interface classes
        self.device_class = device_class
        self.strings = strings or {}
        self.denied = denied


class FakeBackend(usb.backend.IBackend):
    """Implements the parts of pyusb's backend interface that enumeration and string reads use."""

    def __init__(self, devices):
        super().__init__()
        self.devices = list(devices)
        self.opened = []

    def enumerate_devices(self):
        return iter(self.devices)

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=dev.device_class, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=dev.vid, idProduct=dev.pid, bcdDevice=0x0100,
            iManufacturer=1 if dev.strings else 0, iProduct=2 if dev.strings else 0, iSerialNumber=0,
            bNumConfigurations=1, address=dev.address, bus=1, port_number=dev.address, port_numbers=(dev.address,),
            speed=3)

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=9, bNumInterfaces=len(dev.interfaces),
                               bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=50,
                               extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if alt != 0 or intf >= len(dev.interfaces):
            raise IndexError(intf)
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=intf, bAlternateSetting=0,
                               bNumEndpoints=0, bInterfaceClass=dev.interfaces[intf], bInterfaceSubClass=1,
                               bInterfaceProtocol=0, iInterface=0, extra_descriptors=[])

    def open_device(self, dev):
        if dev.denied:
            raise usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)
        self.opened.append(dev)
        return dev

    def close_device(self, dev_handle):
        pass

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        assert bRequest == 0x06 and wValue >> 8 == 3  # GET_DESCRIPTOR(STRING)
        index = wValue & 0xFF
        desc = bytes([4, 3, 0x09, 0x04]) if index == 0 else _string_descriptor(dev_handle.strings[index])
        n = min(len(desc), len(data))
        data[:n] = array.array("B", desc[:n])
        return n


CANON = FakeDevice(0x04A9, 0x3218, 5, [ud.PTP_CLASS], strings={1: "Canon Inc.", 2: "Canon PowerShot A640"})
WEBCAM = FakeDevice(0x046D, 0x0825, 6, [ud.VIDEO_CLASS, ud.VIDEO_CLASS, 1], device_class=IAD_CLASS,
                    strings={1: "Logitech", 2: "C270 HD WEBCAM"})
KEYBOARD = FakeDevice(0x413C, 0x2113, 7, [3], strings={1: "Dell", 2: "Keyboard"})
LOCKED_NIKON = FakeDevice(0x04B0, 0x0437, 8, [ud.PTP_CLASS], strings={1: "Nikon", 2: "D7100"}, denied=True)


def test_lists_ptp_and_uvc_with_names_and_backends():
    found = {c.usb_id: c for c in ud.discover(FakeBackend([CANON, WEBCAM, KEYBOARD]))}
    assert set(found) == {"04a9:3218", "046d:0825"}
    canon, cam = found["04a9:3218"], found["046d:0825"]
    assert (canon.name, canon.backend, canon.usb_class, canon.problem) == ("Canon Inc. Canon PowerShot A640", "gphoto2", 6, "")
    assert (cam.name, cam.backend, cam.usb_class) == ("Logitech C270 HD WEBCAM", "opencv", 14)
    assert "still camera (PTP)" in canon.describe()


def test_no_permission_is_listed_with_the_udev_hint():
    (nikon,) = ud.discover(FakeBackend([LOCKED_NIKON]))
    assert nikon.name == "Nikon device"  # from the maker table: the strings could not be read
    assert nikon.problem == "no permission to USB device 04b0:0437 — see docs/hardware.md for the udev rule"


def test_watcher_reports_plug_and_unplug():
    backend = FakeBackend([WEBCAM])
    watcher = ud.UsbWatcher(backend)
    first = watcher.poll()
    assert [c.usb_id for c in first.added] == ["046d:0825"] and not first.removed
    assert not watcher.poll()  # nothing changed
    backend.devices = [CANON, LOCKED_NIKON]
    change = watcher.poll()
    assert {c.usb_id for c in change.added} == {"04a9:3218", "04b0:0437"}
    assert [c.usb_id for c in change.removed] == ["046d:0825"]
    assert "Disconnected: Logitech C270 HD WEBCAM" in change.message()
    assert watcher.problems == [LOCKED_NIKON_MESSAGE]


LOCKED_NIKON_MESSAGE = "no permission to USB device 04b0:0437 — see docs/hardware.md for the udev rule"


def test_missing_libusb_disables_discovery_with_a_reason(monkeypatch):
    def no_backend(*a, **k):
        raise usb.core.NoBackendError("No backend available")
    monkeypatch.setattr(usb.core, "find", no_backend)
    watcher = ud.UsbWatcher()
    assert not watcher.poll()
    assert "libusb" in watcher.unavailable


@pytest.mark.gui
def test_panel_shows_plug_unplug_and_the_permission_message(qtbot):
    from anklescan.app.camera_panel import CameraPanel

    panel = CameraPanel([("simulated", "Simulated rig")])
    qtbot.addWidget(panel)
    backend = FakeBackend([WEBCAM])
    panel.start_usb_watch(ud.UsbWatcher(backend))
    assert "Connected: Logitech C270 HD WEBCAM" in panel.usb_status.text()
    backend.devices = [LOCKED_NIKON]
    panel.poll_usb()
    assert panel.usb_status.text() == LOCKED_NIKON_MESSAGE
    panel._usb_timer.stop()
