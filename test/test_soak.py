"""
Load tests through the real middleware: a soak at 1 kHz + 60 Hz, and a flood of bad messages.

The calibrator runs as a process (`python -m quatcal_ros calibrator`), so that its memory can
be read from /proc/PID/status (VmRSS sampled over time, VmHWM for the peak).  The test process
publishes simulated stop-and-go streams (simulation.stop_and_go_streams) in real time, stamped
on the wall clock like a live robot and camera, in batches per tick of a few milliseconds, and
listens to /diagnostics and ~/rotation.

- Soak (QUATCAL_SOAK_S seconds, default 60): the link pose at 1 kHz and the sensor pose at
  60 Hz.  Memory stays bounded (the RSS of the last quarter of the run is within a few MB of
  the second quarter's), the node's message counts keep pace with what was published (no
  growing backlog), and the estimate converges to the truth within 3x its uncertainty.  The
  peak RSS is printed (pytest -s) and part of the assertion messages.
- Flood: 2 kHz of NaN poses on sensor_pose from another publisher while the good streams run:
  every bad message is counted, the good ones are not starved, and the estimate converges.

ROS_DOMAIN_ID 63.
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
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.ros import conversions
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
from quatcal_ros.sim import simulation
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import stop_process

REPO_ROOT = Path(__file__).resolve().parents[1]
DOMAIN_ID = 63
NS = NS_PER_S
SOAK_S = float(os.environ.get('QUATCAL_SOAK_S', '60'))
TICK_S = 0.004
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
PUBLISH_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LINK_DEPTH = 1000   # the node's link_pose subscription queue (node.LINK_QOS)
# The RSS of the last quarter of the soak may exceed the second quarter's by this much.
RSS_GROWTH_LIMIT_KB = 6 * 1024


def proc_status_kb(pid, field):
    """Return a memory field of /proc/PID/status ('VmRSS', 'VmHWM') in kB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith(field + ':'):
            return int(line.split()[1])
    raise KeyError(field)


