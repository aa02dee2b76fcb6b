"""
README promises of the calibrator node that no other test checked at node level.

- The journal deleted, moved or replaced while the node runs (README section 4): with the
  next sample it is re-created with every sample of the session, a file put in its place is
  moved aside first, and an ERROR says what happened.
- `parameters changed: ...` (section 3, parameters): logged once per runtime change, never for
  a refused or unchanged value; the estimate stays for the presentation parameters.
- `~/save` with `easy_handeye2_file` set at runtime to a path under `~` (eye-to-hand): the
  file exists, parses, holds only easy_handeye2's keys and the published transform.
- The /diagnostics keys of the leave-one-out validation and `paired_poses`, with values
  checked against the estimate and the poses sent.
- SCARA and gantry cells (section 2): a warning with every estimate, the log repeating it at
  most every 5 s (on a clock of the test's), and every warning of an estimate logged.

The node runs in-process (rclpy style) with a driver node in one private context, on a domain
id reserved on this host (conftest's domain_id); its log is read with capfd.  Every file the
node writes is under the test's tmp_path.
"""

from dataclasses import replace
import re

from diagnostic_msgs.msg import DiagnosticArray
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import TransformStamped
from journal_files import aside_files
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files import journal
from quatcal_ros.ros import conversions
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import harnesses_of
from ros_harness import LATCHED
from ros_harness import SpinMixin
from std_srvs.srv import Trigger
import yaml

NS = NS_PER_S
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
# The frames of each stream's messages: those the node's defaults expect.
FRAMES = {'link_pose': 'base_link', 'sensor_pose': 'camera'}
SCARA_WARNING = 'the link turns about one axis only'
CONVENTION_WARNING = 'the samples fit a rigid mounting far better with setup'


class Rig(SpinMixin):
    """A calibrator node (its files in tmp_path) and a driver node in one private context."""

    spin_timeout = 20.0

    def __init__(self, domain_id, tmp_path, overrides=()):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.journal_path = tmp_path / 'journal' / 'samples.csv'
        # The simulated stamps are in 2023: no check of stamps against the node clock.
        overrides = [Parameter('max_stamp_offset_s', value=0.0),
                     Parameter('diagnostics_period_s', value=0.2),
                     Parameter('samples_file', value=str(self.journal_path)),
                     Parameter('result_file', value=str(tmp_path / 'result.yaml')),
                     *overrides]
        try:
            self.node = CalibratorNode(context=self.context, parameter_overrides=overrides)
        except Exception:
            rclpy.try_shutdown(context=self.context)
            raise
        self.driver = rclpy.create_node('promises_test_driver', context=self.context)
        self.publishers = {name: self.driver.create_publisher(PoseStamped, name, RELIABLE)
                           for name in ('link_pose', 'sensor_pose')}
        self.sent = {'link_pose': 0, 'sensor_pose': 0}
        self.diagnostics, self.transforms = [], []
        self.driver.create_subscription(DiagnosticArray, '/diagnostics',
                                        self.diagnostics.append, 10)
        self.driver.create_subscription(TransformStamped, '/calibrator/transform',
                                        self.transforms.append, LATCHED)
        self.save_client = self.driver.create_client(Trigger, '/calibrator/save')
        self.parameters = AsyncParameterClient(self.driver, 'calibrator')
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: all(p.get_subscription_count() for p in self.publishers.values())
                        and self.save_client.service_is_ready()
                        and self.parameters.services_are_ready(),
                        what='discovery of the calibrator')

    def publish_still(self, cell, link, start_ns, duration_s=0.8, rate_hz=25.0):
        """Publish both streams at rate_hz holding `link` (noise-free sensor); wait for them."""
        sensor = cell.sensor_pose(link)
        for i in range(int(duration_s * rate_hz)):
            stamp = start_ns + int(i * NS / rate_hz)
            for name, pose in (('link_pose', link), ('sensor_pose', sensor)):
                self.publishers[name].publish(conversions.pose_stamped_msg(pose, stamp,
                                                                           FRAMES[name]))
                self.sent[name] += 1
        received = self.node.stats.received
        self.spin_until(lambda: all(received[name] >= self.sent[name] for name in self.sent),
                        what='the node to receive the poses')

    def add_samples(self, samples):
        """Hand samples to the session as a resumed journal does; handle what it says."""
        self.node.handle_events(self.node.session.add_samples(samples))

    def set_parameters(self, *parameters, atomically=False):
        """Set parameters through the node's parameter services (as `ros2 param set` does)."""
        if atomically:
            future = self.parameters.set_parameters_atomically(list(parameters))
        else:
            future = self.parameters.set_parameters(list(parameters))
        self.spin_until(future.done, what='the set_parameters service')
        response = future.result()
        return [response.result] if atomically else list(response.results)

    def call_save(self):
        future = self.save_client.call_async(Trigger.Request())
        self.spin_until(future.done, what='~/save')
        return future.result()


