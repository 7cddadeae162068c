"""The application's logic, under the windows and free of Qt.

Widgets call these objects and observe them (``Event``); the objects hold the state a clinician
works with — the sessions database, the selected patient, session and trial, the accepted
calibration, the scan's trial — and decide what is written. Nothing here imports Qt (the layer
contract in pyproject.toml checks it), so the rules can be read and tested without a window.
"""
