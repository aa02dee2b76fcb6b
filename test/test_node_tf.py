"""
The calibrator with TF input, over real Fast DDS: /tf and /tf_static as a real cell has them.

The cell publishes the robot as a chain of two joints on /tf (base_link -> shoulder -> tool0),
the camera driver's static camera_link -> camera_color_optical_frame on /tf_static, and the
marker detector's camera_color_optical_frame -> marker on /tf at the camera's rate, each
stamped at its exposure and delivered late, as in simulation.stop_and_go_streams. The node
reads them with the four frame parameters of easy_handeye2.
"""

from dataclasses import replace
import json
import re
import time
import types

from journal_files import write_journal
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import journal
from quatcal_ros.ros import conversions
from quatcal_ros.ros.node import CalibratorNode, journal_header
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.ros.qos import TF_QOS, TF_STATIC_BROADCAST_QOS
from quatcal_ros.ros.sim_cell import CAMERA_LINK_TO_SENSOR as CAMERA_LINK_TO_OPTICAL
from quatcal_ros.ros.sim_cell import shoulder_pose as shoulder
from quatcal_ros.ros.static_tf import broadcast_advice
from quatcal_ros.ros.tf_feed import TfFeed
from quatcal_ros.sim import simulation
from quatcal_ros.stream import tf_joint
from quatcal_ros.stream.settings import ConfigError
from quatcal_ros.stream.tf_tree import TransformTree
from quatcal_ros.tools.cli import solve_main
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from ros_harness import harnesses_of, logged_warnings, SpinMixin
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
import yaml

FRAMES = [Parameter('robot_base_frame', value='base_link'),
          Parameter('robot_effector_frame', value='tool0'),
          Parameter('tracking_base_frame', value='camera_color_optical_frame'),
          Parameter('tracking_marker_frame', value='marker')]


class TfHarness(SpinMixin):
    """A calibrator in TF mode and a driver that publishes /tf and /tf_static."""

    def __init__(self, domain_id, overrides=()):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        parameters = [Parameter('max_stamp_offset_s', value=0.0), *FRAMES, *overrides]
        self.node = CalibratorNode(context=self.context, parameter_overrides=parameters)
        self.driver = rclpy.create_node('test_tf_driver', context=self.context)
        self.tf = self.driver.create_publisher(TFMessage, '/tf', TF_QOS)
        self.tf_static = self.driver.create_publisher(
            TFMessage, '/tf_static', TF_STATIC_BROADCAST_QOS)
        self.watch_outputs()
        self.sent = 0
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: self.tf.get_subscription_count()
                        and self.tf_static.get_subscription_count(),
                        what='discovery of the calibrator')

    def publish(self, transforms, static=False):
        """Publish one TFMessage of (parent, child, stamp_ns, Pose)."""
        msg = TFMessage(transforms=[conversions.transform_stamped_msg(pose, stamp, parent, child)
                                    for parent, child, stamp, pose in transforms])
        (self.tf_static if static else self.tf).publish(msg)
        if not static:
            self.sent += 1

    def wait_received(self, timeout=10.0):
        topic = self.node.inputs.topics['link_pose']
        self.spin_until(lambda: self.node.stats.received[topic] >= self.sent, timeout,
                        what='the node to receive /tf')


@pytest.fixture
def tf_harness(domain_id):
    yield from harnesses_of(TfHarness, domain_id)


def cell_messages(streams):
    """Return the cell's /tf messages in delivery order: [[(parent, child, stamp, pose)]]."""
    events = []
    for stamp, link in streams.link:
        first = shoulder(stamp)
        events.append((stamp, 0, [('base_link', 'shoulder', stamp, first),
                                  ('shoulder', 'tool0', stamp, first.inverse() @ link)]))
    for delivery, (stamp, seen) in zip(streams.sensor_delivery_ns, streams.sensor):
        events.append((delivery, 1, [('camera_color_optical_frame', 'marker', stamp, seen)]))
    return [transforms for _, _, transforms in sorted(events, key=lambda e: e[:2])]


