"""Camera images in: calibration targets, their detection and pose, pixel-level refinement."""
