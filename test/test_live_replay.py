"""
Live replay: the calibrator on a bag played with `ros2 bag play --clock` and use_sim_time.

rosbag2 cannot be installed here, so a player node does what `ros2 bag play --clock --loop`
does with a recording of a stop-and-go session (simulation.stop_and_go_streams, fixed seed):
it publishes rosgraph_msgs/Clock advancing with the recording's time and each PoseStamped,
with its recorded header stamp, once the clock reaches the time it was recorded at, in time
order.  Then it plays the recording again from its start, so the clock jumps back.  The
player paces itself to the node: it plays the next STEP of the recording once the node has
taken the last one, as fast as the node keeps up (`--rate` well above 1), so no best-effort
frame is lost and the live run sees exactly what the offline replay reads.

The calibrator runs with use_sim_time:=true in the same process (a private Context, one
executor spun with deadlines).  /clock, /rosout and /diagnostics are remapped into a
namespace of this run, so no other clock or node on the domain can interfere.  The same
recording, written to a rosbag2 bag with rosbags, goes through the offline `replay` tool; the
live run must take the same samples and agree with its estimate.

The second play makes the clock jump back: the session clears its pairing buffers (a logged
notice, /diagnostics time_jumps) and recognises each still of the second play as a repeat of
an earlier sample, so the same data are not counted twice as new evidence (which made the
reported uncertainty too small and could reject good samples).  The last tests check these
rules on the session alone, as the offline replay drives it.  On a domain id reserved on this
host (conftest's domain_id); the node's files go to the session's temporary HOME.
"""

import bisect
import csv
from dataclasses import dataclass, field
import json
import os
import subprocess
import sys
import time
import uuid

from diagnostic_msgs.msg import DiagnosticArray
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
import numpy as np
from numpy.testing import assert_allclose
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.ros import conversions as conv
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation as sim
from quatcal_ros.stream.capture import CaptureConfig
from quatcal_ros.stream.session import Notice
from quatcal_ros.stream.session import Rejected
from quatcal_ros.stream.session import Session
from quatcal_ros.stream.session import SessionConfig
from rcl_interfaces.msg import Log
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

NS = NS_PER_S
SEED = 93
N_STOPS = 8
# The player's clock step (ros2 bag play publishes /clock at a fixed rate; 10 Hz here).
STEP_NS = 100_000_000
# A robot driver publishes its pose 1 ms after the stamp; the camera's latency is simulated.
LINK_DELAY_NS = 1_000_000
# After the second pass the clock runs on this long, so a last /diagnostics covers it all.
TAIL_NS = 1_500_000_000
LINK_TOPIC, SENSOR_TOPIC = '/link_pose', '/sensor_pose'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
# ros2 bag play's /clock QoS (rclcpp::ClockQoS): best effort, depth 1.
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
# Keeps every estimate (the node's ~/rotation is reliable + transient local, depth 1).
ROTATIONS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
TIME_JUMP_TEXT = 'time jumped back by'
REPEAT_TEXT = ' repeats sample '


@dataclass(frozen=True)
class Recording:
    """A recorded session: its streams (with the truth) and its messages in time order."""

    streams: sim.Streams
    messages: list   # (log time ns, topic, header stamp ns, Pose), sorted by log time

    @property
    def start_ns(self):
        return self.messages[0][0]

    @property
    def end_ns(self):
        return self.messages[-1][0]


