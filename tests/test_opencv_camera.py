"""The OpenCV backend's real code path against sources cv2.VideoCapture opens without a camera:
an MJPG .avi written with cv2.VideoWriter and a 'frame_%03d.png' image sequence. Each frame's
grey level encodes its index (20 * i), so flushing can be checked frame by frame."""

import cv2
import numpy as np
import pytest

from anklescan.core.errors import AnkleScanError
from anklescan.hardware import camera as camera_mod
from anklescan.hardware import opencv_camera as oc
from anklescan.hardware.camera import CameraDisconnected

W, H, N = 64, 48, 12


def _index(frame) -> int:
    return round(float(np.mean(frame)) / 20)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "stream.avi"
    # MJPG in AVI is what opencv-python-headless writes through its bundled FFmpeg.
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (W, H), False)
    assert writer.isOpened()
    for i in range(N):
        writer.write(np.full((H, W), 20 * i, np.uint8))
    writer.release()
    return str(path)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seq")
    for i in range(5):
        cv2.imwrite(str(folder / f"frame_{i:03d}.png"), np.full((30, 40), 20 * i, np.uint8))
    return str(folder / "frame_%03d.png")


def test_resolution_is_what_the_source_gives_not_what_was_asked(video):
    cam = oc.OpenCVCamera(video, size=(1920, 1080))
    cam.open()
    assert (cam.info.width, cam.info.height) == (W, H)
    assert cam.capabilities().notes == ("asked for 1920x1080, the device gives 64x48",)
    assert cam.metadata()["requested_size"] == [1920, 1080]


def test_capture_flushes_buffered_frames(video):
    cam = oc.OpenCVCamera(video, flush_frames=2, size=None)
    cam.open()  # reads frame 0 to learn the size
    assert _index(cam.capture()) == 3  # frames 1 and 2 were queued before the call: dropped
    assert cam.frame_info()["flushed"] == 2
    assert _index(cam.capture()) == 6
    cam.flush_frames = 0
    assert _index(cam.capture()) == 7


def test_stream_end_is_a_disconnect(video):
    cam = oc.OpenCVCamera(video, flush_frames=0, size=None, fail_limit=3)
    cam.open()
    frames = [cam.capture() for _ in range(N - 1)]  # what was captured before the "unplug"
    assert [_index(f) for f in frames] == list(range(1, N))
    with pytest.raises(CameraDisconnected, match="stopped delivering frames"):
        cam.capture()
    assert not cam.is_open
    with pytest.raises(CameraDisconnected, match="not open"):
        cam.preview()


def test_image_sequence_and_preview(sequence):
    cam = oc.OpenCVCamera(sequence, flush_frames=0, size=None)
    assert cam.api == cv2.CAP_IMAGES
    cam.open()
    assert cam.preview().shape[:2] == (30, 40)
    assert _index(cam.capture()) == 2
    assert cam.controls() == {}  # a file has no exposure to set
    with pytest.raises(KeyError, match="no adjustable 'exposure'"):
        cam.set_control("exposure", 10)


def test_unopenable_source_is_a_clear_disconnect(tmp_path):
    cam = oc.OpenCVCamera(str(tmp_path / "nothing.avi"))
    with pytest.raises(CameraDisconnected, match="cannot open"):
        cam.open()


def test_registry_opens_a_file_source(video):
    cam = camera_mod.open_camera("opencv", video)
    assert cam.is_open and cam.info.backend == "opencv"
    cam.close()
    assert "opencv" in dict(camera_mod.available_backends())


class FakeDriver:
    """A V4L2-like driver for what a file cannot show: controls and their auto modes."""

    def __init__(self, source, api):
        self.props = {cv2.CAP_PROP_EXPOSURE: 156.0, cv2.CAP_PROP_GAIN: 0.0, cv2.CAP_PROP_AUTO_EXPOSURE: 3.0,
                      cv2.CAP_PROP_AUTOFOCUS: 1.0, cv2.CAP_PROP_AUTO_WB: 1.0, cv2.CAP_PROP_FRAME_WIDTH: 640,
                      cv2.CAP_PROP_FRAME_HEIGHT: 480}
        self.log = []

    def isOpened(self):
        return True

    def release(self):
        pass

    def get(self, prop):
        return self.props.get(prop, -1.0)

    def set(self, prop, value):
        self.log.append((prop, value))
        if prop not in self.props or prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return False
        self.props[prop] = round(value / 2) * 2.0 if prop == cv2.CAP_PROP_EXPOSURE else value  # driver rounds
        return True

    def grab(self):
        return True

    def retrieve(self):
        return True, np.zeros((480, 640, 3), np.uint8)


def test_manual_exposure_uses_the_v4l2_convention_and_reads_back():
    drivers = []
    cam = oc.OpenCVCamera(0, api=cv2.CAP_V4L2, capture_factory=lambda s, a: drivers.append(FakeDriver(s, a)) or drivers[-1])
    cam.open()
    drv = drivers[0]
    assert set(cam.controls()) == {"exposure", "gain"}  # the fake has no focus / WB temperature
    cam.set_control("exposure", 101)
    assert (cv2.CAP_PROP_AUTO_EXPOSURE, 1.0) in drv.log  # V4L2: 1 = manual (3 = auto)
    assert cam.controls()["exposure"].value == 100.0  # what the driver took, not what was asked
    with pytest.raises(AnkleScanError, match="outside"):
        cam.set_control("gain", 1000)
    assert cam.lock_settings() == {"exposure": True, "focus": True, "white_balance": True}
    assert drv.props[cv2.CAP_PROP_AUTOFOCUS] == 0.0 and drv.props[cv2.CAP_PROP_AUTO_WB] == 0.0


def test_lists_v4l2_capture_nodes_from_sysfs(tmp_path):
    root = tmp_path / "video4linux"
    for node, index, name in (("video0", "0", "C270 HD WEBCAM"), ("video1", "0", "C270 HD WEBCAM"),
                              ("video2", "0", "Integrated Camera")):
        d = root / node
        d.mkdir(parents=True)
        (d / "index").write_text(index if node != "video1" else "1")  # video1: metadata node
        (d / "name").write_text(name + "\n")
    usbdev = root / "video0" / "device"
    usbdev.mkdir()
    (usbdev / "idVendor").write_text("046d\n")
    (usbdev / "idProduct").write_text("0825\n")
    found = oc.list_devices(str(root))
    assert [d.id for d in found] == ["/dev/video0", "/dev/video2"]
    assert found[0].label == "C270 HD WEBCAM (/dev/video0)" and found[0].usb_id == "046d:0825"