@pytest.fixture
def rig_factory(domain_id, tmp_path):
    for make in harnesses_of(Rig, domain_id):
        yield lambda *overrides: make(tmp_path, overrides)


def values_of(status):
    return {kv.key: kv.value for kv in status.values}


def log_lines(text, level, words):
    """Return the lines of the node's log `text` at `level` ('WARN', ...) containing words."""
    return [line for line in text.splitlines()
            if line.startswith(f'[{level}]') and '[calibrator]' in line and words in line]


def assert_same_samples(found, expected):
    assert [s.stamp_ns for s in found] == [s.stamp_ns for s in expected]
    for a, b in zip(found, expected):
        np.testing.assert_allclose(a.link.position, b.link.position, atol=1e-12)
        np.testing.assert_allclose(a.sensor.position, b.sensor.position, atol=1e-12)
        assert quat.angle_between(a.link.quaternion, b.link.quaternion) < 1e-9
        assert quat.angle_between(a.sensor.quaternion, b.sensor.quaternion) < 1e-9


# --- the journal deleted, moved or replaced while the node runs ------------------------------

@pytest.mark.parametrize('what', ['deleted', 'moved', 'replaced'])
def test_a_journal_lost_while_the_node_runs_is_re_created_with_every_sample(
        rig_factory, tmp_path, capfd, what):
    rig = rig_factory()
    path = rig.journal_path
    rng = np.random.default_rng(12)
    cell = simulation.random_cell(rng)
    stops = simulation.stop_poses(rng, cell, 4)
    start = simulation.DEFAULT_START_NS

    def capture(k):
        rig.publish_still(cell, stops[k], start + 2 * k * NS)
        rig.spin_until(lambda: len(rig.node.session.samples) == k + 1, what=f'sample {k}')
        return rig.node.session.samples

    for k in range(2):
        samples = capture(k)
    assert_same_samples(journal.read_journal(path).samples, samples)
    moved_to = tmp_path / 'elsewhere.csv'
    if what == 'moved':
        path.rename(moved_to)
    else:
        path.unlink()   # someone cleans up ~/.ros
    if what == 'replaced':
        path.write_text("somebody else's notes\n")
    capfd.readouterr()

    samples = capture(2)
    assert_same_samples(journal.read_journal(path).samples, samples)
    errors = log_lines(capfd.readouterr().err, 'ERROR', '')
    assert [line.split(']: ', 1)[1] for line in errors] == [
        f'{path} was deleted or replaced while the node ran (it held 2 samples): re-created '
        'with all 3 samples of the session'], errors
    assert rig.node.journal.problem is None

    # From then on the re-created journal takes the samples as usual, without a word.
    samples = capture(3)
    assert_same_samples(journal.read_journal(path).samples, samples)
    assert len(samples) == 4
    assert log_lines(capfd.readouterr().err, 'ERROR', '') == []
    assert str(path) not in rig.next_status(
        lambda s: values_of(s)['samples'] == '4').message
    # Nothing is ever deleted or overwritten: what was moved or put there is kept.
    if what == 'moved':
        assert_same_samples(journal.read_journal(moved_to).samples, samples[:2])
    asides = aside_files(path.parent, 'previous')
    if what == 'replaced':
        assert [p.read_text() for p in asides] == ["somebody else's notes\n"]
    else:
        assert asides == []


