"""The spin-and-wait helpers every in-process ROS test harness shares."""

from contextlib import contextmanager
import signal
import subprocess
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import QuaternionStamped
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy

# The QoS of the calibrator's ~/rotation and ~/transform.
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def harnesses_of(harness_class, domain_id):
    """Yield a function that makes harnesses on `domain_id`; close them all afterwards."""
    made = []

    def make(*args, **kwargs):
        made.append(harness_class(domain_id, *args, **kwargs))
        return made[-1]
    yield make
    for harness in made:
        harness.close()


class SpinMixin:
    """
    close(), spin_until() and spin_for() for a harness with executor, node, driver, context.

    spin_timeout and spin_step (seconds) may be overridden per harness.
    """

    spin_timeout = 10.0
    spin_step = 0.05

    def watch_outputs(self):
        """Collect the calibrator's ~/rotation in `rotations`, /diagnostics in `diagnostics`."""
        self.rotations = []
        self.diagnostics = []
        self.driver.create_subscription(QuaternionStamped, '/calibrator/rotation',
                                        self.rotations.append, LATCHED)
        self.driver.create_subscription(DiagnosticArray, '/diagnostics',
                                        self.diagnostics.append, 10)

    def close(self):
        """Stop spinning, destroy both nodes and shut the private context down."""
        self.executor.shutdown()
        self.driver.destroy_node()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def spin_until(self, condition, timeout=None, what='condition'):
        """Spin until condition() holds; fail naming `what` after `timeout` seconds."""
        timeout = self.spin_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=self.spin_step)

    def next_status(self, condition=lambda status: True):
        """Return the next calibrator status on /diagnostics satisfying `condition`."""
        self.diagnostics.clear()
        found = []

        def seen():
            found.extend(s for a in self.diagnostics for s in a.status
                         if s.name == DIAGNOSTIC_NAME and condition(s))
            self.diagnostics.clear()
            return found
        self.spin_until(seen, what='a matching /diagnostics status')
        return found[-1]

    def spin_for(self, seconds):
        """Spin for `seconds` of wall time."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=self.spin_step)


class ProcessWatcher:
    """
    A node of its own (private context on `domain_id`) that watches calibrator processes.

    It collects /calibrator/rotation messages in `rotations` and the calibrator's
    /diagnostics statuses in `statuses`; subclasses add publishers and subscriptions to
    `self.node` after calling this constructor.
    """

    def __init__(self, name, domain_id):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.rotations, self.statuses = [], []
        self.node.create_subscription(QuaternionStamped, '/calibrator/rotation',
                                      self.rotations.append, LATCHED)
        self.node.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda msg: self.statuses.extend(s for s in msg.status if s.name == DIAGNOSTIC_NAME),
            10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, condition, timeout, what, processes=()):
        """Spin until condition() holds; fail when a process exits or after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not condition():
            for process in processes:
                assert process.poll() is None, f'{process.args} exited with {process.returncode}'
            assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        """Stop spinning, destroy the node and shut the private context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def stop_process(process, sig=signal.SIGINT, timeout=15.0):
    """Send `sig`, then wait; return the exit status (None when it had to be killed)."""
    if process.poll() is None:
        process.send_signal(sig)
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        return None


@contextmanager
def logged_warnings(node):
    """Collect the texts `node` logs as warnings (warn or warning) inside the block."""
    warned, logger = [], node.get_logger()

    class Recording:
        def __getattr__(self, name):
            return getattr(logger, name)

        def warning(self, text, **options):
            warned.append(text)
            return logger.warning(text, **options)
        warn = warning
    node.get_logger = Recording
    try:
        yield warned
    finally:
        del node.get_logger
