"""
The node's result outputs for the ROS ecosystem, over real DDS (in-process, rclpy style).

~/transform (TransformStamped link_frame -> sensor_frame, latched), the /diagnostics values
of the full result, publish_tf (tf2_ros present or not), and ~/save's easy_handeye2 file and
static_transform_publisher line.  Samples are handed to the node's session the way a resumed
samples journal is (session.add_samples, then handle_events); the pose-topic input path is
tested in test_node.py.  A domain id reserved on this host (conftest's domain_id) keeps these
tests apart from everything else.
"""

import dataclasses

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
from rcl_interfaces.msg import Log
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import SpinMixin
from std_msgs.msg import Bool
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
import yaml

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
ROSOUT = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Harness(SpinMixin):
    """A calibrator node and a driver node (rosout, diagnostics, services) in one context."""

    def __init__(self, domain_id, tmp_path, overrides=()):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.driver = rclpy.create_node('transform_test_driver', context=self.context)
        self.logs = []
        self.diagnostics = []
        self.driver.create_subscription(Log, '/rosout', self.logs.append, ROSOUT)
        self.driver.create_subscription(DiagnosticArray, '/diagnostics',
                                        self.diagnostics.append, 10)
        overrides = [Parameter('max_stamp_offset_s', value=0.0),
                     Parameter('diagnostics_period_s', value=0.2),
                     Parameter('samples_file', value=str(tmp_path / 'journal.csv')),
                     Parameter('result_file', value=str(tmp_path / 'result.yaml')),
                     *overrides]
        self.node = CalibratorNode(context=self.context, parameter_overrides=overrides)
        self.save = self.driver.create_client(Trigger, '/calibrator/save')
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(self.save.service_is_ready, what='the ~/save service')

    def add_samples(self, samples):
        """Hand samples to the node's session and let it publish, as a resumed journal does."""
        self.node.handle_events(self.node.session.add_samples(samples))

    def call_save(self):
        future = self.save.call_async(Trigger.Request())
        self.spin_until(future.done, what='~/save')
        return future.result()

    def subscribe_transform(self):
        """Subscribe ~/transform late (latched QoS); return the list of messages received."""
        received = []
        self.driver.create_subscription(TransformStamped, '/calibrator/transform',
                                        received.append, LATCHED)
        return received

    def subscribe_tf_static(self):
        """Subscribe /tf_static as tf2 listeners do; return the list of messages received."""
        received = []
        self.driver.create_subscription(TFMessage, '/tf_static', received.append, LATCHED)
        return received

    def node_logs(self, level=None, text=''):
        return [log.msg for log in self.logs if log.name == 'calibrator'
                and (level is None or log.level == level) and text in log.msg]


@pytest.fixture
def make_harness(domain_id, tmp_path):
    made = []

    def make(overrides=()):
        made.append(Harness(domain_id, tmp_path, overrides))
        return made[-1]
    yield make
    for harness in made:
        harness.close()


@pytest.fixture(scope='module')
def cell_and_samples():
    rng = np.random.default_rng(81)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    return cell, samples


def rotation_wxyz(transform):
    q = transform.rotation
    return np.array([q.w, q.x, q.y, q.z])


def translation(transform):
    t = transform.translation
    return np.array([t.x, t.y, t.z])


def values_of(status):
    return {kv.key: kv.value for kv in status.values}


