"""
SIGINT and SIGTERM from the first line on: the entry points of the package's nodes.

Importing rclpy and the messages takes about half a second; a stop signal in that time used
to end the process with a KeyboardInterrupt traceback (SIGINT) or by the signal (SIGTERM).
`guard` installs handlers that only note the signal, before anything heavy is imported;
spin.install_stop_handlers takes over the same list, and a signal noted early stops the node
as soon as rclpy is up, with exit status 0.  Standard library only.
"""

import importlib
import signal
import sys

from quatcal_ros.core.threads import single_threaded_blas

received = []   # the stop signals received so far, in order


def _note(signum, frame):
    received.append(signum)


def guard():
    """Note SIGINT and SIGTERM instead of dying of them (until spin's handlers take over)."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _note)


def run(module, args=None):
    """Guard, then import `module` (numpy's BLAS on one thread) and return its main(args)."""
    guard()
    single_threaded_blas()
    return importlib.import_module(module).main(args)


def calibrator():
    """Entry point of `ros2 run quatcal_ros calibrator`."""
    sys.exit(run('quatcal_ros.ros.node'))


def sim_cell():
    """Entry point of `ros2 run quatcal_ros sim_cell`."""
    sys.exit(run('quatcal_ros.ros.sim_cell'))


def target_detector():
    """Entry point of `ros2 run quatcal_ros target_detector`."""
    sys.exit(run('quatcal_ros.ros.target_detector'))
