"""Calibration: the camera and projector models, the box and the board, the calibration file, checks."""
