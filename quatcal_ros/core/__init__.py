"""
The mathematics of the calibration.

Quaternions, the paper's two-motion solver, least squares, refinement, uncertainty and the
Calibrator (numpy only).
"""
