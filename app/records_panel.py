"""The sidebar: patients, their sessions and a session's trials, and what a clinician does with
them (new patient, new session, exclude / restore a trial, archive). The rules and the writes
are app.logic.session's; this widget shows its state and asks the clinician."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDialog,
    QHBoxLayout,
    QInputDialog,
    QLabel,
    QListView,
    QListWidget,
    QListWidgetItem,
    QMessageBox,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from anklescan.app.main_parts import NewPatientDialog, deg, no_args
from anklescan.core.vocabulary import CONDITION_TITLES, Severity

if TYPE_CHECKING:
    from anklescan.app.logic.session import SessionLogic
    from anklescan.core.records.store import Store
    from anklescan.core.vocabulary import Session, Trial

ID = Qt.ItemDataRole.UserRole


class RecordsPanel(QWidget):
    trialChosen = Signal(int)        # one click on a trial opens it
    recordsChanged = Signal()        # a trial's state changed: plots and reports follow
    sessionShown = Signal(object)    # the selected session (or None)
    operatorChanged = Signal(str)

    def __init__(self, logic: SessionLogic, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.logic = logic
        self.patients, self.sessions, self.trials = QListWidget(), QListWidget(), QListWidget()
        for lst in (self.patients, self.sessions, self.trials):
            # a line too long for the narrow column wraps at a word: cut, "· simulated" or a trial's
            # "[excluded]" went out of sight behind a horizontal scroll bar
            lst.setWordWrap(True)
            lst.setResizeMode(QListView.ResizeMode.Adjust)
            lst.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.patients.currentItemChanged.connect(lambda *_: self.show_patient())
        self.sessions.currentItemChanged.connect(lambda *_: self.show_session())
        self.trials.currentItemChanged.connect(lambda item, _prev: self._trial_clicked(item))
        self.new_patient_button = QPushButton("New patient…")
        self.new_session_condition = QComboBox()
        for key, label in CONDITION_TITLES.items():
            self.new_session_condition.addItem(label, key)
        self.new_session_button = QPushButton("New session")
        self.show_archived = QCheckBox("Show archived")
        self.show_archived.toggled.connect(lambda _on: self.refresh_patients())
        self.exclude_button = QPushButton("Exclude trial…")
        self.restore_button = QPushButton("Restore trial")
        for button, slot in ((self.new_patient_button, self.new_patient), (self.new_session_button, self.new_session),
                             (self.exclude_button, self.exclude_trial), (self.restore_button, self.restore_trial)):
            button.clicked.connect(no_args(slot))
        self.new_patient_action = self._action("New &patient…", self.new_patient, "Ctrl+N")
        self.new_session_action = self._action("New &session", self.new_session, "Ctrl+Shift+N")
        self.operator_action = self._action("&Operator…", self.ask_operator)
        self.exclude_action = self._action("E&xclude trial…", self.exclude_trial)
        self.restore_action = self._action("Res&tore trial", self.restore_trial)
        self.archive_session_action = self._action("Archive session…", self.archive_session)
        self.archive_patient_action = self._action("Archive patient…", self.archive_patient)
        self._layout()
        logic.storeOpened.connect(self.apply_read_only)
        self.update_trial_buttons()

    def _action(self, text: str, slot: Callable[[], object], shortcut: str | None = None) -> QAction:
        a = QAction(text, self)
        if shortcut:
            a.setShortcut(QKeySequence(shortcut))
        a.triggered.connect(no_args(slot))  # ``triggered`` carries ``checked``: never let it reach a slot
        return a

    def _layout(self) -> None:
        v = QVBoxLayout(self)
        rows = {self.patients: (self.new_patient_button, 1, self.show_archived),
                self.sessions: (self.new_session_condition, 1, self.new_session_button),
                self.trials: (self.exclude_button, 0, self.restore_button)}
        for title, widget in (("Patients", self.patients), ("Sessions", self.sessions), ("Trials", self.trials)):
            label = QLabel(title)
            label.setObjectName("heading")
            v.addWidget(label)
            v.addWidget(widget, 2 if widget is self.trials else 1)
            first, stretch, second = rows[widget]
            row = QHBoxLayout()
            row.addWidget(first, stretch)
            row.addWidget(second)
            v.addLayout(row)
        self.setMinimumWidth(240)

    # ---- what is selected -------------------------------------------------------------
    def _current(self, widget: QListWidget, role: int = ID) -> Any:  # what the refresh stored: Qt's data is Any
        item = widget.currentItem()
        return item.data(role) if item else None

    def current_patient_id(self) -> int | None:
        out: int | None = self._current(self.patients)
        return out

    def current_code(self) -> str | None:
        out: str | None = self._current(self.patients, ID + 1)
        return out

    def current_session_id(self) -> int | None:
        out: int | None = self._current(self.sessions)
        return out

    def current_trial_id(self) -> int | None:
        out: int | None = self._current(self.trials)
        return out

    # ---- the lists --------------------------------------------------------------------
    def refresh_patients(self, select_code: str | None = None) -> None:
        current = select_code or self.current_code()
        self.patients.blockSignals(True)
        self.patients.clear()
        self.patients.blockSignals(False)
        for p in self.logic.patients(self.show_archived.isChecked()):
            history = ([f"{p.sprain_count} sprain(s)"] if p.sprain_count else []) + (
                [f"{p.affected_side} side" if p.affected_side != "both" else "both sides"] if p.affected_side else [])
            text = p.code + (f"   ·  {', '.join(history)}" if history else "")
            item = QListWidgetItem(text + ("   (archived)" if p.archived else ""))
            item.setData(ID, p.id)
            item.setData(ID + 1, p.code)
            self.patients.addItem(item)
            if p.code == current:
                self.patients.setCurrentItem(item)
        if self.patients.currentItem() is None:
            self.show_patient()

    def show_patient(self, select_session: int | None = None) -> None:
        self.sessions.clear()
        sessions = self.logic.sessions(self.current_patient_id(), self.show_archived.isChecked())
        labels = CONDITION_TITLES
        for s in sessions:
            item = QListWidgetItem(f"{s.date}  ·  {labels.get(s.condition, s.condition)}"
                                   + ("   (archived)" if s.archived else ""))
            item.setData(ID, s.id)
            self.sessions.addItem(item)
            if s.id == select_session:
                self.sessions.setCurrentItem(item)
        if select_session is None and sessions:
            self.sessions.setCurrentRow(len(sessions) - 1)
        if not sessions:
            self.show_session()

    def show_session(self, select_trial: int | None = None) -> None:
        self.trials.blockSignals(True)
        self.trials.clear()
        session = self.logic.session(self.current_session_id())
        for number, t in enumerate(self.logic.trials(self.current_session_id()), start=1):
            item = QListWidgetItem(f"Trial {number}   {deg(t.ref_inversion)} / {deg(t.ref_plantar_flexion)}"
                                   + ("   · simulated" if t.simulated else "")
                                   + ("" if t.counted else f"   [{t.state_text}]"))
            item.setToolTip(_trial_tip(t))
            if not t.counted:
                item.setForeground(Qt.GlobalColor.gray)
            item.setData(ID, t.id)
            self.trials.addItem(item)
            if t.id == select_trial:
                self.trials.setCurrentItem(item)
        self.trials.blockSignals(False)
        self.update_trial_buttons()
        self.sessionShown.emit(session)

    def select_trial_item(self, trial_id: int) -> None:
        """Keep the list's highlight on the trial the 3-D view shows."""
        for row in range(self.trials.count()):
            item = self.trials.item(row)
            if item.data(ID) == trial_id and self.trials.currentItem() is not item:
                self.trials.blockSignals(True)
                self.trials.setCurrentItem(item)
                self.trials.blockSignals(False)
                self.update_trial_buttons()

    def _trial_clicked(self, item: QListWidgetItem | None) -> None:
        self.update_trial_buttons()
        if item is not None:
            self.trialChosen.emit(item.data(ID))

    def update_trial_buttons(self) -> None:
        trial = self.logic.trial(self.current_trial_id())
        # Restore brings back an excluded trial, or keeps one flagged for moving during its scan
        for widgets, on in (((self.exclude_button, self.exclude_action), self.logic.can_exclude(trial)),
                            ((self.restore_button, self.restore_action), self.logic.can_restore(trial))):
            for w in widgets:
                w.setEnabled(on)

    def apply_read_only(self) -> None:
        """A read-only database (an archived study on a read-only share) is for review: every
        control that would write is disabled, with the reason as its tooltip."""
        ro = self.logic.read_only
        why = f"Read-only database: {self.logic.read_only_reason}" if ro else ""
        for w in (self.new_patient_button, self.new_session_button, self.new_patient_action, self.new_session_action,
                  self.archive_session_action, self.archive_patient_action):
            w.setEnabled(not ro)
            w.setToolTip(why)
        self.refresh_patients()
        self.update_trial_buttons()

    # ---- patients and sessions: the dialog-driven actions (slots take no data) ---------
    def new_patient(self) -> None:
        if not self.logic.require_store():
            return
        dialog = NewPatientDialog(self.window(), existing=self.logic.existing_patient)
        if dialog.exec() == QDialog.DialogCode.Accepted:
            self.add_patient(dialog.code.text(), dialog.sprains.value(), dialog.side.currentData(),
                             dialog.last_sprain_date())

    def add_patient(self, code: str, sprain_count: int = 0, side: str | None = None,
                    last_sprain: str | None = None) -> bool:
        patient = self.logic.add_patient(code, sprain_count, side, last_sprain)
        if patient is not None:
            self.refresh_patients(select_code=patient.code)
        return patient is not None

    def new_session(self) -> Session | None:
        """A session for the selected patient, in the condition chosen beside the button."""
        return self.start_session(self.new_session_condition.currentData())

    def start_session(self, condition: str) -> Session | None:
        if self.current_patient_id() is not None and not self.logic.operator:
            self.ask_operator()
        session = self.logic.start_session(self.current_patient_id(), condition)
        if session is not None:
            self.show_patient(select_session=session.id)
        return session

    def ask_operator(self) -> str:
        """Who measures: asked once, then remembered (File ▸ Operator… changes it)."""
        name, ok = QInputDialog.getText(self.window(), "Operator",
                                        "Your name or initials, for the records and reports:", text=self.logic.operator)
        if ok and name.strip():
            self.logic.set_operator(name)
            self.operatorChanged.emit(self.logic.operator)
        return self.logic.operator

    def exclude_trial(self) -> None:
        tid = self.current_trial_id()
        if tid is None or self.logic.store is None:
            self.logic.notice.emit(Severity.WARNING, "Select a trial first.")
            return
        # the trial as the list numbers it in its session, not its database id
        trial = self.logic.trial(tid)
        number = trial_number(self.logic.store, trial) if trial is not None else tid
        reason, ok = QInputDialog.getText(self.window(), "Exclude trial",
                                          f"Why is trial {number} left out of the statistics?")
        if ok and self.logic.exclude_trial(tid, reason):
            self._changed(tid)

    def restore_trial(self) -> None:
        tid = self.current_trial_id()
        if tid is not None and self.logic.store is not None and self.logic.restore_trial(tid):
            self._changed(tid)

    def _changed(self, tid: int) -> None:
        self.show_session(select_trial=tid)
        self.recordsChanged.emit()

    def archive_session(self) -> None:
        sid = self.current_session_id()
        if sid is None or self.logic.store is None:
            self.logic.notice.emit(Severity.WARNING, "Select a session first.")
        elif self._confirm("Archive session", "Archive this session? It leaves the working lists; "
                           "nothing is deleted and “Show archived” brings it back.") and self.logic.archive_session(sid):
            self.refresh_patients()

    def archive_patient(self) -> None:
        pid = self.current_patient_id()
        if pid is None or self.logic.store is None:
            self.logic.notice.emit(Severity.WARNING, "Select a patient first.")
        elif self._confirm("Archive patient", f"Archive patient {self.current_code()}? The patient leaves the "
                           "working lists; nothing is deleted and “Show archived” brings them back.") \
                and self.logic.archive_patient(pid):
            self.refresh_patients()

    def _confirm(self, title: str, text: str) -> bool:
        return confirm(self.window(), title, text)


def confirm(parent: QWidget | None, title: str, text: str) -> bool:
    answer = QMessageBox.question(parent, title, text, QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
                                  QMessageBox.StandardButton.No)
    return answer == QMessageBox.StandardButton.Yes


def trial_number(store: Store, trial: Trial) -> int:
    """The trial's number in its session (1, 2, ...), as the trials list shows it."""
    return sum(1 for t in store.trials.all(trial.session_id) if t.id <= trial.id)


def _trial_tip(t: Trial) -> str:
    moved = ("" if t.motion_mm is None else f"; moved {t.motion_mm:.1f} ± {t.motion_sd_mm or 0:.1f} mm"
             + (f" in a {t.scan_duration_s:.1f} s scan" if t.scan_duration_s else "")
             + (" (flagged, kept)" if t.motion_flagged and t.motion_keep else ""))
    return (f"Reference inversion / plantar flexion; {t.state_text}{moved}"
            + (f"; database trial {t.id}" if t.id else "")
            + ("; a simulated patient on the simulated rig" if t.simulated else "")
            + ("" if t.cloud_path else " (no point cloud)") + ". Click: open in 3-D")