def start_calibrator(tmp_path, *parameters):
    """Start the calibrator process with `parameters` ('name:=value'); its log in tmp_path."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', HOME=str(tmp_path))
    env['PYTHONPATH'] = os.pathsep.join([str(REPO_ROOT)] + [p for p in [env.get('PYTHONPATH')]
                                                            if p])
    ros_args = ['--ros-args']
    for parameter in ('diagnostics_period_s:=0.5', 'still_window_s:=0.3',
                      f'samples_file:={tmp_path / "samples.csv"}') + parameters:
        ros_args += ['-p', parameter]
    log = (tmp_path / 'calibrator.log').open('w')
    return subprocess.Popen([sys.executable, '-m', 'quatcal_ros', 'calibrator', *ros_args],
                            env=env, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)


class Driver:
    """Publishes pose streams on the wall clock and records what the calibrator reports."""

    def __init__(self):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.node = rclpy.create_node('soak_driver', context=self.context)
        self.link_pub = self.node.create_publisher(PoseStamped, 'link_pose', PUBLISH_QOS)
        self.sensor_pub = self.node.create_publisher(PoseStamped, 'sensor_pose', PUBLISH_QOS)
        self.flood_node = rclpy.create_node('soak_flood', context=self.context)
        self.flood_pub = self.flood_node.create_publisher(PoseStamped, 'sensor_pose',
                                                          PUBLISH_QOS)
        self.published = {'link': 0, 'sensor': 0, 'flood': 0}
        self.lateness_ns = []   # per tick: how late its first link pose went out
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
        self.executor.shutdown()
        self.flood_node.destroy_node()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def spin_some(self, budget_s=0.0):
        """Handle the callbacks that are ready (and wait up to budget_s for one)."""
        self.executor.spin_once(timeout_sec=budget_s)
        for _ in range(20):
            self.executor.spin_once(timeout_sec=0.0)

    def wait_for(self, condition, timeout, what, process):
        deadline = time.monotonic() + timeout
        while not condition():
            assert process.poll() is None, f'the calibrator exited with {process.returncode}'
            assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
            self.spin_some(0.05)

    def wait_for_calibrator(self, process):
        self.wait_for(lambda: (self.link_pub.get_subscription_count()
                               and self.sensor_pub.get_subscription_count() and self.statuses),
                      60.0, 'the calibrator to start', process)

    def run(self, streams, process, flood_hz=0.0, on_second=None):
        """
        Publish `streams` in real time (stamps are wall-clock ns); return when all are out.

        flood_hz: NaN poses per second on sensor_pose from another node (stamped now).
        on_second(): called about once per second (memory sampling).
        """
        link = streams.link
        sensor = list(zip(streams.sensor_delivery_ns, streams.sensor))
        i = j = 0
        flood_due = time.time_ns()
        next_second = time.monotonic() + 1.0
        nan_msg = PoseStamped()
        nan_msg.pose.position.x = float('nan')
        nan_msg.pose.orientation.w = 1.0
        while i < len(link) or j < len(sensor):
            now = time.time_ns()
            if i < len(link) and link[i][0] <= now:
                self.lateness_ns.append(now - link[i][0])
            while i < len(link) and link[i][0] <= now:
                stamp, pose = link[i]
                self.link_pub.publish(conversions.pose_stamped_msg(pose, stamp, 'base'))
                self.published['link'] += 1
                i += 1
            while j < len(sensor) and sensor[j][0] <= now:
                _, (stamp, pose) = sensor[j]
                self.sensor_pub.publish(conversions.pose_stamped_msg(pose, stamp, 'camera'))
                self.published['sensor'] += 1
                j += 1
            while flood_hz and flood_due <= now:
                nan_msg.header.stamp = conversions.time_msg(flood_due)
                self.flood_pub.publish(nan_msg)
                self.published['flood'] += 1
                flood_due += int(NS / flood_hz)
            if time.monotonic() >= next_second:
                next_second += 1.0
                assert process.poll() is None, f'the calibrator exited: {process.returncode}'
                if on_second:
                    on_second()
            self.spin_some()
            time.sleep(max(0.0, TICK_S - (time.time_ns() - now) / NS))

    def latest(self):
        return self.statuses[-1][2]


def error_deg(msg, truth):
    q = msg.quaternion
    return float(np.degrees(quat.angle_between([q.w, q.x, q.y, q.z], truth.quaternion)))


def make_streams(seed, duration_s, link_rate_hz, sensor_rate_hz, still_s=0.6, move_s=0.6):
    """Simulate streams that start two seconds from now on the wall clock."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    return simulation.stop_and_go_streams(
        rng, cell, n_stops=int(np.ceil(duration_s / (still_s + move_s))) + 1,
        link_rate_hz=link_rate_hz, sensor_rate_hz=sensor_rate_hz, still_s=still_s,
        move_s=move_s, rotation_noise_deg=0.2, translation_noise_m=0.001, latency_s=0.03,
        drop_probability=0.02, rotation_spread_deg=40.0, start_ns=time.time_ns() + 2 * NS)