# --- "parameters changed: ..." ---------------------------------------------------------------

def test_parameters_changed_is_logged_once_per_change(rig_factory, capfd):
    rig = rig_factory()
    rng = np.random.default_rng(31)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 8, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    rig.add_samples(samples)
    assert rig.node.session.result is not None
    capfd.readouterr()

    def logged():
        text = capfd.readouterr().err
        return (log_lines(text, 'INFO', 'parameters changed:'),
                log_lines(text, 'INFO', 're-estimating from the'))

    (done,) = rig.set_parameters(Parameter('robust', value=False))
    assert done.successful, done.reason
    changed, re_estimates = logged()
    assert [line.split(']: ')[1] for line in changed] == ['parameters changed: robust']
    assert [line.split(']: ')[1] for line in re_estimates] == [
        're-estimating from the 8 samples with the new settings']

    # The same value again is no change; a refused value changes nothing: no line.
    (same,) = rig.set_parameters(Parameter('robust', value=False))
    (refused,) = rig.set_parameters(Parameter('pairs', value='some'))
    assert same.successful and not refused.successful
    assert logged() == ([], [])

    # Two parameters set at once: one change, one line naming both.
    (done,) = rig.set_parameters(Parameter('method', value='closed-form'),
                                 Parameter('pairs', value='consecutive'), atomically=True)
    assert done.successful, done.reason
    changed, re_estimates = logged()
    assert [line.split(']: ')[1] for line in changed] == ['parameters changed: pairs, method']
    assert len(re_estimates) == 1
    assert rig.node.session.result.method == 'closed-form'

    # Two set one after the other: two changes, two lines.  Output-only parameters are logged
    # as changed, and the estimate stays (no re-estimate).
    before = rig.node.session.result
    results = rig.set_parameters(Parameter('sensor_frame', value='cam'),
                                 Parameter('max_position_m', value=50.0))
    assert all(r.successful for r in results)
    changed, re_estimates = logged()
    assert [line.split(']: ')[1] for line in changed] == [
        'parameters changed: sensor_frame', 'parameters changed: max_position_m']
    assert re_estimates == [] and rig.node.session.result is before


# --- ~/save writes easy_handeye2's file ------------------------------------------------------

