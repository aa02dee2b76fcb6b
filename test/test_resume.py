"""
Crash safety and resuming of the calibrator node, and what it says when things go wrong.

Issue 5, points 3, 5 and 6 (docs/what_happens_when.md), mostly over real DDS.

The main test kills the node process with SIGKILL in the middle of a session fed by a
stop-and-go stream, checks that the samples journal holds every sample the node reported, and
restarts it with resume:=true: same sample count, the estimate of calibrate() on the journal's
samples (to 1e-9), and more samples taken as the stream goes on.  The other tests build the
node in-process (rclpy style) and read its log with capfd.  Two domain ids reserved on this
host (conftest: domain_id in-process, process_domain_id for processes) keep them apart.
"""

import ast
import contextlib
from dataclasses import replace
import errno
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
from journal_files import aside_files
from journal_files import write_journal
import numpy as np
from numpy.testing import assert_allclose
import pytest
from quatcal_ros.core import calibration
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files import journal
from quatcal_ros.files import persistence
from quatcal_ros.files.journal import JournalHeader
from quatcal_ros.ros import conversions
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.ros.node import NODE_NAME
from quatcal_ros.sim import simulation
from quatcal_ros.stream import settings
from quatcal_ros.stream.session import SampleCaptured
from quatcal_ros.stream.session import Session
from quatcal_ros.stream.settings import ConfigError
from quatcal_ros.stream.settings import Settings
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.logging import LoggingSeverity
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import LATCHED
from ros_harness import ProcessWatcher
from ros_harness import SpinMixin
from ros_harness import stop_process
from std_srvs.srv import Trigger

REPO_ROOT = Path(__file__).resolve().parents[1]
NS = NS_PER_S
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
HEADER = JournalHeader('eye_in_hand', 'tool0', 'camera')
SAMPLE_LOG = re.compile(r'sample (\d+) captured at stamp ([0-9.]+) s')


def canonical(q_wxyz):
    q = np.asarray(q_wxyz, dtype=float)
    return q if q[0] >= 0 else -q


def rotation_of(msg):
    q = msg.quaternion
    return canonical([q.w, q.x, q.y, q.z])


def status_values(status):
    return {kv.key: kv.value for kv in status.values}


def synthetic_samples(n, seed=1, noise_deg=0.1):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, n, rotation_noise_deg=noise_deg,
                                    translation_noise_m=0.001)
    return cell, samples


def stream_events(streams):
    """(delivery ns, topic, header stamp ns, pose) of both streams in delivery order."""
    return streams.delivery_order(('link_pose', 'sensor_pose'))


# --- in-process ------------------------------------------------------------------------------

class Rig(SpinMixin):
    """A calibrator node and a driver node in one private context and executor."""

    spin_timeout = 15.0

    def __init__(self, domain_id, overrides):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        # The synthetic stamps are in 2023: no check against the node clock.
        overrides = [Parameter('max_stamp_offset_s', value=0.0)] + overrides
        try:
            self.node = CalibratorNode(context=self.context, parameter_overrides=overrides)
        except Exception:
            rclpy.try_shutdown(context=self.context)
            raise
        self.driver = rclpy.create_node('resume_test_driver', context=self.context)
        self.publishers = {name: self.driver.create_publisher(PoseStamped, name, RELIABLE)
                           for name in ('link_pose', 'sensor_pose')}
        self.rotations = []
        self.driver.create_subscription(QuaternionStamped, '/calibrator/rotation',
                                        self.rotations.append, LATCHED)
        self.clients = {name: self.driver.create_client(Trigger, f'/calibrator/{name}')
                        for name in ('reset', 'save')}
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: all(p.get_subscription_count() for p in self.publishers.values())
                        and all(c.service_is_ready() for c in self.clients.values()),
                        what='discovery')

    def call(self, name):
        future = self.clients[name].call_async(Trigger.Request())
        self.spin_until(future.done, what=f'the {name} service')
        return future.result()

    def still(self, link, sensor, start_ns, duration_s=0.8, rate_hz=25.0):
        """Publish both streams holding one pose pair; wait until the node has them."""
        before = dict(self.node.stats.received)
        count = int(duration_s * rate_hz)
        for i in range(count):
            stamp = start_ns + int(i * NS / rate_hz)
            for name, pose in (('link_pose', link), ('sensor_pose', sensor)):
                self.publishers[name].publish(conversions.pose_stamped_msg(pose, stamp, 'f'))
        self.spin_until(lambda: all(self.node.stats.received[name] >= before.get(name, 0) + count
                                    for name in self.publishers), what='the poses')