def test_soak_1khz_link_60hz_sensor(tmp_path):
    duration_s = max(SOAK_S, 1.0)
    process = start_calibrator(tmp_path)
    driver = Driver()
    memory = []     # (monotonic time, VmRSS kB)
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(11, duration_s, 1000.0, 60.0)
        start = time.monotonic()
        driver.run(streams, process,
                   on_second=lambda: memory.append((time.monotonic(),
                                                    proc_status_kb(process.pid, 'VmRSS'))))
        published = dict(driver.published)
        end = time.monotonic()
        # Drain: the node must reach the published counts (the link stream is reliable).
        driver.wait_for(lambda: (int(driver.latest()['link_messages']) >= published['link']
                                 and driver.statuses[-1][0] > end + 0.6),
                        10.0, 'the calibrator to catch up', process)
        peak_kb = proc_status_kb(process.pid, 'VmHWM')
        values = driver.latest()
    finally:
        status = stop_process(process, timeout=20.0)
        driver.close()
    log = (tmp_path / 'calibrator.log').read_text()
    assert status == 0, log[-3000:]

    run_s = end - start
    stream_s = (streams.link[-1][0] - streams.link[0][0]) / NS
    link_hz = (published['link'] - 1) / stream_s
    rss = np.array([kb for t, kb in memory])
    times = np.array([t - start for t, kb in memory])
    quarter = run_s / 4
    second = rss[(times >= quarter) & (times < 2 * quarter)]
    last = rss[times >= 3 * quarter]
    growth_kb = float(last.mean() - second.mean())
    lags = np.array([(t - start, sent - int(v['link_messages']))
                     for t, sent, v in driver.statuses if start <= t <= end])
    lag_second = lags[(lags[:, 0] >= quarter) & (lags[:, 0] < 2 * quarter), 1]
    lag_last = lags[lags[:, 0] >= 3 * quarter, 1]
    uncertainty = float(values['uncertainty_deg'])
    error = error_deg(driver.rotations[-1], streams.truth)
    late_ms = np.percentile(driver.lateness_ns, [50, 99]) / 1e6
    report = (f'soak {stream_s:.0f} s: published {published["link"]} link ({link_hz:.0f} Hz, '
              f'{late_ms[0]:.1f} / {late_ms[1]:.1f} ms late at the median / 99th percentile) '
              f'and {published["sensor"]} sensor poses; received {values["link_messages"]}'
              f' and {values["sensor_messages"]}; peak RSS (VmHWM) {peak_kb / 1024:.1f} MB; RSS '
              f'2nd quarter {second.mean() / 1024:.1f} MB, last quarter {last.mean() / 1024:.1f}'
              f' MB (growth {growth_kb / 1024:+.2f} MB); link lag (published - received) '
              f'median / max {np.median(lag_second):.0f} / {lag_second.max()} in the 2nd '
              f'quarter, {np.median(lag_last):.0f} / {lag_last.max()} in the last; '
              f'{values["samples"]} samples, uncertainty {uncertainty:.4f} deg, true error '
              f'{error:.4f} deg')
    print('\n' + report)
    assert link_hz > 999.0 and stream_s >= duration_s, report
    assert late_ms[0] < 20.0, report     # the publisher kept (nearly) real time
    assert growth_kb < RSS_GROWTH_LIMIT_KB, report
    # No growing backlog: the node keeps within a few ticks of the publisher, and received
    # every link pose (reliable) and nearly every sensor pose (best effort).
    assert np.median(lag_last) <= np.median(lag_second) + 50, report
    assert lag_last.max() < LINK_DEPTH, report
    assert int(values['link_messages']) == published['link'], report
    assert int(values['sensor_messages']) >= 0.99 * published['sensor'], report
    assert values['bad_messages'] == '0', report
    assert int(values['samples']) >= 0.8 * len(streams.stops), report
    assert error < 3.0 * uncertainty, report


def test_flood_of_bad_messages_does_not_starve_good_ones(tmp_path):
    process = start_calibrator(tmp_path)
    driver = Driver()
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(12, 16.0, 200.0, 30.0, still_s=0.5, move_s=0.5)
        driver.run(streams, process, flood_hz=2000.0)
        published = dict(driver.published)
        end = time.monotonic()
        driver.wait_for(lambda: (driver.statuses[-1][0] > end + 0.6
                                 and int(driver.latest()['link_messages']) >= published['link']),
                        10.0, 'the calibrator to catch up', process)
        values = driver.latest()
    finally:
        status = stop_process(process, timeout=20.0)
        driver.close()
    log = (tmp_path / 'calibrator.log').read_text()
    assert status == 0, log[-3000:]
    bad = int(values.get('bad_sensor_pose_non_finite', 0))
    good_sensor = int(values['sensor_messages']) - bad
    uncertainty = float(values['uncertainty_deg'])
    error = error_deg(driver.rotations[-1], streams.truth)
    report = (f'flood: published {published["flood"]} NaN, {published["sensor"]} good sensor '
              f'and {published["link"]} link poses; node counted {bad} bad, {good_sensor} good '
              f'sensor, {values["link_messages"]} link poses; {values["samples"]} samples of '
              f'{len(streams.stops)} stops, uncertainty {uncertainty:.4f} deg, true error '
              f'{error:.4f} deg')
    print('\n' + report)
    assert published['flood'] >= 1900 * 16, report
    assert bad >= 0.95 * published['flood'], report                 # handled, not dropped
    assert good_sensor >= 0.97 * published['sensor'], report        # not starved
    assert int(values['samples']) >= len(streams.stops) - 2, report
    assert error < 3.0 * uncertainty, report
    # One warning per reason and 5 s, naming the topic.
    warnings = log.count('/sensor_pose: bad message skipped (non_finite')
    assert 1 <= warnings <= 1 + 20 / 5, log[-3000:]
