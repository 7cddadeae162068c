"""User-facing errors.

Every error a user can cause (bad files, bad geometry) is an ``AnkleScanError`` whose
``str()`` is one line that names the problem; the command line prints it and exits 2.
"""


class AnkleScanError(Exception):
    """A problem with the user's input, reported as one line."""


class CaptureError(AnkleScanError):
    """A capture folder or one of its frames is missing, unreadable or inconsistent."""


class CalibrationError(AnkleScanError):
    """A calibration file or control-point set is malformed or degenerate."""


class GeometryError(AnkleScanError):
    """Geometry that cannot be solved: singular, degenerate or coplanar input."""
