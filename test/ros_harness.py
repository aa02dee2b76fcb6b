"""The spin-and-wait helpers every in-process ROS test harness shares."""

import signal
import subprocess
import time

import rclpy


class SpinMixin:
    """
    close(), spin_until() and spin_for() for a harness with executor, node, driver, context.

    spin_timeout and spin_step (seconds) may be overridden per harness.
    """

    spin_timeout = 10.0
    spin_step = 0.05

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

    def spin_for(self, seconds):
        """Spin for `seconds` of wall time."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=self.spin_step)


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