def tf_cell(seed, n_stops):
    """Return a simulated cell and its stop-and-go streams (50 Hz robot, 30 Hz camera)."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    return cell, simulation.stop_and_go_streams(
        rng, cell, n_stops=n_stops, link_rate_hz=50.0, sensor_rate_hz=30.0, still_s=1.0,
        move_s=1.0, rotation_noise_deg=0.2, translation_noise_m=0.001, rotation_spread_deg=40.0)


def play(h, messages):
    """Publish the messages in chunks the node keeps up with."""
    for k in range(0, len(messages), 50):
        for transforms in messages[k:k + 50]:
            h.publish(transforms)
        h.wait_received()


def publish_camera_driver(h, streams):
    """Publish the driver's static camera_link -> camera_color_optical_frame."""
    h.publish([('camera_link', 'camera_color_optical_frame', streams.link[0][0],
                CAMERA_LINK_TO_OPTICAL)], static=True)


def test_the_node_on_a_tf_cell_converges_to_the_truth(tf_harness, tmp_path):
    cell, streams = tf_cell(11, 12)
    h = tf_harness()
    publish_camera_driver(h, streams)
    start = streams.link[0][0]
    messages = cell_messages(streams)
    # Malformed TF among them: a NaN, a loop, and a second parent for tool0.
    nan = Pose.identity()
    nan.position[0] = float('nan')
    bad = [[('base_link', 'shoulder', start + 5, nan)],
           [('tool0', 'base_link', start + 7, Pose.identity())],
           [('world', 'tool0', start + 9, Pose.identity())]]
    play(h, messages[:40] + bad + messages[40:])
    h.spin_until(lambda: h.rotations, what='an estimate on ~/rotation')
    result = h.node.session.result
    assert result.samples >= 10
    error = np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))
    assert error < 3.0 * result.uncertainty_deg
    moved = 1e3 * np.linalg.norm(result.translation - cell.mounting.position)
    assert moved < 3.0 * result.translation_uncertainty_mm
    bad_counts = {reason: count for (where, reason), count in h.node.stats.bad.items()
                  if where == '/tf'}
    assert bad_counts.get('non_finite', 0) == 1 and bad_counts.get('breaks_tree', 0) == 2
    # Named by its frames (/tf carries many): it said 'transform.translation.x is nan' alone.
    assert h.node.stats.example('/tf', 'non_finite') == (
        'base_link -> shoulder: transform.translation.x is nan')

    # ~/save writes easy_handeye2's file naming the four TF frames the node reads.
    calib = tmp_path / 'cell.calib'
    for done in h.node.set_parameters([Parameter('result_file', value=str(tmp_path / 'r.yaml')),
                                       Parameter('easy_handeye2_file', value=str(calib))]):
        assert done.successful, done.reason
    save = h.driver.create_client(Trigger, '/calibrator/save')
    h.spin_until(save.service_is_ready, what='the ~/save service')
    future = save.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/save')
    assert future.result().success, future.result().message
    parameters = yaml.safe_load(calib.read_text())['parameters']
    assert {name: parameters[name] for name in (
        'calibration_type', 'robot_base_frame', 'robot_effector_frame', 'tracking_base_frame',
        'tracking_marker_frame')} == {
        'calibration_type': 'eye_in_hand', 'robot_base_frame': 'base_link',
        'robot_effector_frame': 'tool0', 'tracking_base_frame': 'camera_color_optical_frame',
        'tracking_marker_frame': 'marker'}


def test_the_local_tf2_msgs_is_the_standard_type(tf_harness):
    """Type name and Jazzy type hash of tf2_msgs/TFMessage: robot_state_publisher matches."""
    h = tf_harness()
    (info,) = [i for i in h.driver.get_publishers_info_by_topic('/tf')
               if i.node_name == 'test_tf_driver']
    assert info.topic_type == 'tf2_msgs/msg/TFMessage'
    assert str(info.topic_type_hash) == (
        'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087')


