"""
The command-line tools (python -m quatcal_ros TOOL).

Solve, replay and demo.
"""