@pytest.fixture(autouse=True)
def calibrator_info_logs():
    """Show the calibrator's INFO lines (another test may have raised its level)."""
    rclpy.logging.set_logger_level(NODE_NAME, LoggingSeverity.INFO)


@pytest.fixture
def rig_factory(domain_id):
    made = []

    def make(*overrides):
        made.append(Rig(domain_id, list(overrides)))
        return made[-1]
    yield make
    for rig in made:
        rig.close()


def random_stops(rng, cell, n):
    """Return n link poses around the cell's home, each turned ~40 deg about a random axis."""
    return [Pose(cell.home.position + rng.uniform(-0.05, 0.05, 3),
                 quat.normalize(quat.multiply(quat.from_rotation_vector(rng.normal(size=3) * 0.4),
                                              cell.home.quaternion))) for _ in range(n)]


def make_node(domain_id, *overrides):
    """Make a calibrator node without a driver (start-up behaviour); the caller closes it."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        return CalibratorNode(context=context, parameter_overrides=list(overrides)), context
    except Exception:
        rclpy.try_shutdown(context=context)
        raise


def close_node(node, context):
    node.destroy_node()
    rclpy.try_shutdown(context=context)


@contextlib.contextmanager
def resumed_node(domain_id, path, samples):
    """Yield a calibrator node that resumed a journal of `samples` at `path`; close it."""
    write_journal(path, samples)
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)),
                              Parameter('resume', value=True))
    try:
        yield node
    finally:
        close_node(node, context)


@pytest.mark.parametrize('torn', [False, True])
def test_resume_reloads_the_journal_and_publishes_its_estimate(rig_factory, tmp_path, capfd,
                                                               torn):
    _, samples = synthetic_samples(10)
    path = tmp_path / 'samples.csv'
    before = write_journal(path, samples)
    if torn:    # the node died while writing the last line
        path.write_bytes(before[:-30])
        before = before[:before[:-1].rfind(b'\n') + 1]
    rig = rig_factory(Parameter('samples_file', value=str(path)),
                      Parameter('resume', value=True))
    n = 9 if torn else 10
    assert len(rig.node.session.samples) == n and rig.node.journal.count == n
    expected = calibration.calibrate(journal.read_journal(path).samples)
    rig.spin_until(lambda: rig.rotations, what='the resumed estimate on ~/rotation')
    assert_allclose(rotation_of(rig.rotations[-1]), canonical(expected.quaternion), atol=1e-12)
    values = status_values(rig.node.diagnostic_status())
    assert values['samples'] == str(n) and values['state'] == 'estimating'
    assert path.read_bytes() == before                # resumed (torn line cut), not rewritten
    assert aside_files(tmp_path, 'previous') == []
    log = capfd.readouterr().err
    assert f'resumed {n} samples from {path}' in log
    assert ('being written when the node stopped: dropped' in log) == torn


def test_start_moves_an_earlier_journal_aside_and_says_so(tmp_path, capfd, domain_id):
    _, samples = synthetic_samples(4)
    path = tmp_path / 'samples.csv'
    before = write_journal(path, samples)
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)))
    try:
        assert node.session.samples == [] and node.journal.count == 0
    finally:
        close_node(node, context)
    (aside,) = aside_files(tmp_path, 'previous')
    assert aside.read_bytes() == before
    log = capfd.readouterr().err
    assert f'held 4 samples of an earlier session: moved to {aside}' in log
    assert 'resume:=true would have continued it' in log


@pytest.mark.parametrize('content, words', [
    (None, 'row 4, field sensor_qw'),                        # a damaged row: corrupt
    (b'format: quatcal_ros/rotation\nrotation: {x: 0, y: 0, z: 0, w: 1}\n',
     'not a quatcal_ros samples journal'),                   # a YAML file: foreign
])
def test_corrupt_or_foreign_journal_is_moved_aside_and_reported(tmp_path, capfd, content,
                                                                words, domain_id):
    path = tmp_path / 'samples.csv'
    if content is None:
        _, samples = synthetic_samples(4)
        lines = write_journal(path, samples).decode().splitlines(keepends=True)
        lines[3] = lines[3].rsplit(',', 1)[0] + ',NaN-ish\n'
        content = ''.join(lines).encode()
    path.write_bytes(content)
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)),
                              Parameter('resume', value=True))
    try:
        assert node.session.samples == []
        assert journal.read_journal(path).samples == []       # a new, empty journal
    finally:
        close_node(node, context)
    (aside,) = aside_files(tmp_path, 'corrupt')
    assert aside.read_bytes() == content                      # kept as it was
    log = capfd.readouterr().err
    assert '[ERROR]' in log and words in log and f'moved to {aside}' in log
    assert 'nothing resumed' in log


def test_resume_is_refused_for_another_setup_or_frames(tmp_path, domain_id):
    _, samples = synthetic_samples(4)
    path = tmp_path / 'samples.csv'
    before = write_journal(path, samples, JournalHeader('eye_to_hand', 'world', 'camera'))
    for extra in ([], [Parameter('setup', value='eye_to_hand')]):
        with pytest.raises(ConfigError, match='resume:=true refused') as error:
            make_node(domain_id, Parameter('samples_file', value=str(path)),
                      Parameter('resume', value=True), *extra)
        assert 'link_frame' in str(error.value)
        assert ("setup 'eye_to_hand' (parameters: 'eye_in_hand')" in str(error.value)) \
            == (not extra)
        # The base the parameters name, and why it is not link_frame's default value.
        said = ("link_frame 'world' (parameters: 'base_link', as, with eye_to_hand, link_frame "
                "left at its default 'tool0' names the robot base")
        assert (said in str(error.value)) == bool(extra)
    assert path.read_bytes() == before
    assert aside_files(tmp_path, 'previous') == aside_files(tmp_path, 'corrupt') == []


def test_an_earlier_versions_eye_to_hand_journal_resumes_under_the_named_base(tmp_path,
                                                                              domain_id):
    # Before, eye-to-hand sessions without link_frame named the robot base 'tool0' (the
    # flange default) in the journal; now the base is link_frame_id or base_link. Such a
    # journal resumes, its first line rewritten; a runtime change of link_frame_id, which now
    # names the base, is recorded there too.
    _, samples = synthetic_samples(4)
    path = tmp_path / 'samples.csv'
    write_journal(path, samples, JournalHeader('eye_to_hand', 'tool0', 'camera'))
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)),
                              Parameter('resume', value=True),
                              Parameter('setup', value='eye_to_hand'))
    try:
        assert len(node.session.samples) == 4
        assert journal.read_journal(path).header == JournalHeader('eye_to_hand', 'base_link',
                                                                  'camera', False)
        (changed,) = node.set_parameters([Parameter('link_frame_id', value='world')])
        assert changed.successful
        contents = journal.read_journal(path)
        assert contents.header == JournalHeader('eye_to_hand', 'world', 'camera', False)
        assert len(contents.samples) == 4
    finally:
        close_node(node, context)


def test_a_second_node_on_the_same_samples_file_is_refused(tmp_path, domain_id):
    path = tmp_path / 'samples.csv'
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)))
    try:
        with pytest.raises(ConfigError, match='in use by another running calibrator'):
            make_node(domain_id, Parameter('samples_file', value=str(path)))
    finally:
        close_node(node, context)
    # The lock is released.
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)))
    close_node(node, context)


def test_samples_are_journaled_reset_moves_the_journal_aside(rig_factory, tmp_path):
    rng = np.random.default_rng(8)
    cell = simulation.random_cell(rng)
    path = tmp_path / 'samples.csv'
    rig = rig_factory(Parameter('samples_file', value=str(path)),
                      Parameter('still_window_s', value=0.3))
    stops = random_stops(rng, cell, 4)
    start = simulation.DEFAULT_START_NS
    for k, link in enumerate(stops):
        rig.still(link, cell.sensor_pose(link), start + k * NS)
        rig.spin_until(lambda: len(rig.node.session.samples) == k + 1, what=f'sample {k}')
        saved = journal.read_journal(path).samples
        assert len(saved) == k + 1          # on disk as soon as it is captured
    assert_allclose(saved[-1].link.position, rig.node.session.samples[-1].link.position,
                    rtol=0, atol=0)
    # A runtime change of setup is recorded in the journal's header line.
    (changed,) = rig.node.set_parameters([Parameter('sensor_frame', value='camera_optical')])
    assert changed.successful
    assert journal.read_journal(path).header.sensor_frame == 'camera_optical'
    before = path.read_bytes()
    reset = rig.call('reset')
    assert reset.success
    (aside,) = aside_files(tmp_path, 'previous')
    assert f'the old samples journal was moved to {aside}' in reset.message
    assert aside.read_bytes() == before
    assert journal.read_journal(path).samples == [] and rig.node.journal.count == 0
    rig.still(stops[0], cell.sensor_pose(stops[0]), start + 10 * NS)
    rig.spin_until(lambda: len(rig.node.session.samples) == 1, what='a sample after reset')
    assert len(journal.read_journal(path).samples) == 1


def test_a_sample_is_written_before_the_estimate_is_published_and_fsynced_before_its_log(
        tmp_path, monkeypatch, domain_id):
    _, samples = synthetic_samples(10)
    path = tmp_path / 'samples.csv'
    with resumed_node(domain_id, path, samples[:7]) as node:
        steps = []
        real_write, real_fsync = os.write, os.fsync
        monkeypatch.setattr(journal.os, 'write',
                            lambda fd, data: steps.append('write') or real_write(fd, data))
        monkeypatch.setattr(journal.os, 'fsync',
                            lambda fd: steps.append('fsync') or real_fsync(fd))
        publish = node.rotation_publisher.publish
        monkeypatch.setattr(node.rotation_publisher, 'publish',
                            lambda msg: steps.append('publish') or publish(msg))
        log_sample = node.log.sample
        monkeypatch.setattr(node.log, 'sample',
                            lambda *a: steps.append('log') or log_sample(*a))
        node.handle_events(node.session.add_sample(samples[7]))
        # The sample's events first (journal, log), then the estimate the node asks for.
        assert steps == ['write', 'fsync', 'log', 'publish']
        assert len(journal.read_journal(path).samples) == 8

        # An fsync that fails is reported (the sample is in the file) and tried again.
        def failing_fsync(fd):
            raise OSError(errno.EIO, 'Input/output error')
        monkeypatch.setattr(journal.os, 'fsync', failing_fsync)
        node.handle_events(node.session.add_sample(samples[8]))
        assert 'could not fsync' in node.diagnostic_status().message
        assert 'Input/output error' in node.diagnostic_status().message
        monkeypatch.setattr(journal.os, 'fsync', lambda fd: steps.append('fsync again'))
        node.handle_events(node.session.add_sample(samples[9]))
        assert steps[-3:] == ['fsync again', 'log', 'publish']
        assert 'could not fsync' not in node.diagnostic_status().message
        assert len(journal.read_journal(path).samples) == 10


def test_a_resumed_journal_gains_a_new_sensor_time_offset_with_its_first_sample(
        tmp_path, domain_id, capfd):
    _, samples = synthetic_samples(8)
    path = tmp_path / 'samples.csv'
    write_journal(path, samples[:6], replace(HEADER, sensor_time_offsets=(0.0,)))
    node, context = make_node(domain_id, Parameter('samples_file', value=str(path)),
                              Parameter('resume', value=True),
                              Parameter('sensor_time_offset_s', value=-0.03))
    try:
        assert 'its 6 samples were paired with sensor_time_offset_s 0 (its first line); ' \
            '-0.03 applies to new poses only' in capfd.readouterr().err
        assert journal.read_journal(path).header.sensor_time_offsets == (0.0,)
        node.handle_events(node.session.add_sample(samples[6]))
        assert journal.read_journal(path).header.sensor_time_offsets == (0.0, -0.03)
        assert len(journal.read_journal(path).samples) == 7
        # A change and back before any sample: nothing paired with it, nothing listed.
        for offset in (0.05, -0.03):
            (done,) = node.set_parameters([Parameter('sensor_time_offset_s', value=offset)])
            assert done.successful
        node.handle_events(node.session.add_sample(samples[7]))
        assert journal.read_journal(path).header.sensor_time_offsets == (0.0, -0.03)
    finally:
        close_node(node, context)


def test_a_full_disk_keeps_the_samples_and_the_estimate_going(tmp_path, monkeypatch,
                                                              domain_id, capfd):
    _, samples = synthetic_samples(11)
    path = tmp_path / 'samples.csv'
    with resumed_node(domain_id, path, samples[:7]) as node:
        def full(fd, data):
            raise OSError(errno.ENOSPC, 'No space left on device')
        real_write = journal.os.write
        monkeypatch.setattr(journal.os, 'write', full)
        for sample in samples[7:9]:
            node.handle_events(node.session.add_sample(sample))
        status = node.diagnostic_status()
        assert status.level == status.WARN
        assert (f'2 captured sample(s) not yet saved to {path} (No space left on device): they '
                'are kept and written with the next sample') in status.message
        assert node.session.result.samples == 9   # the estimate goes on
        assert len(journal.read_journal(path).samples) == 7
        # The log says so of each such sample: 'captured' promises a sample on disk.
        log = capfd.readouterr().err
        waiting = re.findall(r'sample (\d) captured at stamp [^\n]*; not yet saved: kept in '
                             r'memory, written with the next sample\)', log)
        assert waiting == ['7', '8'], log
        monkeypatch.setattr(journal.os, 'write', real_write)   # space again
        node.handle_events(node.session.add_sample(samples[9]))
        assert 'not yet saved' not in node.diagnostic_status().message
        written = [s.stamp_ns for s in journal.read_journal(path).samples]
        assert written == [s.stamp_ns for s in samples[:10]]   # in order, no gap
        log = capfd.readouterr().err
        assert (f'the 2 captured sample(s) that could not be written are now saved to {path}'
                in log), log
        assert re.search(r'sample 9 captured at stamp [^\n]* m\)\n', log), log


def test_a_due_full_solve_is_the_one_estimate_the_node_publishes(tmp_path, monkeypatch,
                                                                 domain_id):
    _, samples = synthetic_samples(20, seed=4)
    path = tmp_path / 'samples.csv'
    with resumed_node(domain_id, path, samples[:19]) as node:
        published = []
        publish = node.rotation_publisher.publish
        monkeypatch.setattr(node.rotation_publisher, 'publish',
                            lambda msg: published.append(rotation_of(msg)) or publish(msg))
        # The 20th sample: the node asks for its estimate, and a full solve falls due.
        node.handle_events(node.session.add_sample(samples[19]))
        expected = calibration.calibrate(journal.read_journal(path).samples)
        assert len(published) == 1
        assert_allclose(published[0], canonical(expected.quaternion), atol=1e-12)
        assert node.session.estimate() == []


def test_a_moved_marker_makes_the_node_warn_and_suggest_a_reset(rig_factory, tmp_path, capfd):
    rng = np.random.default_rng(12)
    cell = simulation.random_cell(rng)
    rig = rig_factory(Parameter('samples_file', value=str(tmp_path / 'samples.csv')),
                      Parameter('still_window_s', value=0.3))
    stops = random_stops(rng, cell, 10)
    turn = Pose(np.zeros(3), quat.from_axis_angle([0.0, 0.6, 0.8], np.radians(3.0)))
    start = simulation.DEFAULT_START_NS
    for k, link in enumerate(stops):
        sensor = cell.sensor_pose(link)
        if k >= 7:    # the marker was bumped before the eighth stop
            base_sensor = link @ cell.mounting
            sensor = base_sensor.inverse() @ turn @ base_sensor @ sensor
        rig.still(link, sensor, start + k * NS)
        rig.spin_until(lambda: len(rig.node.session.samples) == k + 1, what=f'sample {k}')
        status = rig.node.diagnostic_status()
        moved = 'has the marker or the sensor moved? call ~/reset and recollect'
        assert (moved in status.message) == (k >= 9), (k, status.message)
    assert status.level == status.WARN
    rise = re.search(r'the residual rose from ([0-9.]+) to ([0-9.]+) deg over the last 3 '
                     r'samples \(from sample 7 on\)', status.message)
    assert rise and float(rise[1]) < 0.5 and 2.0 < float(rise[2]) < 4.0, status.message
    log = capfd.readouterr().err
    assert log.count(moved) == 1 and '[WARN]' in log
    assert rig.call('reset').success
    assert moved not in rig.node.diagnostic_status().message


def test_save_keeps_the_old_result_when_the_write_fails(rig_factory, tmp_path, monkeypatch):
    _, samples = synthetic_samples(6)
    path = tmp_path / 'samples.csv'
    write_journal(path, samples)
    result_file = tmp_path / 'calibration.yaml'
    rig = rig_factory(Parameter('samples_file', value=str(path)),
                      Parameter('resume', value=True),
                      Parameter('result_file', value=str(result_file)))
    assert rig.call('save').success
    old = result_file.read_bytes()
    assert persistence.read_result_yaml(result_file)['quality']['samples'] == 6

    def failing_fsync(fd):   # the temporary file cannot be made durable: the write fails
        raise OSError(5, 'Input/output error')

    monkeypatch.setattr(persistence.os, 'fsync', failing_fsync)
    refused = rig.call('save')
    assert not refused.success and 'Input/output error' in refused.message
    assert result_file.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()
                  if 'calibration' in p.name) == ['calibration.yaml']   # no temporary left


def test_a_stalled_stream_makes_no_sample_from_stale_data():
    """The sensor stalls from the middle of one stop to the middle of the next."""
    rng = np.random.default_rng(4)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(
        rng, cell, n_stops=8, link_rate_hz=100.0, sensor_rate_hz=30.0, still_s=1.0,
        move_s=1.0, rotation_noise_deg=0.1)
    stall = [sum(streams.stills[k]) // 2 for k in (3, 4)]
    session = Session()
    captured = []
    for _, name, stamp, pose in stream_events(streams):
        if name == 'sensor_pose' and stall[0] < stamp < stall[1]:
            continue
        add = session.add_link_pose if name == 'link_pose' else session.add_sensor_pose
        captured += [e.sample for e in add(stamp, pose) if isinstance(e, SampleCaptured)]
    session.estimate()
    assert len(captured) == 8          # every stop, the stalled ones from their fresh halves
    for sample in captured:            # each at a real stop: no sample spans the motion
        assert min(quat.angle_between(sample.link.quaternion, stop.quaternion)
                   for stop in streams.stops) < np.radians(0.05)
    assert quat.angle_between(session.result.quaternion, cell.mounting.quaternion) \
        < np.radians(3 * session.result.uncertainty_deg)
    assert streams.stills[3][0] < captured[3].stamp_ns < stall[0]
    assert stall[1] < captured[4].stamp_ns < streams.stills[4][1]


# --- point 5: files are data -----------------------------------------------------------------

def test_result_reader_refuses_python_tags(tmp_path):
    path = tmp_path / 'calibration.yaml'
    path.write_text('format: quatcal_ros/rotation\n'
                    'rotation: !!python/object/apply:os.system ["touch pwned"]\n')
    with pytest.raises(ValueError, match=r'calibration.yaml, line 2: refused: not plain data'):
        persistence.read_result_yaml(path)
    assert not (tmp_path / 'pwned').exists() and not Path('pwned').exists()
    path.write_text('rotation: {x: 0, y: 0\n')
    with pytest.raises(ValueError, match='not readable YAML'):
        persistence.read_result_yaml(path)
    path.write_text('- 1\n- 2\n')
    with pytest.raises(ValueError, match='no mapping'):
        persistence.read_result_yaml(path)


def unsafe_calls(tree):
    """Yield (line, what) for each construct of `tree` (ast) that can run code from data."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [alias.name for alias in node.names] + [getattr(node, 'module', '') or '']
            for name in names:
                if name.split('.')[0] in ('pickle', 'cPickle', 'dill', 'marshal', 'shelve'):
                    yield node.lineno, f'import {name}'
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.id if isinstance(func, ast.Name) else getattr(func, 'attr', '')
            owner = getattr(getattr(func, 'value', None), 'id', '')
            if name in ('eval', 'exec', 'unsafe_load', 'full_load', 'system', 'popen') or (
                    owner == 'yaml' and name in ('load', 'load_all')):
                yield node.lineno, f'{owner + "." if owner else ""}{name}()'
            for keyword in node.keywords:
                if keyword.arg in ('shell', 'allow_pickle') and getattr(
                        keyword.value, 'value', False) is True:
                    yield node.lineno, f'{keyword.arg}=True'


