"""The calibration report: an HTML page with inline SVG figures (matplotlib)."""
