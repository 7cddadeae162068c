"""Latency self-test: a simulated camera whose frames lag the projector by a known delay, on a
fake clock (instant and deterministic), must give back that delay; plus the settle registry."""

import numpy as np
import pytest
from gui_actions import use_true_calibration

from anklescan.core.errors import AnkleScanError
from anklescan.hardware import sync
from anklescan.hardware.simrig import SimRig, simulated_devices


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class LaggedCamera:
    """Wraps a SimulatedCamera: each capture takes ``frame_s`` and photographs what the
    projector showed ``delay_s`` before the capture began (a camera + projector pipeline lag)."""

    def __init__(self, sim_camera, projector, clock, delay_s, frame_s):
        self.sim, self.projector, self.clock = sim_camera, projector, clock
        self.delay_s, self.frame_s = delay_s, frame_s
        self.history = [(-1e9, projector.image)]

    def show(self, bright: bool) -> float:
        w, h = self.projector.size
        self.history.append((self.clock(), np.full((h, w), 255 if bright else 0, np.uint8)))
        return self.clock()

    def capture(self):
        seen_at = self.clock() - self.delay_s
        image = [img for t, img in self.history if t <= seen_at][-1]
        self.projector.show(image)
        if self.frame_s:
            self.clock.t += self.frame_s
        return self.sim.capture()


@pytest.fixture(scope="module")
def sim():
    rig = SimRig(scale=0.1)
    camera, projector = simulated_devices(rig)
    camera.open()
    return camera, projector


@pytest.mark.parametrize("delay_ms,frame_ms", [(120, 10), (45, 5), (300, 33)])
def test_self_test_recovers_a_known_delay(sim, delay_ms, frame_ms):
    clock = FakeClock()
    cam = LaggedCamera(*sim, clock, delay_ms / 1000, frame_ms / 1000)
    result = sync.run_latency_test(cam, cam.show, toggles=6, hold_s=0.5, clock=clock)
    # The first capture that sees the change starts at most one frame after the true delay.
    assert delay_ms <= result.latency_s * 1000 <= delay_ms + frame_ms + 1e-6
    assert result.resolution_s == pytest.approx(frame_ms / 1000)
    assert result.settle_s >= result.latency_s + 0.02 - 1e-9
    assert len(result.latencies_s) == 6
    assert result.white_level - result.black_level > 20


def test_delay_longer_than_the_hold_is_reported(sim):
    clock = FakeClock()
    cam = LaggedCamera(*sim, clock, 0.8, 0.02)
    with pytest.raises(AnkleScanError, match="longer hold"):
        sync.run_latency_test(cam, cam.show, toggles=4, hold_s=0.3, clock=clock)


def test_camera_not_seeing_the_projector_is_reported():
    clock = FakeClock()

    class Dark:
        def capture(self):
            clock.t += 0.01
            return np.full((10, 10), 7, np.uint8)

    with pytest.raises(AnkleScanError, match="does not see the projector"):
        sync.run_latency_test(Dark(), lambda bright: clock(), toggles=4, hold_s=0.1, clock=clock)


def test_half_switched_frames_do_not_count():
    toggles = [sync.Toggle(1.0, True)]
    samples = [sync.Sample(0.5, 0.51, 10), sync.Sample(1.01, 1.02, 10), sync.Sample(1.05, 1.06, 120),
               sync.Sample(1.10, 1.11, 200), sync.Sample(1.2, 1.21, 200)]
    result = sync.analyse(toggles, samples)
    assert result.latency_s == pytest.approx(0.10)  # 1.05 is only part-way to white


def test_flicker_back_to_the_old_level_counts_from_the_last_change():
    toggles = [sync.Toggle(1.0, True)]
    samples = [sync.Sample(0.9, 0.91, 10), sync.Sample(1.0, 1.01, 200), sync.Sample(1.1, 1.11, 10),
               sync.Sample(1.2, 1.21, 200), sync.Sample(1.3, 1.31, 200)]
    assert sync.analyse(toggles, samples).latency_s == pytest.approx(0.2)


def test_real_clock_path_with_the_simulated_camera(sim):
    # The driver on the real clock, with a 60 ms lag; a loose upper bound: the machine is
    # shared. Below, the lag is read to within one step between capture calls (59.98 ms seen).
    import time
    cam = LaggedCamera(*sim, time.monotonic, 0.06, 0.0)
    result = sync.run_latency_test(cam, cam.show, toggles=2, hold_s=0.2, clock=time.monotonic)
    assert 0.06 - result.resolution_s <= result.latency_s < 0.15


def test_settle_registry_is_per_camera():
    class Cam:
        pass
    a, b = Cam(), Cam()
    sync.remember(a, sync.Settle(0.12, "self-test"))
    assert sync.settle_for(a, 0.03).seconds == 0.12
    assert sync.settle_for(b, 0.03) == sync.Settle(0.03, "settings")
    assert sync.settle_for(object(), 0.05).source == "settings"  # not weak-referenceable: still works


@pytest.mark.gui
def test_panel_self_test_sets_the_settle_time_the_scan_records(qtbot, tmp_path):
    """Through the main window: the panel's self-test on the real projector window and the
    simulated camera, then a scan whose manifest carries the measured settle time and timings."""
    import json

    from anklescan.app.main_window import MainWindow

    win = MainWindow(open_rig_now=True)
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    panel = win.camera_panel
    try:
        with qtbot.waitSignal(panel.settleChanged, timeout=20_000) as got:
            assert panel.run_latency_test(toggles=2, hold_s=0.15)
        measured = sync.settle_for(win.rig.camera, 0.5)
        assert measured.source == "self-test" and got.args[0] == pytest.approx(measured.seconds * 1000)
        assert panel.settle.value() == round(measured.seconds * 1000)
        assert "latency" in panel.latency_result.text()
        assert measured.seconds < 0.5  # the simulated camera sees a painted frame at once

        win.settings.operator = "tester"
        use_true_calibration(win)
        win.records.add_patient("P-002", 2, "right")
        win.records.start_session("barefoot")
        with qtbot.waitSignal(win.controller.busyChanged, timeout=120_000, check_params_cb=lambda b: b is False):
            assert win.scan_flow.start_scan()
        folder = win.last_result.folder
        capture = json.loads((folder / "manifest.json").read_text())["capture"]
        assert capture["settle_source"] == "self-test" and capture["backend"] == "simulated"
        assert "exposure" in capture["controls"] and "latency_test" in capture
        timing = capture["frames"]
        assert len(timing) == len(json.loads((folder / "manifest.json").read_text())["frames"])
        first = next(iter(timing.values()))
        assert first["capture_start_s"] - first["shown_s"] >= measured.seconds - 1e-3
    finally:
        win.close()
