"""The app shows a measurement's warnings beside the marks they name, and the honest ± (SPEC §3, §6)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_uncertainty as bench  # noqa: E402
from gui_actions import calibrated_window  # noqa: E402

from anklescan.app.mark_editor import STATUS_COLUMN  # noqa: E402
from anklescan.core.measure.angles import compute_angles  # noqa: E402
from anklescan.core.measure.measure_warnings import WarningContext, measure_warnings  # noqa: E402
from anklescan.core.measure.uncertainty import position_uncertainty  # noqa: E402

pytestmark = pytest.mark.gui


def test_marks_page_shows_the_volume_warning_and_the_honest_sd(qtbot) -> None:
    win = calibrated_window(qtbot)
    win.records.add_patient("P-037", 0, None)
    win.records.start_session("barefoot")
    cal = bench.noisy_calibration(bench.true_rig(), bench.box_points((0.0,)), 0.2, np.random.default_rng(1))
    marks = bench.true_marks((5.0, -5.0))
    joint, _ = position_uncertainty(cal, marks, {k: np.eye(3) * 0.01 for k in marks})
    warnings = measure_warnings(WarningContext(marks, cal))
    editor = win.marks_page.editor
    # what the scan flow hands the editor when a measurement finishes (app/scan_flow.py)
    editor.propose_auto({k: tuple(v) for k, v in marks.items()}, warnings=warnings, covariance=joint)
    status = {lab: editor.list.item(lab - 1, STATUS_COLUMN).text() for lab in range(1, 8)}
    assert "mm above vol." in status[1] and "mm above vol." in status[3]
    assert "knee's height" in editor.list.item(2, STATUS_COLUMN).toolTip()
    assert all("outside" not in status[lab] for lab in (2, 4, 5, 6, 7))
    assert "mark 1 lies" in editor.list.item(0, STATUS_COLUMN).toolTip()
    want = compute_angles(marks, 0.0, joint=joint)["leg_plantar_flexion"]
    assert editor.angle_labels["leg_plantar_flexion"].text() == f"{want.value:+.2f}° ± {want.sd:.2f}°"
    # a person selects the knee mark's row: the warning is still beside it
    QTest.mouseClick(editor.list.viewport(), Qt.MouseButton.LeftButton,
                     pos=editor.list.visualItemRect(editor.list.item(2, STATUS_COLUMN)).center())
    assert editor.current_label == 3 and "above vol." in editor.list.item(2, STATUS_COLUMN).text()
    win.close()