def test_tf_input_needs_all_four_frames(domain_id):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        with pytest.raises(ConfigError, match='tracking_marker_frame not set'):
            CalibratorNode(context=context, parameter_overrides=FRAMES[:3])
    finally:
        rclpy.try_shutdown(context=context)


def test_publish_tf_gives_no_frame_a_second_parent(tf_harness, tmp_path, capsys):
    """The optical frame is under camera_link: the node broadcasts tool0 -> camera_link."""
    cell, streams = tf_cell(12, 10)
    # link_frame and sensor_frame left out: the result is named by the TF frames
    h = tf_harness([Parameter('publish_tf', value=True),
                    Parameter('result_file', value=str(tmp_path / 'r.yaml'))])
    heard = []
    h.driver.create_subscription(TFMessage, '/tf_static', heard.append, TF_STATIC_BROADCAST_QOS)
    publish_camera_driver(h, streams)
    play(h, cell_messages(streams))
    h.spin_until(lambda: h.rotations, what='an estimate')
    result = h.node.session.result

    def ours():
        return [t for msg in heard for t in msg.transforms if t.header.frame_id == 'tool0']
    h.spin_until(lambda: ours() and np.allclose(
        conversions.pose_from_msg(ours()[-1]).position,
        (Pose.create(result.translation, result.quaternion)
         @ CAMERA_LINK_TO_OPTICAL.inverse()).position, atol=1e-9),
        what="the node's /tf_static for the last estimate")
    children = {t.child_frame_id for t in ours()}
    assert children == {'camera_link'}   # never the optical frame: it has its parent
    composed = conversions.pose_from_msg(ours()[-1]) @ CAMERA_LINK_TO_OPTICAL
    np.testing.assert_allclose(composed.position, result.translation, atol=1e-9)
    assert np.degrees(quat.angle_between(composed.quaternion, result.quaternion)) < 1e-7
    assert np.degrees(quat.angle_between(composed.quaternion, cell.mounting.quaternion)) < \
        3 * result.uncertainty_deg
    # The command ~/save logs to broadcast it is the same transform (it was tool0 -> the
    # optical frame: pasted, a second parent).
    said = broadcast_advice(tf_joint.joint(result, h.node.config.result_frames,
                                           h.node.inputs.tf.tree))
    assert said.startswith('to broadcast the result on /tf_static (camera_color_optical_frame '
                           'already hangs from camera_link in TF'), said
    values = [float(v) for v in re.findall(r'--(?:x|y|z|qx|qy|qz|qw) (\S+)', said)]
    assert said.endswith('--frame-id tool0 --child-frame-id camera_link')
    line = Pose.create(values[:3], quat.wxyz_from_xyzw(values[3:]))
    np.testing.assert_allclose(line.position, conversions.pose_from_msg(ours()[-1]).position,
                               atol=1e-9)
    # So is the saved file's URDF joint (its transform stays the calibrated frames').
    save = h.driver.create_client(Trigger, '/calibrator/save')
    h.spin_until(save.service_is_ready, what='the ~/save service')
    future = save.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/save')
    saved = yaml.safe_load((tmp_path / 'r.yaml').read_text())
    assert saved['child_frame'] == 'camera_color_optical_frame'
    assert saved['urdf'].startswith('<!-- camera_color_optical_frame already hangs from '
                                    'camera_link in TF'), saved['urdf']
    assert '<parent link="tool0"/>' in saved['urdf']
    assert '<child link="camera_link"/>' in saved['urdf']
    xyz = re.search(r'xyz="([^"]+)"', saved['urdf']).group(1).split()
    np.testing.assert_allclose([float(v) for v in xyz], line.position, atol=1e-9)
    # The journal records the static chain, so a solve of it later gives the same joint (it
    # gave tool0 -> the optical frame: the journal knew no tree).
    header = h.node.journal.header
    assert header.static_chain[0] == 'camera_link'
    assert h.node.journal.path.read_text().split('\n', 1)[0] == header.line()
    assert solve_main([str(h.node.journal.path)]) == 0
    solved = json.loads(capsys.readouterr().out)
    assert solved['static_transform_publisher'].endswith(
        '--frame-id tool0 --child-frame-id camera_link')
    values = [float(v) for v in re.findall(r'--(?:x|y|z|qx|qy|qz|qw) (\S+)',
                                           solved['static_transform_publisher'])]
    np.testing.assert_allclose(values[:3], line.position, atol=1e-6)