@pytest.fixture(scope='module')
def recording():
    """Record 8 fast stops: link 100 Hz, camera 30 Hz (30 ms late, 5 % dropped), noisy."""
    rng = np.random.default_rng(SEED)
    streams = sim.stop_and_go_streams(
        rng, sim.random_cell(rng), N_STOPS, link_rate_hz=100.0, still_s=1.0, move_s=1.0,
        rotation_noise_deg=0.2, translation_noise_m=0.001)
    link = [(stamp + LINK_DELAY_NS, LINK_TOPIC, stamp, pose) for stamp, pose in streams.link]
    sensor = [(delivered, SENSOR_TOPIC, stamp, pose)
              for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    return Recording(streams, sorted(link + sensor, key=lambda m: (m[0], m[1])))


@pytest.fixture(scope='module')
def offline(recording, repo_root, tmp_path_factory):
    """Write the recording to a rosbag2 bag, run `replay` on it: (JSON, sample stamps s)."""
    from quatcal_ros.ros.bag import TYPESTORE, write_bag
    frames = {LINK_TOPIC: 'base', SENSOR_TOPIC: 'camera'}
    folder = tmp_path_factory.mktemp('live_replay')
    write_bag(folder / 'recording', {LINK_TOPIC: POSE_STAMPED, SENSOR_TOPIC: POSE_STAMPED},
              [(topic, log_ns, conv.pose_stamped_msg(pose, stamp, frames[topic], TYPESTORE))
               for log_ns, topic, stamp, pose in recording.messages])
    done = subprocess.run(
        [sys.executable, '-m', 'quatcal_ros', 'replay', str(folder / 'recording'),
         '--link-topic', LINK_TOPIC, '--sensor-topic', SENSOR_TOPIC,
         '--samples-out', str(folder / 'samples.csv'), '--quiet'],
        capture_output=True, text=True, timeout=120,
        env=dict(os.environ, PYTHONPATH=str(repo_root)))
    assert done.returncode == 0, done.stderr
    with open(folder / 'samples.csv', newline='') as stream:
        stamps_s = [float(row['stamp']) for row in csv.DictReader(stream)]
    return json.loads(done.stdout), stamps_s


@dataclass
class Pass:
    """What the node had at the end of one play of the recording (read in-process)."""

    result: object
    samples: list
    rotations: int   # ~/rotation messages received by then


@dataclass
class LiveRun:
    """Everything the test nodes saw of the calibrator over two plays of the recording."""

    namespace: str
    diagnostics: list = field(default_factory=list)   # DiagnosticStatus of the calibrator
    diagnostic_stamps: list = field(default_factory=list)
    rotations: list = field(default_factory=list)      # QuaternionStamped
    logs: list = field(default_factory=list)           # rcl_interfaces/Log of the calibrator
    diagnostics_before_clock: int = 0
    clockless: list = field(default_factory=list)   # statuses saying that no clock runs
    capture_response: object = None
    passes: list = field(default_factory=list)

    def on_diagnostics(self, array):
        for status in array.status:
            if status.name != DIAGNOSTIC_NAME:
                continue
            if 'no /clock message has come' in status.message:   # the steady-clock watch
                self.clockless.append(status)
                continue
            self.diagnostics.append(status)
            self.diagnostic_stamps.append(conv.stamp_ns_from_header(array.header))

    def on_log(self, msg):
        if msg.name == f'{self.namespace.strip("/")}.calibrator':
            self.logs.append(msg.msg)


def values_of(status):
    """Return the key: value pairs of a DiagnosticStatus, as a dict of strings."""
    return {kv.key: kv.value for kv in status.values}


def rotation_of(msg):
    """(w, x, y, z) of a QuaternionStamped."""
    q = msg.quaternion
    return np.array([q.w, q.x, q.y, q.z])


def angle_deg(q_wxyz, p_wxyz):
    """Angle between two rotations (w, x, y, z), degrees."""
    return float(np.degrees(quat.angle_between(q_wxyz, p_wxyz)))


class Player:
    """
    `ros2 bag play --clock` in a test node: /clock and the recorded poses, in time order.

    Paced by the node under test: each STEP_NS of the recording is published once the node's
    clock shows the step's time and the node has received the poses sent so far.
    """

    def __init__(self, node, calibrator, executor, messages):
        self.calibrator = calibrator
        self.executor = executor
        self.messages = messages
        self.clock_pub = node.create_publisher(Clock, 'clock', CLOCK_QOS)
        self.publishers = {
            LINK_TOPIC: node.create_publisher(PoseStamped, 'link_pose', RELIABLE),
            # A camera driver publishes sensor data best effort; ros2 bag play keeps the QoS.
            SENSOR_TOPIC: node.create_publisher(PoseStamped, 'sensor_pose',
                                                qos_profile_sensor_data),
        }
        self.sent = {'link_pose': 0, 'sensor_pose': 0}
        self.frames = {LINK_TOPIC: 'base', SENSOR_TOPIC: 'camera'}

    def spin_until(self, condition, timeout=20.0, what='condition', every=None):
        """Spin until condition(); call every() each 0.1 s meanwhile (a periodic /clock)."""
        deadline = time.monotonic() + timeout
        next_call = time.monotonic() + 0.1
        while not condition():
            now = time.monotonic()
            if now > deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')
            if every is not None and now > next_call:
                every()
                next_call = now + 0.1
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, seconds):
        """Spin for a fixed wall time."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def set_clock(self, now_ns):
        """Publish /clock = now_ns until the node's clock shows it."""
        def publish():
            self.clock_pub.publish(Clock(clock=conv.time_msg(now_ns)))
        publish()
        self.spin_until(lambda: self.calibrator.now_ns() == now_ns, every=publish,
                        what=f'the node clock to show {now_ns} ns')

    def play(self, start_ns, end_ns):
        """Play the messages logged in [start_ns, end_ns]; the clock may run past the last."""
        received = self.calibrator.stats.received
        index = bisect.bisect_left([m[0] for m in self.messages], start_ns)
        now = start_ns
        while True:
            self.set_clock(now)
            while index < len(self.messages) and self.messages[index][0] <= now:
                _, topic, stamp, pose = self.messages[index]
                self.publishers[topic].publish(
                    conv.pose_stamped_msg(pose, stamp, self.frames[topic]))
                self.sent[topic.strip('/')] += 1
                index += 1
            # The node holds up to a few ms of link poses to decode them together; the
            # player asks for them at once (what the next /clock or sensor message would do).
            self.spin_until(lambda: (self.calibrator.inputs.flush() is None
                                     and all(received[s] >= n for s, n in self.sent.items())),
                            what='the node to receive the poses')
            if now >= end_ns:
                return
            now = min(now + STEP_NS, end_ns)