def test_unsafe_calls_are_found():
    code = ('import pickle\nimport yaml\nyaml.load(s)\neval(t)\n'
            'subprocess.run(c, shell=True)\nnp.load(f, allow_pickle=True)\n')
    assert [line for line, _ in unsafe_calls(ast.parse(code))] == [1, 3, 4, 5, 6]


def test_no_code_from_data_in_the_package():
    """Point 5: no pickle, eval, exec, unsafe YAML or shell in the package's code."""
    hits = []
    for source in sorted((REPO_ROOT / 'quatcal_ros').rglob('*.py')):
        tree = ast.parse(source.read_text(), str(source))
        where = source.relative_to(REPO_ROOT)
        hits += [f'{where}:{line}: {what}' for line, what in unsafe_calls(tree)]
    assert hits == []


# --- as processes: SIGKILL in the middle of a session ---------------------------------------

def _process_env(home, domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
               HOME=str(home))
    env['PYTHONPATH'] = os.pathsep.join(
        [str(REPO_ROOT)] + [p for p in [env.get('PYTHONPATH')] if p])
    return env


def _calibrator_command(*ros_args):
    return [sys.executable, '-m', 'quatcal_ros', 'calibrator', '--ros-args', *ros_args]


class Feeder(ProcessWatcher):
    """Publishes the stream to the calibrator process and listens to its outputs."""

    def __init__(self, events, domain_id):
        super().__init__('resume_test_feeder', domain_id)
        self.events = events
        self.next = 0
        self.publishers = {name: self.node.create_publisher(PoseStamped, name, RELIABLE)
                           for name in ('link_pose', 'sensor_pose')}

    def connect(self, process):
        self.spin_until(lambda: all(p.get_subscription_count()
                                    for p in self.publishers.values()),
                        60.0, 'the calibrator to subscribe', (process,))
        settle = time.monotonic() + 0.5    # and for the other side to match ours
        while time.monotonic() < settle:
            self.executor.spin_once(timeout_sec=0.05)

    def feed_until(self, condition, process, speed=4.0, timeout=60.0):
        """Publish the events in delivery order at `speed` x real time until condition()."""
        wall0, stream0 = time.monotonic(), self.events[self.next][0]
        deadline = wall0 + timeout
        while not condition():
            assert process.poll() is None, f'the calibrator exited with {process.returncode}'
            assert self.next < len(self.events), 'the stream ended first'
            assert time.monotonic() < deadline, 'timed out feeding the stream'
            due = stream0 + (time.monotonic() - wall0) * speed * NS
            while self.next < len(self.events) and self.events[self.next][0] <= due:
                _, name, stamp, pose = self.events[self.next]
                self.publishers[name].publish(conversions.pose_stamped_msg(pose, stamp, 'f'))
                self.next += 1
            self.executor.spin_once(timeout_sec=0.02)

    def samples_reported(self):
        return int(status_values(self.statuses[-1])['samples']) if self.statuses else None


