"""The procedures that make and check a calibration: the paper's solution from known points, the
box and board, levelling to the tables' frame, verification, the daily check and the frame check
of a scan. Above ``anklescan.core.scan``, whose decoding and reconstruction they use."""
