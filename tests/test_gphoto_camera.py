"""The gphoto2 backend at its library boundary: a fake ``gp`` module records every call and
hands back a JPEG; the backend's real code runs against it. Plus the real package, where
installed, listing no cameras on this machine."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from anklescan.core.errors import AnkleScanError
from anklescan.hardware import camera as camera_mod
from anklescan.hardware import gphoto_camera as gpc
from anklescan.hardware.camera import CameraDisconnected


class GPhoto2Error(Exception):
    def __init__(self, code):
        super().__init__(f"[{code}] fake gphoto2 error")
        self.code = code


class Widget:
    def __init__(self, value, choices):
        self.value, self.choices = value, list(choices)

    def count_choices(self):
        return len(self.choices)

    def get_choice(self, i):
        return self.choices[i]

    def get_value(self):
        return self.value

    def set_value(self, v):
        self.value = v


class Config:
    def __init__(self, widgets):
        self.widgets = widgets

    def get_child_by_name(self, name):
        if name not in self.widgets:
            raise GPhoto2Error(-2)
        return self.widgets[name]


def make_gp(jpeg: bytes, fail_capture_after=None):
    log = []
    widgets = {"iso": Widget("Auto", ["Auto", "100", "200", "400"]),
               "shutterspeed": Widget("1/60", ["1/30", "1/60", "1/125"]),
               "aperture": Widget("4", ["2.8", "4", "5.6", "8"]),
               "focusmode": Widget("AI Focus", ["One Shot", "AI Focus", "Manual"]),
               "imageformat": Widget("RAW", ["RAW", "Large Fine JPEG"])}

    class CameraFile:
        def __init__(self, data):
            self.data = data

        def get_data_and_size(self):
            return memoryview(self.data)

    class Camera:
        captures = 0

        @staticmethod
        def autodetect():
            found = [("Canon PowerShot A640", "usb:001,005")]
            return SimpleNamespace(count=lambda: len(found), get_name=lambda i: found[i][0],
                                   get_value=lambda i: found[i][1])

        def set_port_info(self, info):
            log.append(("set_port_info", info))

        def set_abilities(self, ab):
            log.append(("set_abilities", ab))

        def init(self):
            log.append(("init",))

        def exit(self):
            log.append(("exit",))

        def get_config(self):
            return Config(widgets)

        def set_config(self, config):
            log.append(("set_config", {k: w.value for k, w in config.widgets.items()}))

        def capture(self, kind):
            log.append(("capture", kind))
            if fail_capture_after is not None and Camera.captures >= fail_capture_after:
                raise GPhoto2Error(-52)  # GP_ERROR_IO_USB_FIND: the camera left the bus
            Camera.captures += 1
            return SimpleNamespace(folder="/store_00020001/DCIM/100CANON", name=f"IMG_{Camera.captures:04d}.JPG")

        def file_get(self, folder, name, kind):
            log.append(("file_get", folder, name, kind))
            return CameraFile(jpeg)

        def file_delete(self, folder, name):
            log.append(("file_delete", folder, name))

        def capture_preview(self):
            log.append(("capture_preview",))
            return CameraFile(jpeg)

    class PortInfoList:
        def load(self):
            pass

        def lookup_path(self, path):
            log.append(("lookup_path", path))
            return 0

        def __getitem__(self, i):
            return f"port#{i}"

    class CameraAbilitiesList(PortInfoList):
        def lookup_model(self, model):
            log.append(("lookup_model", model))
            return 0

    gp = SimpleNamespace(Camera=Camera, PortInfoList=PortInfoList, CameraAbilitiesList=CameraAbilitiesList,
                         GPhoto2Error=GPhoto2Error, GP_CAPTURE_IMAGE=0, GP_FILE_TYPE_NORMAL=1)
    return gp, log, widgets


@pytest.fixture
def jpeg():
    img = np.zeros((60, 80, 3), np.uint8)
    img[:, 40:] = (30, 160, 240)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def test_lists_and_opens_the_chosen_camera(jpeg):
    gp, log, widgets = make_gp(jpeg)
    (dev,) = gpc.list_devices(gp)
    assert dev.id == "Canon PowerShot A640@usb:001,005" and dev.backend == "gphoto2"
    cam = gpc.open_device(dev.id, gp=gp)
    cam.open()
    assert ("lookup_path", "usb:001,005") in log and ("lookup_model", "Canon PowerShot A640") in log
    assert ("init",) in log
    assert widgets["imageformat"].value == "Large Fine JPEG"  # RAW would not decode


def test_capture_to_memory_decodes_and_cleans_the_card(jpeg):
    gp, log, _ = make_gp(jpeg)
    cam = gpc.GPhotoCamera(gp=gp)
    cam.open()
    image = cam.capture()
    assert image.shape == (60, 80, 3) and abs(int(image[30, 70, 2]) - 240) < 8
    assert cam.info.width == 80 and cam.info.height == 60
    calls = [c[0] for c in log]
    assert calls[-3:] == ["capture", "file_get", "file_delete"]
    assert log[-2] == ("file_get", "/store_00020001/DCIM/100CANON", "IMG_0001.JPG", 1)
    assert cam.frame_info()["camera_file"].endswith("IMG_0001.JPG")


def test_iso_shutter_aperture_are_choice_controls(jpeg):
    gp, log, widgets = make_gp(jpeg)
    cam = gpc.GPhotoCamera(gp=gp)
    cam.open()
    controls = cam.controls()
    assert set(controls) >= {"iso", "shutter", "aperture", "focus_mode"}
    assert controls["shutter"].choices == ("1/30", "1/60", "1/125") and controls["shutter"].value == 1
    cam.set_control("iso", 2)
    assert widgets["iso"].value == "200" and cam.controls()["iso"].value == 2
    cam.set_choice("aperture", "8")
    assert widgets["aperture"].value == "8"
    with pytest.raises(AnkleScanError, match="choices"):
        cam.set_choice("aperture", "1.2")
    locked = cam.lock_settings()
    assert locked["focus_mode"] and widgets["focusmode"].value == "Manual"
    assert cam.metadata()["controls"]["iso"] == "200"


def test_camera_gone_mid_scan_raises_disconnected(jpeg):
    gp, log, _ = make_gp(jpeg, fail_capture_after=2)
    cam = gpc.GPhotoCamera(gp=gp)
    cam.open()
    cam.capture()
    cam.capture()
    with pytest.raises(CameraDisconnected, match="capture failed"):
        cam.capture()
    assert not cam.is_open
    with pytest.raises(CameraDisconnected, match="not open"):
        cam.capture()


def test_raw_files_give_a_clear_message():
    gp, _, _ = make_gp(b"\x49\x49\x2a\x00 not a jpeg")
    cam = gpc.GPhotoCamera(gp=gp)
    cam.open()
    with pytest.raises(AnkleScanError, match="set the camera to JPEG"):
        cam.capture()


def test_missing_package_degrades_with_a_clear_message(monkeypatch):
    monkeypatch.setattr(gpc, "import_gp", lambda: None)
    assert "pip install 'anklescan[cameras]'" in gpc.unavailable_reason()
    labels = dict(camera_mod.available_backends())
    assert "not installed" in labels["gphoto2"]
    with pytest.raises(AnkleScanError, match="gphoto2 package is not installed"):
        camera_mod.open_camera("gphoto2")
    assert camera_mod.list_devices("gphoto2") == []


def test_real_library_lists_no_camera_here():
    gp = pytest.importorskip("gphoto2")
    assert gpc.list_devices(gp) == []
