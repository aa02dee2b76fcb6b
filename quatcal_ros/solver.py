"""
The paper's method under its published name: `quatcal_ros.solver.solve_two_motions`.

This name is a contract (DESIGN.md, contract 1); the implementation lives in
`quatcal_ros.core.solver`.
"""

from quatcal_ros.core.solver import (  # noqa: F401 - re-exported names
    AngleMismatchError, DegenerateMotionError, NoRotationError, ParallelAxesError,
    solve_two_motions, TwoMotionSolution)
