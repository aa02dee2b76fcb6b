"""
The calibrator process under a long stream, and the node that feeds it: test_soak's harness.

bench/bench_soak.py uses it too (it publishes the same streams on the wall clock and times
them; test_soak paces them by the node's counts and asserts only counts and memory).
"""

import os
from pathlib import Path
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.ros import conversions
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
from quatcal_ros.sim import simulation
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import LATCHED

REPO_ROOT = Path(__file__).resolve().parents[1]
# Reliable, and as deep as the node's link_pose queue (qos.LINK_QOS).
PUBLISH_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def proc_status_kb(pid, field):
    """Return a memory field of /proc/PID/status ('VmRSS', 'VmHWM') in kB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith(field + ':'):
            return int(line.split()[1])
    raise KeyError(field)


def start_calibrator(workdir, domain_id, *parameters):
    """Start `python -m quatcal_ros calibrator` with `parameters` ('name:=value') on domain_id."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', HOME=str(workdir))
    env['PYTHONPATH'] = os.pathsep.join([str(REPO_ROOT)] + [p for p in [env.get('PYTHONPATH')]
                                                            if p])
    ros_args = ['--ros-args']
    for parameter in (f'samples_file:={workdir / "samples.csv"}',) + parameters:
        ros_args += ['-p', parameter]
    log = (workdir / 'calibrator.log').open('w')
    return subprocess.Popen([sys.executable, '-m', 'quatcal_ros', 'calibrator', *ros_args],
                            env=env, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)


def make_streams(seed, duration_s, link_rate_hz, sensor_rate_hz, start_ns, still_s=0.6,
                 move_s=0.6):
    """Simulate stop-and-go streams of about duration_s seconds from start_ns."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    return simulation.stop_and_go_streams(
        rng, cell, n_stops=int(np.ceil(duration_s / (still_s + move_s))) + 1,
        link_rate_hz=link_rate_hz, sensor_rate_hz=sensor_rate_hz, still_s=still_s,
        move_s=move_s, rotation_noise_deg=0.2, translation_noise_m=0.001, latency_s=0.03,
        drop_probability=0.02, rotation_spread_deg=40.0, start_ns=start_ns)


def error_deg(msg, truth):
    """Return the angle between a QuaternionStamped and the true mounting (degrees)."""
    q = msg.quaternion
    return float(np.degrees(quat.angle_between([q.w, q.x, q.y, q.z], truth.quaternion)))


class Driver:
    """Publishes pose streams (and a flood of NaN poses) and records what the node reports."""

    def __init__(self, domain_id):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('soak_driver', context=self.context)
        self.publishers = {
            'link': self.node.create_publisher(PoseStamped, 'link_pose', PUBLISH_QOS),
            'sensor': self.node.create_publisher(PoseStamped, 'sensor_pose', PUBLISH_QOS)}
        self.flood_node = rclpy.create_node('soak_flood', context=self.context)
        self.publishers['flood'] = self.flood_node.create_publisher(PoseStamped, 'sensor_pose',
                                                                    PUBLISH_QOS)
        self.frames = {'link': 'base', 'sensor': 'camera', 'flood': 'camera'}
        self.published = {'link': 0, 'sensor': 0, 'flood': 0}
        self.rotations = []
        self.statuses = []      # (monotonic time, published link count, values)
        self.node.create_subscription(QuaternionStamped, '/calibrator/rotation',
                                      self.rotations.append, LATCHED)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.flood_node)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name == DIAGNOSTIC_NAME:
                values = {kv.key: kv.value for kv in status.values}
                values['message'] = status.message
                self.statuses.append((time.monotonic(), self.published['link'], values))

    def close(self):
        """Destroy the nodes and shut the private context down."""
        self.executor.shutdown()
        self.flood_node.destroy_node()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def publish(self, kind, stamp_ns, pose=None):
        """Publish a link, sensor or flood pose (a flood pose is NaN); count it."""
        if kind == 'flood':
            msg = PoseStamped()
            msg.header.stamp = conversions.time_msg(stamp_ns)
            msg.header.frame_id = self.frames[kind]
            msg.pose.position.x = float('nan')
            msg.pose.orientation.w = 1.0
        else:
            msg = conversions.pose_stamped_msg(pose, stamp_ns, self.frames[kind])
        self.publishers[kind].publish(msg)
        self.published[kind] += 1

    def spin_some(self, budget_s=0.0):
        """Handle the callbacks that are ready (and wait up to budget_s for one)."""
        self.executor.spin_once(timeout_sec=budget_s)
        for _ in range(20):
            self.executor.spin_once(timeout_sec=0.0)

    def wait_for(self, condition, timeout, what, process):
        """Spin until condition(); fail if the calibrator exits, or after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not condition():
            assert process.poll() is None, f'the calibrator exited with {process.returncode}'
            assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
            self.spin_some(0.05)

    def wait_for_calibrator(self, process):
        """Wait until the calibrator subscribes to both streams and reports on /diagnostics."""
        self.wait_for(lambda: (self.publishers['link'].get_subscription_count()
                               and self.publishers['sensor'].get_subscription_count()
                               and self.statuses),
                      120.0, 'the calibrator to start', process)

    def latest(self):
        """Return the values of the latest /diagnostics status of the calibrator."""
        return self.statuses[-1][2]

    def received(self):
        """Return the latest reported (link, sensor_pose) message counts, bad ones included."""
        values = self.latest() if self.statuses else {}
        return int(values.get('link_messages', 0)), int(values.get('sensor_messages', 0))