def test_transform_is_latched_with_frames_and_values(make_harness, cell_and_samples,
                                                     tmp_path):
    cell, samples = cell_and_samples
    calib = tmp_path / 'calibrations' / 'arm.calib'
    h = make_harness([Parameter('link_frame', value='flange'),
                      Parameter('sensor_frame', value='cam'),
                      Parameter('link_frame_id', value='base_link'),
                      Parameter('easy_handeye2_file', value=str(calib))])
    h.add_samples(samples)
    result = h.node.session.result
    assert result is not None and result.method == 'refined'

    # Published before anyone listened: a late joiner gets it (reliable + transient local).
    received = h.subscribe_transform()
    h.spin_until(lambda: received, what='the latched ~/transform')
    msg = received[-1]
    assert msg.header.frame_id == 'flange' and msg.child_frame_id == 'cam'
    np.testing.assert_allclose(translation(msg.transform), result.translation, atol=1e-12)
    assert quat.angle_between(rotation_wxyz(msg.transform), result.quaternion) < 1e-9
    assert np.linalg.norm(translation(msg.transform) - cell.mounting.position) < 0.003
    assert np.degrees(quat.angle_between(rotation_wxyz(msg.transform),
                                         cell.mounting.quaternion)) < 0.3

    status = h.next_status(lambda s: values_of(s).get('samples') == '12')
    values = values_of(status)
    assert values['method'] == 'refined'
    np.testing.assert_allclose([float(v) for v in values['translation_xyz_m'].split()],
                               result.translation, atol=1e-6)
    assert float(values['translation_uncertainty_mm']) == pytest.approx(
        result.translation_uncertainty_mm, rel=1e-5)
    assert values['tf_static'] == 'off (publish_tf is false)'

    saved = h.call_save()
    assert saved.success, saved.message
    assert str(tmp_path / 'result.yaml') in saved.message and str(calib) in saved.message
    document = yaml.safe_load(calib.read_text())
    assert document['parameters']['name'] == 'arm'
    assert document['parameters']['calibration_type'] == 'eye_in_hand'
    assert document['parameters']['robot_effector_frame'] == 'flange'
    assert document['parameters']['robot_base_frame'] == 'base_link'
    assert document['parameters']['tracking_base_frame'] == 'cam'
    t = [document['transform']['translation'][k] for k in 'xyz']
    q = quat.wxyz_from_xyzw([document['transform']['rotation'][k] for k in 'xyzw'])
    np.testing.assert_allclose(t, result.translation, atol=1e-15)
    assert quat.angle_between(q, result.quaternion) < 1e-9
    h.spin_until(lambda: h.node_logs(Log.INFO, 'ros2 run tf2_ros static_transform_publisher'),
                 what='the static_transform_publisher line in the log')
    (line,) = h.node_logs(Log.INFO, 'ros2 run tf2_ros static_transform_publisher')
    assert line.endswith('--frame-id flange --child-frame-id cam')
    assert f'--x {t[0]:.10f}'.rstrip('0') in line


def test_a_new_estimate_replaces_the_latched_transform(make_harness, cell_and_samples):
    _, samples = cell_and_samples
    h = make_harness()
    received = h.subscribe_transform()
    h.add_samples(samples[:8])
    h.spin_until(lambda: received, what='the first ~/transform')
    first = h.node.session.result
    h.add_samples(samples[8:])
    h.spin_until(lambda: len(received) >= 2, what='the second ~/transform')
    np.testing.assert_allclose(translation(received[-1].transform),
                               h.node.session.result.translation, atol=1e-12)
    assert not np.allclose(first.translation, h.node.session.result.translation, atol=1e-9)
    assert received[-1].header.frame_id == 'tool0' and received[-1].child_frame_id == 'camera'


def test_publish_tf_broadcasts_every_estimate_on_tf_static(make_harness, cell_and_samples):
    """A tf2_msgs publisher of the node's own (no tf2_ros): latched, so late listeners get it."""
    _, samples = cell_and_samples
    h = make_harness([Parameter('publish_tf', value=True)])
    assert values_of(h.node.diagnostic_status())['tf_static'] == (
        'nothing broadcast yet: no estimate')
    h.add_samples(samples[:8])
    h.add_samples(samples[8:])
    received = h.subscribe_tf_static()   # late: transient local delivers the last one
    h.spin_until(lambda: received, what='/tf_static')
    (last,) = received[-1].transforms
    assert last.header.frame_id == 'tool0' and last.child_frame_id == 'camera'
    np.testing.assert_allclose(translation(last.transform), h.node.session.result.translation,
                               atol=1e-12)
    assert values_of(h.node.diagnostic_status())['tf_static'] == 'broadcast'
    # After ~/reset the latched transform is the old session's: said so, until a new one.
    assert h.node._on_reset(None, Trigger.Response()).success
    assert values_of(h.node.diagnostic_status())['tf_static'] == (
        'broadcast: the estimate before ~/reset, latched until a new one')
    h.add_samples(samples)
    assert values_of(h.node.diagnostic_status())['tf_static'] == 'broadcast'