def journal_count(path):
    try:
        return len(journal.read_journal(path).samples)
    except (FileNotFoundError, journal.JournalError):
        return 0


def test_a_shutdown_between_executor_steps_ends_the_spin_quietly(monkeypatch):
    """The RCLError of a step on a context a signal shut down is a stop, not a crash."""
    from quatcal_ros.ros import spin

    class Stub:
        destroyed = 0

        def destroy_node(self):
            self.destroyed += 1

    def spin_on_a_dead_context(node, executor):
        raise RuntimeError('failed to initialize wait set: the given context is not valid')
    monkeypatch.setattr(spin.rclpy, 'spin', spin_on_a_dead_context)
    monkeypatch.setattr(spin.rclpy, 'try_shutdown', lambda: None)
    monkeypatch.setattr(spin.rclpy, 'ok', lambda: False)
    stub = Stub()
    spin.spin_until_stopped(stub, None)           # returns: the context is down
    monkeypatch.setattr(spin.rclpy, 'ok', lambda: True)
    with pytest.raises(RuntimeError, match='context is not valid'):
        spin.spin_until_stopped(stub, None)       # a live context: a real error
    assert stub.destroyed == 2                    # the node is destroyed either way


def test_sigkill_mid_session_loses_no_sample_and_resume_continues(tmp_path, process_domain_id):
    rng = np.random.default_rng(21)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(
        rng, cell, n_stops=24, link_rate_hz=50.0, sensor_rate_hz=30.0, still_s=0.7,
        move_s=0.4, rotation_noise_deg=0.1, translation_noise_m=0.0005,
        rotation_spread_deg=40.0)
    samples_file = tmp_path / 'journal' / 'samples.csv'
    ros_args = ['-p', f'samples_file:={samples_file}', '-p', 'still_window_s:=0.3',
                '-p', 'diagnostics_period_s:=0.2', '-p', 'max_stamp_offset_s:=0.0']
    feeder = Feeder(stream_events(streams), process_domain_id)
    env = _process_env(tmp_path, process_domain_id)
    first_log, second_log = tmp_path / 'first.log', tmp_path / 'second.log'
    process = subprocess.Popen(_calibrator_command(*ros_args), env=env, cwd=tmp_path,
                               stdout=first_log.open('w'), stderr=subprocess.STDOUT)
    try:
        feeder.connect(process)
        # Killed as soon as the sixth sample is on disk, with more poses in flight.
        feeder.feed_until(lambda: journal_count(samples_file) >= 6, process)
        process.send_signal(signal.SIGKILL)
        assert process.wait(timeout=10) == -signal.SIGKILL

        # No sample the node reported captured is missing from the journal.
        logged = [(int(i), float(stamp)) for i, stamp in SAMPLE_LOG.findall(
            first_log.read_text())]
        contents = journal.read_journal(samples_file)
        kept = contents.samples
        assert [i for i, _ in logged] == list(range(len(logged)))
        assert len(kept) >= 6
        # Written before it is logged: at most one sample on disk but not yet reported.
        assert len(logged) <= len(kept) <= len(logged) + 1
        for i, stamp in logged:
            assert abs(kept[i].stamp_ns * 1e-9 - stamp) < 6e-4
        assert len(contents.notices) <= 1                    # a torn last line at most
        intact = samples_file.read_bytes()[:contents.intact_bytes]

        # Restart with resume:=true: same samples, the estimate of calibrate() on them.
        options = settings.session_config(Settings(still_window_s=0.3)).calibration
        expected = calibration.calibrate(kept, options)
        feeder.rotations.clear()
        feeder.statuses.clear()
        process = subprocess.Popen(_calibrator_command(*ros_args, '-p', 'resume:=true'),
                                   env=env, cwd=tmp_path, stdout=second_log.open('w'),
                                   stderr=subprocess.STDOUT)
        # Messages the killed node sent may still wait in the readers: wait for the new
        # node's, which are the resumed samples' (a timeout here means they never came).
        resumed = canonical(expected.quaternion)

        def resumed_estimate():
            return (feeder.statuses and feeder.samples_reported() == len(kept)
                    and feeder.rotations and np.allclose(
                        rotation_of(feeder.rotations[-1]), resumed, rtol=0, atol=1e-9))
        feeder.spin_until(resumed_estimate, 60.0, 'the resumed estimate and diagnostics',
                          (process,))
        assert f'resumed {len(kept)} samples from {samples_file}' in second_log.read_text()

        # The stream goes on: new samples are taken and appended after the resumed ones.
        feeder.connect(process)
        feeder.feed_until(lambda: journal_count(samples_file) >= len(kept) + 3, process)
        feeder.spin_until(lambda: feeder.samples_reported() == journal_count(samples_file),
                          10.0, 'diagnostics to count the journal', (process,))
    finally:
        code = stop_process(process, signal.SIGINT, timeout=20)   # killed if it hangs
        feeder.close()
    assert code == 0, second_log.read_text()
    final = journal.read_journal(samples_file)
    assert final.notices == []
    assert samples_file.read_bytes().startswith(intact)
    log = second_log.read_text()
    assert f'sample {len(kept)} captured' in log
    assert aside_files(samples_file.parent, 'previous') == []
    assert aside_files(samples_file.parent, 'corrupt') == []


def test_process_refuses_to_resume_another_setup_with_exit_2(tmp_path, process_domain_id):
    _, samples = synthetic_samples(4)
    path = tmp_path / 'samples.csv'
    before = write_journal(path, samples, JournalHeader('eye_to_hand', 'tool0', 'camera'))
    done = subprocess.run(
        _calibrator_command('-p', f'samples_file:={path}', '-p', 'resume:=true'),
        env=_process_env(tmp_path, process_domain_id), cwd=tmp_path, capture_output=True,
        text=True, timeout=60)
    output = done.stdout + done.stderr
    assert done.returncode == 2, output
    assert 'resume:=true refused' in output and "setup 'eye_to_hand'" in output
    assert 'resume:=false to move it aside' in output
    assert path.read_bytes() == before