def test_save_writes_the_easy_handeye2_file_named_at_runtime_under_home(
        rig_factory, tmp_path, monkeypatch):
    """Eye-to-hand, easy_handeye2_file set by `ros2 param set` to the README's ~ path."""
    monkeypatch.setenv('HOME', str(tmp_path))   # ~ of the node: the test's own directory
    rig = rig_factory(Parameter('setup', value='eye_to_hand'))
    rng = np.random.default_rng(44)
    cell = simulation.random_cell(rng, 'eye_to_hand')
    samples, _ = simulation.samples(rng, cell, 10, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    rig.add_samples(samples)
    result = rig.node.session.result
    assert result is not None
    (done,) = rig.set_parameters(Parameter(
        'easy_handeye2_file', value='~/.ros2/easy_handeye2/calibrations/cell_a.calib'))
    assert done.successful, done.reason
    assert rig.node.session.result is result   # an output parameter: the estimate stays
    rig.spin_until(lambda: rig.transforms, what='the latched ~/transform')
    published = rig.transforms[-1]

    calib = tmp_path / '.ros2' / 'easy_handeye2' / 'calibrations' / 'cell_a.calib'
    saved = rig.call_save()
    assert saved.success, saved.message
    assert f'easy_handeye2 layout saved to {calib}' in saved.message
    document = yaml.safe_load(calib.read_text())
    assert set(document) == {'parameters', 'transform'}    # easy_handeye2 refuses others
    parameters = document['parameters']
    assert {'name', 'calibration_type', 'robot_base_frame', 'robot_effector_frame',
            'tracking_base_frame', 'tracking_marker_frame'} <= set(parameters)
    assert parameters['name'] == 'cell_a'
    assert parameters['calibration_type'] == 'eye_on_base'
    assert parameters['robot_base_frame'] == published.header.frame_id == 'base_link'
    assert parameters['tracking_base_frame'] == published.child_frame_id == 'camera'
    t = published.transform.translation
    q = published.transform.rotation
    np.testing.assert_allclose([document['transform']['translation'][k] for k in 'xyz'],
                               [t.x, t.y, t.z], atol=1e-12)
    written = quat.wxyz_from_xyzw([document['transform']['rotation'][k] for k in 'xyzw'])
    assert np.degrees(quat.angle_between(written, [q.w, q.x, q.y, q.z])) < 1e-9
    # And that transform is the mounting base -> camera of the simulated cell.
    assert np.linalg.norm([t.x, t.y, t.z] - cell.mounting.position) < 0.005
    assert np.degrees(quat.angle_between(written, cell.mounting.quaternion)) < 0.5


# --- /diagnostics keys -----------------------------------------------------------------------

def test_diagnostics_carry_the_leave_one_out_validation(rig_factory):
    rig = rig_factory()
    rng = np.random.default_rng(58)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    # One sample whose sensor position is 8 mm off: the worst predicted by the others.
    shifted = 7
    off = samples[shifted].sensor
    samples[shifted] = replace(samples[shifted], sensor=Pose(
        off.position + np.array([0.008, 0.0, 0.0]), off.quaternion))

    rig.add_samples(samples[:5])   # below 6 good samples: no verdict yet
    values = values_of(rig.next_status(lambda s: values_of(s)['samples'] == '5'))
    assert values['state'] == 'estimating' and values['validation'] == 'unknown'
    assert values['validation_rms_rotation_deg'] == ''
    assert values['validation_rms_translation_mm'] == ''
    assert values['validation_worst_samples'] == ''

    rig.add_samples(samples[5:])
    result = rig.node.session.result
    status = rig.next_status(lambda s: values_of(s)['samples'] == '12')
    values = values_of(status)
    assert values['validation'] == 'pass' == result.validation['verdict']
    rotation = float(values['validation_rms_rotation_deg'])
    translation = float(values['validation_rms_translation_mm'])
    assert rotation == pytest.approx(result.validation['rms_rotation_deg'], rel=1e-5)
    assert translation == pytest.approx(result.validation['rms_translation_mm'], rel=1e-5)
    assert values['validation_rms_reprojection_px'] == ''   # (camera images only)
    # Of the order of the noise (0.1 deg, 0.5 mm per axis, and one sample 8 mm off).
    assert 0.05 < rotation < 1.0
    assert 0.5 < translation < 10.0
    worst = [int(k) for k in values['validation_worst_samples'].split()]
    assert len(worst) == len(set(worst)) == 3 and all(0 <= k < 12 for k in worst)
    assert worst[0] == shifted
    errors = {e['sample']: e['translation_mm'] for e in result.validation['samples']}
    assert errors[shifted] == max(errors.values()) > 5.0
    # The other counts of the estimate, against what it holds.
    assert values['motions'] == str(12 * 11 // 2) == str(result.motions)
    assert 0 < int(values['inliers']) <= int(values['motions'])
    assert float(values['residual_rms_deg']) == pytest.approx(result.residual_rms_deg, rel=1e-5)
    assert values['hint'] == result.hint
    assert values['paired_poses'] == '0'   # the samples came whole, not from pose streams

    # A validation that fails makes the level WARN and says why.
    (done,) = rig.node.set_parameters([Parameter('validation_max_translation_mm', value=0.5)])
    assert done.successful
    status = rig.next_status(lambda s: values_of(s)['validation'] == 'fail')
    assert status.level == DiagnosticStatus.WARN
    assert 'validation failed: leave-one-out prediction errors (RMS) above the thresholds: ' \
        f'translation {translation:.2f} mm > 0.5 mm' in status.message


def test_diagnostics_count_the_paired_poses(rig_factory):
    rig = rig_factory()
    rng = np.random.default_rng(63)
    cell = simulation.random_cell(rng)
    start = simulation.DEFAULT_START_NS
    stops = simulation.stop_poses(rng, cell, 2)
    rig.publish_still(cell, stops[0], start)
    values = values_of(rig.next_status(lambda s: values_of(s)['sensor_messages'] == '20'))
    # Every sensor pose has a link pose at its stamp: each is paired, none twice.
    assert values['paired_poses'] == '20' == str(rig.node.session.counters['pairs'])
    # A sensor pose in a gap of the link stream (none within max_gap_s of it) is not paired.
    rig.publishers['sensor_pose'].publish(conversions.pose_stamped_msg(
        cell.sensor_pose(stops[0]), start + 4 * NS, FRAMES['sensor_pose']))
    rig.sent['sensor_pose'] += 1
    rig.publish_still(cell, stops[1], start + 8 * NS, duration_s=0.4)
    values = values_of(rig.next_status(lambda s: values_of(s)['sensor_messages'] == '31'))
    assert values['paired_poses'] == '30'
    assert values['bad_messages'] == '0' and values['rejected_messages'] == '0'


# --- SCARA and gantry cells: the warning, throttled ------------------------------------------

@pytest.mark.parametrize('kind', ['scara', 'gantry'])
def test_a_reduced_dof_cell_warns_with_every_estimate_and_logs_it_once_then_rarely(
        rig_factory, capfd, kind):
    rig = rig_factory()
    now_s = [1_000.0]
    rig.node.log.clock = lambda: now_s[0]   # the throttle's clock, moved by the test
    rng = np.random.default_rng(71)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 12, kind, 0.05, 0.0005)
    words = SCARA_WARNING if kind == 'scara' else 'the link never turns'
    logged = []
    # (seconds on the throttle's clock, samples so far, warning lines logged so far): in full
    # once, then shortened ('still: ...') once a minute while every estimate repeats it
    for at_s, count, expected in ((0.0, 4, 1), (1.0, 6, 1), (5.5, 8, 1), (59.0, 10, 1),
                                  (60.5, 12, 2)):
        now_s[0] = 1_000.0 + at_s
        rig.add_samples(samples[len(rig.node.session.samples):count])
        result = rig.node.session.result
        assert result is not None and result.samples == count
        assert any(words in w for w in result.warnings)
        status = rig.node.diagnostic_status()
        assert status.level == DiagnosticStatus.WARN and words in status.message
        text = capfd.readouterr().err
        assert len(log_lines(text, 'INFO', f'from {count} samples')) == 1   # the estimate
        logged += log_lines(text, 'WARN', words)
        assert len(logged) == expected, (at_s, logged)
    assert 'still: ' + words in logged[1] and 'still: ' not in logged[0]


def test_every_warning_of_a_reduced_dof_estimate_reaches_the_log(rig_factory, capfd):
    # A SCARA cell calibrated with the sensor poses taken as inverted: two warnings.
    rig = rig_factory(Parameter('invert_sensor', value=True))
    rng = np.random.default_rng(72)
    cell = simulation.random_cell(rng)
    rig.add_samples(simulation.reduced_dof_samples(rng, cell, 12, 'scara', 0.05, 0.0005))
    warnings = rig.node.session.result.warnings
    assert [w[:len(SCARA_WARNING)] for w in warnings[:1]] == [SCARA_WARNING]
    # the fix named: the sensor poses are not inverted (and nothing about the setup)
    assert any(CONVENTION_WARNING in w and 'drop --invert-sensor' in w and '--setup' not in w
               for w in warnings)
    status = rig.node.diagnostic_status()
    assert SCARA_WARNING in status.message and CONVENTION_WARNING in status.message
    text = capfd.readouterr().err
    assert len(log_lines(text, 'WARN', SCARA_WARNING)) == 1
    assert len(log_lines(text, 'WARN', CONVENTION_WARNING)) == 1, re.findall(
        r'\[WARN\].*', text)
    # ~/save saves it, as asked, and its reply carries the warnings (it said only 'saved to'),
    # with the failed validation's as the saved file has it
    saved = rig.call_save()
    failed = int(rig.node.session.result.validation['verdict'] == 'fail')
    assert saved.success and f'the estimate has {len(warnings) + failed} warning(s), in the ' \
        f'file too: {SCARA_WARNING}' in saved.message
    # An estimate not to use is said first (test_node_transform); this one may be used.
    assert rig.node.session.result.usable and saved.message.startswith('saved to ')
