"""The calibration as a model: what a calibration file holds and how each device maps rays and
pixels (the paper's 11- and 9-parameter models, the OpenCV form, the covariance of their
parameters). Below ``anklescan.core.scan``, which triangulates with it; imports nothing above."""