def test_save_puts_swapped_link_frames_before_the_setup_advice(tf_harness, tmp_path):
    # The saved warnings said only 'use setup eye_to_hand' (the data look like it); the swap,
    # the right fix, was on /diagnostics alone.
    cell, streams = tf_cell(12, 10)
    h = tf_harness([Parameter('robot_base_frame', value='tool0'),
                    Parameter('robot_effector_frame', value='base_link'),
                    Parameter('result_file', value=str(tmp_path / 'r.yaml')),
                    Parameter('validation_max_rotation_deg', value=0.001)])
    publish_camera_driver(h, streams)
    play(h, cell_messages(streams))
    h.spin_until(lambda: h.rotations, what='an estimate')
    save = h.driver.create_client(Trigger, '/calibrator/save')
    h.spin_until(save.service_is_ready, what='the ~/save service')
    future = save.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/save')
    warnings = yaml.safe_load((tmp_path / 'r.yaml').read_text())['warnings']
    assert warnings[0].startswith('TF input: the link frames look swapped: the base frame '
                                  'given, tool0, hangs below the effector frame given, '
                                  'base_link'), warnings
    # A failed validation is in the saved warnings, as in solve's and replay's files.
    assert any(w.startswith('validation failed: ') for w in warnings), warnings


def test_a_capture_refused_on_tf_input_names_the_frame_it_misses(tf_harness):
    # It said to check that both topics publish, and nothing of the frame /diagnostics named.
    cell, streams = tf_cell(12, 10)
    h = tf_harness([Parameter('capture_mode', value='manual'),
                    Parameter('tracking_marker_frame', value='markr')])
    publish_camera_driver(h, streams)
    play(h, cell_messages(streams)[:20])
    capture = h.driver.create_client(Trigger, '/calibrator/capture')
    h.spin_until(capture.service_is_ready, what='the ~/capture service')
    future = capture.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/capture')
    refused = future.result()
    assert not refused.success and refused.message.startswith('no paired poses')
    assert ('(TF input: camera_color_optical_frame -> markr cannot be composed: no frame markr '
            'on /tf or /tf_static yet') in refused.message, refused.message


def test_a_broadcast_before_the_camera_drivers_tf_static_gives_way_to_it(tf_harness):
    # A resumed estimate is broadcast at start, before the driver's latched /tf_static has
    # come: tool0 -> the optical frame, heard back, once made the node refuse the driver's
    # camera_link -> optical frame as a second parent, for the life of the node.
    cell, streams = tf_cell(12, 10)
    h = tf_harness([Parameter('publish_tf', value=True)])
    heard = []
    h.driver.create_subscription(TFMessage, '/tf_static', heard.append, TF_STATIC_BROADCAST_QOS)
    play(h, cell_messages(streams))
    h.spin_until(lambda: h.rotations, what='an estimate')

    def ours():
        return [t for msg in heard for t in msg.transforms if t.header.frame_id == 'tool0']
    h.spin_until(lambda: ours(), what="the node's /tf_static")
    assert ours()[-1].child_frame_id == 'camera_color_optical_frame'   # no parent known yet
    publish_camera_driver(h, streams)
    h.spin_until(lambda: ours()[-1].child_frame_id == 'camera_link',
                 what="the broadcast again, under the driver's camera_link")
    assert h.node.inputs.tf.tree.parent('camera_color_optical_frame') == 'camera_link'
    assert not [key for key in h.node.stats.bad if key[1] == 'breaks_tree']
    result = h.node.result
    composed = conversions.pose_from_msg(ours()[-1]) @ CAMERA_LINK_TO_OPTICAL
    np.testing.assert_allclose(composed.position, result.translation, atol=1e-9)


