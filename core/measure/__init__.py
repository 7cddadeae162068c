"""Measuring: the marks in a scan and the posture angles from them."""