@pytest.fixture(scope='module')
def live(recording, domain_id):
    """Play the recording twice (--loop) into a calibrator with use_sim_time; a LiveRun."""
    namespace = f'/live_replay_{uuid.uuid4().hex[:10]}'
    run = LiveRun(namespace)
    remaps = ['--ros-args']
    for topic in ('clock', 'rosout', 'diagnostics'):
        remaps += ['-r', f'/{topic}:={namespace}/{topic}']
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=context)
    calibrator = listener = None
    try:
        calibrator = CalibratorNode(
            context=context, namespace=namespace, cli_args=remaps,
            parameter_overrides=[Parameter('use_sim_time', value=True)])
        listener = Node('live_replay_player', context=context, namespace=namespace)
        for node in (calibrator, listener):
            executor.add_node(node)
        player = Player(listener, calibrator, executor, recording.messages)
        listener.create_subscription(DiagnosticArray, f'{namespace}/diagnostics',
                                     run.on_diagnostics, RELIABLE)
        listener.create_subscription(QuaternionStamped, f'{namespace}/calibrator/rotation',
                                     run.rotations.append, ROTATIONS_QOS)
        listener.create_subscription(Log, f'{namespace}/rosout', run.on_log,
                                     QoSProfile(depth=1000, reliability=RELIABLE.reliability))
        capture = listener.create_client(Trigger, f'{namespace}/calibrator/capture')
        player.spin_until(
            lambda: (all(p.get_subscription_count() for p in player.publishers.values())
                     and player.clock_pub.get_subscription_count()
                     and capture.service_is_ready()),
            what='discovery of the calibrator')
        # No /clock yet: ROS time stands at 0, so the diagnostics timer does not fire; only
        # the steady-clock watch may, to say that no clock runs (checked below).
        player.spin_for(0.5)
        run.diagnostics_before_clock = len(run.diagnostics)

        for number in (1, 2):
            player.play(recording.start_ns, recording.end_ns)
            session = calibrator.session
            player.spin_until(
                lambda: run.rotations and np.allclose(
                    rotation_of(run.rotations[-1]), session.result.quaternion, atol=1e-9),
                what='the latest estimate on ~/rotation')
            run.passes.append(Pass(session.result, session.samples, len(run.rotations)))
            if number == 1:
                # The robot stands at its last stop: the capture is refused only because it
                # has not moved since the last sample, so recent pairs count on the node clock.
                future = capture.call_async(Trigger.Request())
                player.spin_until(future.done, what='the capture service')
                run.capture_response = future.result()
        # The bag has ended: the clock runs on so that a last /diagnostics covers it all.
        player.play(recording.end_ns + STEP_NS, recording.end_ns + TAIL_NS)
        player.spin_until(lambda: run.diagnostic_stamps
                          and run.diagnostic_stamps[-1] > recording.end_ns,
                          what='the final diagnostics')
        player.spin_until(lambda: any(TIME_JUMP_TEXT in text for text in run.logs),
                          timeout=5.0, what='the time-jump notice on /rosout')
    finally:
        executor.shutdown()
        for node in (listener, calibrator):
            if node is not None:
                node.destroy_node()
        rclpy.try_shutdown(context=context)
    return run