def test_a_bag_of_the_same_tf_traffic_replays_to_the_same_samples(tf_harness, tmp_path):
    """The live node and `replay` share the TF input (ros.tf_feed): the same samples."""
    from quatcal_ros.core.calibration import calibrate
    from quatcal_ros.ros.bag import Bag, PoseInput, Replay, TF_TYPE, TYPESTORE, write_bag
    from quatcal_ros.stream import settings
    from quatcal_ros.stream.session import Session

    cell, streams = tf_cell(13, 10)
    h = tf_harness()
    publish_camera_driver(h, streams)
    messages = cell_messages(streams)
    play(h, messages)
    h.spin_until(lambda: h.rotations, what='an estimate')
    live = h.node.session

    def bag_message(transforms):
        return TYPESTORE.types[TF_TYPE](transforms=[
            conversions.transform_stamped_msg(pose, stamp, parent, child, typestore=TYPESTORE)
            for parent, child, stamp, pose in transforms])
    start = streams.link[0][0]
    records = [('/tf_static', start, bag_message([('camera_link', 'camera_color_optical_frame',
                                                  start, CAMERA_LINK_TO_OPTICAL)]))]
    records += [('/tf', max(t[2] for t in transforms), bag_message(transforms))
                for transforms in messages]
    write_bag(tmp_path / 'cell', {'/tf': TF_TYPE, '/tf_static': TF_TYPE},
              sorted(records, key=lambda record: record[1]))
    offline = Session(settings.session_config(settings.Settings()))
    with Bag(tmp_path / 'cell') as recording:
        Replay(recording, PoseInput(frames=('base_link', 'tool0')),
               PoseInput(frames=('camera_color_optical_frame', 'marker'))).run(offline)
    offline.estimate()
    assert [s.stamp_ns for s in offline.samples] == [s.stamp_ns for s in live.samples]
    for mine, theirs in zip(offline.samples, live.samples):
        np.testing.assert_allclose(mine.sensor.position, theirs.sensor.position, atol=1e-12)
        np.testing.assert_allclose(mine.link.quaternion, theirs.link.quaternion, atol=1e-12)
    # The same samples: the replay's estimate is calibrate()'s on the live node's samples.
    full = calibrate(list(live.samples), live.config.calibration)
    assert np.degrees(quat.angle_between(offline.result.quaternion, full.quaternion)) < 1e-9


