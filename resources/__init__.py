"""Package data shipped with anklescan: the window icon and the printable calibration box
(calibration_box.json / .svg, see anklescan.core.calibration.procedures.box). Read through
``importlib.resources.files("anklescan.resources")`` so installed and editable copies alike find it."""
