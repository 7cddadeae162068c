"""GUI test setup: a real X server (pytest-xvfb) at 24-bit colour, Qt on xcb, settings isolated.

Only GUI tests (those requesting ``qapp``/``qtbot``) switch Qt to xcb; other tests never create a
QApplication. 24-bit depth matters: at pytest-xvfb's default 16 bits a grey level of 1 cannot
survive a screen grab, and the projector test compares the screen with the pattern bit for bit.
"""

import os

import pytest


@pytest.fixture(scope="session")
def qapp_args():
    os.environ["QT_QPA_PLATFORM"] = "xcb"  # offscreen has no OpenGL and no real screen to grab
    return ["anklescan-tests"]


@pytest.fixture(autouse=True)
def _isolated_settings(request, tmp_path, monkeypatch):
    if request.node.get_closest_marker("gui"):
        # a quarter-scale simulated rig keeps GUI scans fast; the app's default (0.75) is what
        # automatic marks need, and is covered by the demo's test
        (tmp_path / "settings.ini").write_text("[scan]\nsim_scale=0.25\n")
        monkeypatch.setenv("ANKLESCAN_SETTINGS", str(tmp_path / "settings.ini"))
        monkeypatch.setenv("ANKLESCAN_DATA", str(tmp_path / "data"))