def test_node_clock_follows_the_played_clock(live, recording):
    assert live.diagnostics_before_clock == 0
    # Statuses from the steady-clock watch (discovery took long) say so, at WARN.
    assert all(status.level == DiagnosticStatus.WARN for status in live.clockless)
    # Every stamp the node puts out is on the recording's clock (2023), not the wall clock.
    stamps = np.array(live.diagnostic_stamps)
    start, stop = recording.start_ns, recording.end_ns + TAIL_NS
    assert np.all((stamps >= start) & (stamps <= stop))
    assert np.all(np.abs(stamps - time.time_ns()) > 30 * 86400 * NS)
    rotation_stamps = [conv.stamp_ns_from_header(m.header) for m in live.rotations]
    assert all(start <= s <= recording.end_ns for s in rotation_stamps)
    # The diagnostics timer runs on the node clock: one per second of the recording, however
    # fast it is played; after the jump back it starts again from the new time.
    steps = np.diff(stamps)
    assert np.sum(steps < 0) == 1   # the clock jumped back once, with the second pass
    assert_allclose(steps[steps > 0], NS, atol=2 * STEP_NS)
    played_s = (2 * (recording.end_ns - start) + TAIL_NS) / NS
    assert abs(len(stamps) - played_s) <= 3
    # No pose was refused: the header stamps are checked against the node clock, which is
    # the played one (the wall clock is years away from them).
    assert all(values_of(status)['bad_messages'] == '0' for status in live.diagnostics)
    # Still windows and the capture service's "recent pairs" are on the same clock.
    response = live.capture_response
    assert not response.success
    assert response.message.startswith('no motion since the last sample'), response.message


def test_live_estimate_matches_the_offline_replay(live, recording, offline):
    offline, offline_stamps_s = offline
    first = live.passes[0]
    truth = recording.streams.truth.quaternion
    live_q = first.result.quaternion
    assert_allclose(rotation_of(live.rotations[first.rotations - 1]), live_q, atol=1e-9)
    r = offline['rotation']
    offline_q = quat.wxyz_from_xyzw([r['x'], r['y'], r['z'], r['w']])
    assert offline['warnings'] == []
    # The same stills, one per stop, at the same stamps.
    assert len(first.samples) == offline['samples'] == N_STOPS
    assert_allclose([s.stamp_ns / NS for s in first.samples], offline_stamps_s, rtol=0,
                    atol=1e-5)
    live_u, offline_u = first.result.uncertainty_deg, offline['uncertainty_deg']
    assert angle_deg(live_q, offline_q) <= max(live_u, offline_u)
    # With 12 samples or fewer the live estimator solves in full, as the replay does: the same
    # samples give the same estimate, to rounding.
    assert angle_deg(live_q, offline_q) < 1e-6
    assert first.result.uncertainty_deg == pytest.approx(offline['uncertainty_deg'], rel=1e-6)
    assert angle_deg(live_q, truth) <= 3 * live_u
    assert angle_deg(offline_q, truth) <= 3 * offline_u