def test_sim_cell_in_tf_mode_drives_the_calibrator_to_its_ground_truth(domain_id):
    """sim_cell publishes like a real cell (two joints, a static camera_link, the marker)."""
    from quatcal_ros.ros.sim_cell import SimCell

    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=context)
    cell = SimCell(context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in (
            ('tf_mode', True), ('seed', 4), ('n_stops', 8), ('still_s', 1.0), ('move_s', 0.6),
            ('link_rate_hz', 100.0), ('link_frame', 'tool0'),
            ('sensor_frame', 'camera_color_optical_frame'))])
    node = CalibratorNode(context=context, parameter_overrides=FRAMES)
    try:
        for each in (cell, node):
            executor.add_node(each)
        deadline = time.monotonic() + 60.0
        while (node.session.result is None or node.session.result.samples < 7) \
                and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        result = node.session.result
        assert result is not None and result.samples >= 7, node.session.last_error
        error = np.degrees(quat.angle_between(result.quaternion, cell.cell.mounting.quaternion))
        assert error < 3.0 * result.uncertainty_deg
        assert not node.stats.bad
    finally:
        executor.shutdown()
        cell.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_frame_that_never_comes_is_named_on_diagnostics(tf_harness):
    cell, streams = tf_cell(14, 3)
    h = tf_harness([Parameter('robot_effector_frame', value='tool_0')])   # a typo
    publish_camera_driver(h, streams)
    play(h, cell_messages(streams)[:200])
    status = h.node.diagnostic_status()
    assert ('TF input: base_link -> tool_0 cannot be composed: no frame tool_0 on /tf or '
            '/tf_static yet (frames seen: ') in status.message
    assert 'tool0' in status.message   # among the frames seen
    assert 'camera_color_optical_frame -> marker' not in status.message   # that one works
    # /tf is busy, so the link stream is not 'no message at all': its poses never compose.
    h.spin_until(lambda: 'link_pose stale: no pose composed from /tf in'
                 in h.node.diagnostic_status().message, what='the stale link stream named')
    assert 'no message at all' not in h.node.diagnostic_status().message
    # Only /diagnostics said so; the log is told once the problem has stood a while (not
    # while the first transforms come in).
    h.node._tf_log.after = 0   # (as if it had stood TF_PROBLEM_LOG_S)
    with logged_warnings(h.node) as warned:
        h.node.diagnostic_status()
        h.node.diagnostic_status()
    said = [w for w in warned if w.startswith('TF input: base_link -> tool_0 cannot be')]
    assert len(said) == 1, warned


def test_a_late_transform_is_only_late_not_a_time_jump(tf_harness):
    """A transform a second late (a stalled publisher) is inserted in order; nothing is reset."""
    cell, streams = tf_cell(16, 4)
    h = tf_harness()
    publish_camera_driver(h, streams)
    messages = cell_messages(streams)
    play(h, messages[:300])
    generation = h.node.inputs.tf.tree.generation
    newest = max(t[2] for transforms in messages[:300] for t in transforms)
    late = newest - 10 ** 9
    h.publish([('base_link', 'shoulder', late, shoulder(late))])
    play(h, messages[300:])
    assert h.node.inputs.tf.tree.generation == generation   # the buffers were not cleared
    assert h.node.session.counters['time_jumps'] == 0
    assert not h.node.stats.bad
    h.spin_until(lambda: h.node.session.result is not None, what='an estimate')


def camera_tree():
    """Return a tree of the camera driver's camera_link -> optical frame alone."""
    tree = TransformTree()
    tree.set_transform('camera_link', 'camera_color_optical_frame', 0, CAMERA_LINK_TO_OPTICAL,
                       static=True)
    return tree


def test_the_journal_header_keeps_a_recorded_tf_joint_until_the_tree_shows_one():
    """A resumed node before the driver's /tf_static keeps the journal's static chain."""
    config = types.SimpleNamespace(setup='eye_in_hand', invert_sensor=False,
                                   result_frames=('tool0', 'optical'), sensor_time_offset_s=0.0)
    plain = journal.JournalHeader('eye_in_hand', 'tool0', 'optical', False,
                                  sensor_time_offsets=(0.0,))
    assert journal_header(config) == plain   # pose topics: no joint
    tree = TransformTree()
    tree.set_transform('camera_link', 'optical', 0, CAMERA_LINK_TO_OPTICAL, static=True)
    chain = tf_joint.static_chain('tool0', 'optical', tree)
    assert chain[0] == 'camera_link'
    assert journal_header(config, tree, plain).static_chain == chain
    recorded = replace(plain, static_chain=('camera', (0, 0, 0, 0, 0, 0, 1)))
    assert journal_header(config, TransformTree(), recorded) == recorded   # kept
    assert journal_header(config, tree, recorded).static_chain == chain    # the tree's now
    other = replace(recorded, sensor_frame='lens')   # recorded for another sensor frame
    assert journal_header(config, TransformTree(), other) == plain