def test_publish_tf_holds_an_estimate_that_says_not_to_use_it(make_harness, cell_and_samples):
    # setup changed to the wrong one at runtime: /tf_static got a transform 81 deg and 828 mm
    # off, beside its warning 'do not use this estimate'.
    _, samples = cell_and_samples
    h = make_harness([Parameter('publish_tf', value=True)])
    received = h.subscribe_tf_static()
    usable = []   # ~/usable: ~/transform carries such an estimate too, this says so
    h.driver.create_subscription(Bool, '/calibrator/usable', usable.append, LATCHED)
    h.add_samples(samples)
    h.spin_until(lambda: received and usable, what='/tf_static and ~/usable')
    assert usable[-1].data is True
    good = translation(received[-1].transforms[0].transform)
    (done,) = h.node.set_parameters([Parameter('setup', value='eye_to_hand')])
    assert done.successful
    result = h.node.session.result
    assert not result.usable and any('do not use this estimate' in w for w in result.warnings)
    h.spin_until(lambda: usable[-1].data is False, what='~/usable false')
    np.testing.assert_array_equal(translation(received[-1].transforms[0].transform), good)
    assert values_of(h.node.diagnostic_status())['tf_static'] == (
        'not broadcast: the estimate says not to use it')
    (done,) = h.node.set_parameters([Parameter('setup', value='eye_in_hand')])
    assert done.successful and h.node.session.result.usable
    assert values_of(h.node.diagnostic_status())['tf_static'] == 'broadcast'
    h.spin_until(lambda: usable[-1].data is True, what='~/usable true again')


def test_publish_tf_waits_for_the_convention_check_and_withdraws_a_wrong_one(
        make_harness, cell_and_samples):
    # A wrong setup's 3-sample estimate (3 samples fit every convention) was latched, 176 deg
    # off, and kept as 'the last one without such a warning' when sample 4 found it wrong.
    _, samples = cell_and_samples
    h = make_harness([Parameter('publish_tf', value=True),
                      Parameter('setup', value='eye_to_hand')])
    received = h.subscribe_tf_static()
    h.add_samples(samples[:3])
    assert h.node.session.result is not None
    h.spin_for(0.5)
    assert received == []
    assert values_of(h.node.diagnostic_status())['tf_static'] == (
        'not broadcast yet: the frame convention is not checked')
    assert not h.node_logs(30, 'publish_tf')   # (a wait of every session: info, no WARN)
    h.add_samples(samples[3:])   # the convention checked: this setup fits badly
    h.spin_for(0.5)
    assert received == [] and not h.node.session.result.usable
    # ~/save writes it as asked, and says first that it is not to be used (the reply, past a
    # kilobyte, ended with its warnings).
    saved = h.call_save()
    assert saved.success and saved.message.startswith(
        'saved an estimate that says not to use it ("usable": false in the file): saved to ')
    # Latched under a convention later found wrong: withdrawn (every estimate was made so).
    (done,) = h.node.set_parameters([Parameter('setup', value='eye_in_hand')])
    assert done.successful and h.node.session.result.usable
    h.spin_until(lambda: received, what='/tf_static')
    wrong = dataclasses.replace(h.node.session.result, warnings=[
        'frame convention: the samples fit badly as configured ...; do not use this estimate '
        'as configured'])
    h.node.publish_estimate(wrong)
    h.spin_until(lambda: not received[-1].transforms, what='the withdrawal')
    assert values_of(h.node.diagnostic_status())['tf_static'] == (
        'not broadcast: the estimate says not to use it')


def test_publish_tf_turned_on_at_runtime_sends_the_current_estimate(make_harness,
                                                                    cell_and_samples):
    _, samples = cell_and_samples
    h = make_harness([Parameter('sensor_frame', value='cam')])
    received = h.subscribe_tf_static()
    h.add_samples(samples)
    h.spin_for(0.5)
    assert received == []
    assert values_of(h.node.diagnostic_status())['tf_static'] == 'off (publish_tf is false)'
    before = h.node.session.result
    (done,) = h.node.set_parameters([Parameter('publish_tf', value=True)])
    assert done.successful
    h.spin_until(lambda: received, what='/tf_static')
    assert received[-1].transforms[0].child_frame_id == 'cam'
    # Presentation only: the estimate stands (no re-estimate), its samples too.
    assert h.node.session.result is before and len(h.node.session.samples) == len(samples)


def test_save_reports_an_unwritable_easy_handeye2_file(make_harness, cell_and_samples,
                                                       tmp_path):
    _, samples = cell_and_samples
    blocker = tmp_path / 'not_a_directory'
    blocker.write_text('')
    h = make_harness([Parameter('easy_handeye2_file', value=str(blocker / 'x.calib'))])
    h.add_samples(samples)
    saved = h.call_save()
    assert not saved.success
    assert 'could not write easy_handeye2_file' in saved.message
    assert (tmp_path / 'result.yaml').exists()   # the main result file is written first