def test_loop_restart_resets_the_pairing_and_adds_nothing_twice(live, recording):
    first, second = live.passes
    jumps = [text for text in live.logs if TIME_JUMP_TEXT in text]
    jump_s = (recording.end_ns - recording.start_ns) / NS
    assert len(jumps) == 1, jumps
    assert f'{TIME_JUMP_TEXT} {jump_s:.1f} s (bag replayed?): pairing buffers cleared' in jumps[0]
    # The second pass stops at the same stops at the same stamps: each still is recognised as
    # a repeat and not added (it would count the same data twice as new evidence).
    repeats = [text for text in live.logs if REPEAT_TEXT in text]
    assert [int(text.split(REPEAT_TEXT)[1].split()[0]) for text in repeats] == list(
        range(N_STOPS))
    assert [s.stamp_ns for s in second.samples] == [s.stamp_ns for s in first.samples]
    assert second.result is first.result
    assert second.rotations == first.rotations == len(live.rotations)
    # /diagnostics: one jump, nothing rejected as late or out of order, nothing stale.
    status = live.diagnostics[-1]
    final = values_of(status)
    assert status.level == DiagnosticStatus.OK, status.message
    assert final['time_jumps'] == '1' and final['repeated_samples'] == str(N_STOPS)
    assert final['rejected_messages'] == '0' and final['bad_messages'] == '0'
    assert final['samples'] == str(N_STOPS)
    assert final['residual_rms_deg'] == f'{first.result.residual_rms_deg:.6g}'
    jumps_seen = [int(values_of(status)['time_jumps']) for status in live.diagnostics]
    assert jumps_seen == sorted(jumps_seen) and jumps_seen[0] == 0


# --- the same rules in the session, which the offline replay drives ---------------------------

def feed(session, streams):
    """Feed streams to a session in delivery order; return the events."""
    link = [(stamp + LINK_DELAY_NS, 0, stamp, pose) for stamp, pose in streams.link]
    sensor = [(delivered, 1, stamp, pose)
              for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    events = []
    for _, stream, stamp, pose in sorted(link + sensor, key=lambda m: (m[0], m[1])):
        add = session.add_link_pose if stream == 0 else session.add_sensor_pose
        events += add(stamp, pose)
    return events


def texts(events):
    """Return the texts of the Notice events."""
    return [event.text for event in events if isinstance(event, Notice)]


def test_a_new_recording_after_a_time_jump_adds_its_samples():
    """The jump keeps the samples; only repeats of them are left out, not new stills."""
    rng = np.random.default_rng(SEED + 1)
    cell = sim.random_cell(rng)
    one, two = (sim.stop_and_go_streams(rng, cell, 5, link_rate_hz=100.0, still_s=1.0,
                                        move_s=1.0, rotation_noise_deg=0.2) for _ in range(2))
    session = Session()
    feed(session, one)
    events = feed(session, two)   # the same stamps again (a second bag), other stops
    assert sum(TIME_JUMP_TEXT in text for text in texts(events)) == 1
    assert not any(REPEAT_TEXT in text for text in texts(events))
    assert not [event for event in events if isinstance(event, Rejected)]
    assert session.counters['samples'] == 10 and session.counters['repeated_samples'] == 0
    session.estimate()
    error = angle_deg(session.result.quaternion, cell.mounting.quaternion)
    assert error <= 3 * session.result.uncertainty_deg
    # Played again, it adds nothing.
    again = feed(session, two)
    assert sum(REPEAT_TEXT in text for text in texts(again)) == 5
    assert session.counters['samples'] == 10 and session.counters['time_jumps'] == 2
    assert not [event for event in again if isinstance(event, Rejected)]
    assert session.estimate() == []   # no new sample: no new estimate


def test_manual_capture_of_a_repeated_still_is_refused():
    rng = np.random.default_rng(SEED + 2)
    streams = sim.stop_and_go_streams(rng, sim.random_cell(rng), 2, link_rate_hz=100.0,
                                      still_s=1.0, move_s=1.0)
    session = Session(SessionConfig(capture=CaptureConfig(mode='manual')))
    end_ns = streams.stills[-1][1]
    feed(session, streams)
    ok, reason = session.capture(end_ns)
    assert ok, reason
    feed(session, streams)   # played again: the same still at the same stamps
    ok, reason = session.capture(end_ns)
    assert not ok and 'repeats sample 0' in reason, reason
    assert session.counters['samples'] == 1 and session.counters['repeated_samples'] == 1