def test_a_resumed_node_joins_the_tree_where_its_journal_says_before_tf_static(
        tf_harness, tmp_path):
    """Resumed before the camera driver's /tf_static: ~/save said tool0 -> the optical frame."""
    rng = np.random.default_rng(5)
    samples, _ = simulation.samples(rng, simulation.random_cell(rng), 15,
                                    rotation_noise_deg=0.1, translation_noise_m=0.001)
    optical = 'camera_color_optical_frame'
    chain = tf_joint.static_chain('tool0', optical, camera_tree())
    write_journal(tmp_path / 'samples.csv', samples[:14],
                  journal.JournalHeader('eye_in_hand', 'tool0', optical, False, chain))
    h = tf_harness([Parameter('samples_file', value=str(tmp_path / 'samples.csv')),
                    Parameter('resume', value=True),
                    Parameter('result_file', value=str(tmp_path / 'r.yaml'))])
    assert h.node.session.result is not None   # from the journal's samples
    # One more sample, as captured live: its estimate is warm-started from the last one.
    h.node.handle_events(h.node.session.add_samples(samples[14:]))
    full = calibrate(h.node.session.samples,   # (as the journal gave them back)
                     h.node.session.config.calibration).to_json_dict()
    assert h.node.session.result.to_json_dict() != full
    save = h.driver.create_client(Trigger, '/calibrator/save')
    h.spin_until(save.service_is_ready, what='the ~/save service')
    future = save.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/save')
    assert future.result().success, future.result().message
    # ~/save solved in full first: its file is what `solve` of the journal gives.
    assert h.node.session.result.to_json_dict() == full
    saved = yaml.safe_load((tmp_path / 'r.yaml').read_text())
    assert '<child link="camera_link"/>' in saved['urdf'], saved['urdf']
    assert saved['urdf'].startswith(f'<!-- {optical} already hangs from camera_link in TF')
    assert 'frames seen: none' in ' '.join(h.node.inputs.tf.problems())   # (the journal's)
    # The driver's own chain has one more frame: it replaces the journal's edge (it was
    # refused as a second parent, the journal's edge kept for good).
    colour = Pose.create([0.0, 0.015, 0.0], [1.0, 0.0, 0.0, 0.0])
    h.publish([('camera_link', 'camera_color_frame', 0, colour),
               ('camera_color_frame', optical, 0, colour.inverse() @ CAMERA_LINK_TO_OPTICAL)],
              static=True)
    h.spin_until(lambda: h.node.inputs.tf.tree.parent(optical) == 'camera_color_frame',
                 what="the driver's /tf_static")
    assert h.node.stats.bad_total == 0
    future = save.call_async(Trigger.Request())
    h.spin_until(future.done, what='~/save')
    again = yaml.safe_load((tmp_path / 'r.yaml').read_text())
    assert '<child link="camera_link"/>' in again['urdf']   # the same joint, to rounding

    def origin(urdf):
        return [float(v) for key in ('xyz', 'rpy')
                for v in re.search(f'{key}="([^"]+)"', urdf).group(1).split()]
    np.testing.assert_allclose(origin(again['urdf']), origin(saved['urdf']), atol=1e-9)


def test_the_frames_named_as_seen_are_not_the_nodes_own_broadcast():
    """Before the camera's TF came, 'frames seen' listed the node's own /tf_static frames."""
    frames = {'link': ('base_link', 'tool0'), 'sensor': ('optical', 'marker')}
    feed = TfFeed(TfFeed.new_tree(), PoseScreen(), frames, lambda *pose: None, link='link',
                  sensor='sensor')
    feed.tree.set_transform('base_link', 'tool0', 0, Pose.identity())
    feed.tree.set_transform('tool0', 'camera_link', 0, Pose.identity(), static=True)
    feed.ours = {('tool0', 'camera_link')}   # (heard back)
    assert feed.problems() == ['TF input: optical -> marker cannot be composed: no frame '
                               'optical or marker on /tf or /tf_static yet (frames seen: '
                               'base_link, tool0)']
