"""
The sim_cell node over real DDS, in-process (rclpy's own test pattern), and as a program.

On domain ids reserved on this host (conftest).  The streams are checked by their stamps and
contents, not by when they arrive: no rate or delay measured on the wall clock is asserted.
"""

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
import uuid

from geometry_msgs.msg import PoseStamped, TransformStamped
import numpy as np
from numpy.testing import assert_allclose
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.ros import conversions as conv
from quatcal_ros.ros.sim_cell import SimCell
from quatcal_ros.sim import simulation as sim
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture
def namespace():
    """Return a namespace of this test alone, so that other runs on the domain cannot talk in."""
    return f'/quatcal_test_{uuid.uuid4().hex[:12]}'


@pytest.fixture
def context(domain_id):
    """Yield a private rclpy Context on the module's domain, shut down afterwards."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


class Recorder:
    """A subscriber node that keeps (arrival_ns, message) of the sim_cell topics."""

    def __init__(self, context, namespace):
        self.node = Node('sim_cell_recorder', context=context, namespace=namespace)
        self.link, self.sensor, self.truth = [], [], []
        stream = QoSProfile(depth=1000)      # seconds of the streams: a busy executor loses none
        self.node.create_subscription(PoseStamped, 'link_pose', self._keep(self.link), stream)
        self.node.create_subscription(PoseStamped, 'sensor_pose', self._keep(self.sensor), stream)
        self.node.create_subscription(TransformStamped, 'sim_cell/ground_truth',
                                      self._keep(self.truth), LATCHED)

    def _keep(self, store):
        return lambda msg: store.append((time.time_ns(), msg))


def spin_until(executor, condition, timeout_s):
    """Spin until condition() holds or timeout_s passes; return condition()."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            break
        executor.spin_once(timeout_sec=min(0.05, remaining))
    return condition()


def spin_for(executor, seconds):
    """Spin for a fixed time."""
    spin_until(executor, lambda: False, seconds)


def stamp_span_s(store):
    """Return the time between the first and the last header stamp of a Recorder store (s)."""
    if len(store) < 2:
        return 0.0
    first, last = (conv.stamp_ns_from_header(store[k][1].header) for k in (0, -1))
    return (last - first) / 1e9


def _overrides(**values):
    return [Parameter(name, value=value) for name, value in values.items()]


CASES = {
    'eye_in_hand_given_mounting_noise_free': {
        'seed': 7, 'setup': 'eye_in_hand', 'link_rate_hz': 200.0, 'sensor_rate_hz': 20.0,
        'latency_s': 0.05, 'drop_probability': 0.2, 'rotation_noise_deg': 0.0,
        'translation_noise_m': 0.0, 'still_s': 0.5, 'move_s': 1.0,
        'mounting_xyz': [0.05, -0.02, 0.1], 'mounting_rpy_deg': [10.0, -20.0, 30.0]},
    'eye_to_hand_random_mounting_default_noise': {
        'seed': 3, 'setup': 'eye_to_hand', 'link_rate_hz': 250.0, 'sensor_rate_hz': 25.0,
        'latency_s': 0.03, 'drop_probability': 0.05, 'still_s': 0.5, 'move_s': 1.0,
        'clock_offset_s': 0.013},
    'eye_in_hand_scara': {
        'seed': 5, 'setup': 'eye_in_hand', 'link_rate_hz': 200.0, 'sensor_rate_hz': 20.0,
        'latency_s': 0.03, 'drop_probability': 0.05, 'still_s': 0.5, 'move_s': 1.0,
        'robot': 'scara'},
}


def _expected_streams(values, start_ns):
    """Return stop_and_go_streams() for the node's parameters (same rng use, same order)."""
    rng = np.random.default_rng(values['seed'])
    mounting = None
    if 'mounting_xyz' in values:
        roll, pitch, yaw = np.radians(values['mounting_rpy_deg'])
        mounting = Pose.create(values['mounting_xyz'],
                               sim.quaternion_wxyz_from_rpy(roll, pitch, yaw))
    cell = sim.random_cell(rng, values['setup'], mounting=mounting)
    return sim.stop_and_go_streams(
        rng, cell, n_stops=20, link_rate_hz=values['link_rate_hz'],
        sensor_rate_hz=values['sensor_rate_hz'], still_s=values['still_s'],
        move_s=values['move_s'], rotation_noise_deg=values.get('rotation_noise_deg', 0.2),
        translation_noise_m=values.get('translation_noise_m', 0.001),
        latency_s=values['latency_s'], drop_probability=values['drop_probability'],
        start_ns=start_ns, clock_offset_s=values.get('clock_offset_s', 0.0),
        robot=values.get('robot', 'arm'))


@pytest.mark.parametrize('case', sorted(CASES))
def test_publishes_latched_truth_and_the_simulated_streams(context, namespace, case):
    values = CASES[case]
    sim_node = SimCell(context=context, namespace=namespace,
                       parameter_overrides=_overrides(**values))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(sim_node)
    nodes = [sim_node]
    try:
        spin_for(executor, 0.5)            # ground truth is published before anyone listens
        recorder = Recorder(context, namespace)
        nodes.append(recorder.node)
        executor.add_node(recorder.node)
        # Three seconds of the streams by their stamps, however long they take to arrive.
        assert spin_until(executor, lambda: (recorder.truth and len(recorder.sensor) >= 20
                                             and stamp_span_s(recorder.link) >= 3.0), 60.0)
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()

    # Latched ground truth: the mounting, link -> sensor (eye_in_hand) or base -> sensor.
    assert len(recorder.truth) == 1
    truth = recorder.truth[0][1]
    parent = 'tool0' if values['setup'] == 'eye_in_hand' else 'base_link'
    assert (truth.header.frame_id, truth.child_frame_id) == (parent, 'camera')
    mounting = conv.pose_from_msg(truth)
    assert quat.angle_between(mounting.quaternion, sim_node.cell.mounting.quaternion) < 1e-12
    if 'mounting_rpy_deg' in values:
        assert_allclose(mounting.position, values['mounting_xyz'], atol=1e-15)

    link = [(conv.stamp_ns_from_header(m.header), conv.pose_from_msg(m), arrival, m)
            for arrival, m in recorder.link]
    sensor = [(conv.stamp_ns_from_header(m.header), conv.pose_from_msg(m), arrival, m)
              for arrival, m in recorder.sensor]
    assert {m.header.frame_id for *_, m in link} == {'base_link'}
    assert {m.header.frame_id for *_, m in sensor} == {'camera'}

    # Stamps on the node's grids, counted from the ground truth stamp (trajectory start).
    start = conv.stamp_ns_from_header(truth.header)
    link_period = 1e9 / values['link_rate_hz']
    sensor_period = 1e9 / values['sensor_rate_hz']
    link_steps = np.diff([s for s, *_ in link]) / round(link_period)
    assert np.all(link_steps == np.round(link_steps)) and np.all(link_steps >= 1)
    assert np.mean(link_steps == 1) > 0.95   # every grid point, but for a very few
    offset_ns = round(values.get('clock_offset_s', 0.0) * 1e9)   # the sensor clock's lead
    exposures = np.array([s for s, *_ in sensor]) - offset_ns
    assert np.all((exposures - start) % round(sensor_period) == 0)

    # Frames are published latency_s after their exposure (the same system clock), never
    # before (a loaded machine only makes them later).
    delays = np.array([(arrival - stamp) / 1e9 for stamp, _, arrival, _ in sensor])
    assert delays.min() >= values['latency_s'] - offset_ns / 1e9

    # The very poses of stop_and_go_streams with the same seed and start.
    expected = _expected_streams(values, start)
    expected_link = dict(expected.link)
    for stamp, pose, *_ in link:
        assert_allclose(pose.position, expected_link[stamp].position, rtol=0, atol=1e-12)
        assert quat.angle_between(pose.quaternion, expected_link[stamp].quaternion) < 1e-7
    expected_sensor = dict(expected.sensor)
    first, last = sensor[0][0], sensor[-1][0]
    assert [s for s, *_ in sensor] == [s for s in expected_sensor if first <= s <= last]
    for stamp, pose, *_ in sensor:
        assert_allclose(pose.position, expected_sensor[stamp].position, rtol=0, atol=1e-12)

    if values.get('robot') == 'scara':   # every link orientation: home turned about base z
        home = sim_node.cell.home.quaternion
        for _, pose, *_ in link:
            turn = quat.rotation_vector(quat.multiply(pose.quaternion, quat.conjugate(home)))
            assert_allclose(turn[:2], 0.0, atol=1e-9)

    # Noise free: link @ X @ sensor is the fixed object (sensor stamps are on link stamps).
    if values.get('rotation_noise_deg', 0.2) == 0.0 and values['setup'] == 'eye_in_hand':
        link_by_stamp = {stamp: pose for stamp, pose, *_ in link}
        objects = [link_by_stamp[stamp] @ mounting @ pose
                   for stamp, pose, *_ in sensor if stamp in link_by_stamp]
        assert len(objects) > 10
        for obj in objects:
            assert_allclose(obj.position, sim_node.cell.target.position, atol=1e-9)


def test_follows_the_ros_clock_with_use_sim_time(context, namespace):
    values = {'seed': 1, 'link_rate_hz': 100.0, 'sensor_rate_hz': 10.0, 'latency_s': 0.0}
    # /clock remapped into the test's namespace, so no other clock can reach the node.
    sim_node = SimCell(context=context, namespace=namespace,
                       cli_args=['--ros-args', '-r', f'/clock:={namespace}/clock'],
                       parameter_overrides=_overrides(use_sim_time=True, **values))
    recorder = Recorder(context, namespace)
    clock_pub = recorder.node.create_publisher(Clock, 'clock', 10)
    executor = SingleThreadedExecutor(context=context)
    for node in (sim_node, recorder.node):
        executor.add_node(node)
    sim_start_ns = 1000 * 10 ** 9
    sim_now_ns = sim_start_ns
    try:
        spin_for(executor, 0.5)
        assert not recorder.truth and not recorder.link   # no /clock yet: ROS time is 0
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and len(recorder.link) < 150:
            # 50 ms of sim time per round: the node catches up with several samples per tick.
            sim_now_ns += 5 * 10 ** 7
            clock_pub.publish(Clock(clock=conv.time_msg(sim_now_ns)))
            spin_for(executor, 0.02)
    finally:
        executor.shutdown()
        sim_node.destroy_node()
        recorder.node.destroy_node()
    assert len(recorder.link) >= 150
    truth_stamp = conv.stamp_ns_from_header(recorder.truth[0][1].header)
    assert sim_start_ns <= truth_stamp <= sim_now_ns
    stamps = np.array([conv.stamp_ns_from_header(m.header) for _, m in recorder.link])
    assert stamps.min() >= truth_stamp and stamps.max() <= sim_now_ns
    assert np.all(np.diff(stamps) == 10 ** 7)


def test_camera_images_show_the_board_where_the_cell_puts_it(context, namespace, repo_root):
    """With camera_images the sensor stream is a camera's: the board at the true pose."""
    from quatcal_ros.vision.detect import detect
    values = {'camera_images': True, 'board_file': str(repo_root / 'config' / 'sim_board.yaml'),
              'seed': 2, 'sensor_rate_hz': 10.0, 'still_s': 0.5, 'move_s': 0.5,
              'link_rate_hz': 50.0, 'drop_probability': 0.0}
    sim_node = SimCell(context=context, namespace=namespace,
                       parameter_overrides=_overrides(**values))
    recorder = Node('sim_cell_camera', context=context, namespace=namespace)
    images, infos, poses = [], [], []
    camera_qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)  # keeps all
    recorder.create_subscription(Image, 'image', images.append, camera_qos)
    recorder.create_subscription(CameraInfo, 'camera_info', infos.append, camera_qos)
    recorder.create_subscription(PoseStamped, 'sensor_pose', poses.append, QoSProfile(depth=10))
    executor = SingleThreadedExecutor(context=context)
    for node in (sim_node, recorder):
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: min(len(images), len(infos)) >= 8, 30.0), (
            len(images), len(infos))
    finally:
        executor.shutdown()
        sim_node.destroy_node()
        recorder.destroy_node()
    assert not poses   # the camera replaces the sensor pose
    by_stamp = {conv.stamp_ns_from_header(info.header): info for info in infos}
    camera = sim_node.camera
    origin = sim_node._origin_ns
    checked = 0
    for image in images:
        stamp = conv.stamp_ns_from_header(image.header)
        if stamp not in by_stamp:   # (its camera_info lost: best effort)
            continue
        checked += 1
        info = by_stamp[stamp]   # each image with the camera_info of its stamp
        assert image.header.frame_id == info.header.frame_id == 'camera'
        seen_as = conv.camera_from_camera_info(info)
        assert (seen_as.width, seen_as.height) == (640, 480)
        assert np.array_equal(seen_as.K, camera.camera.K)
        assert np.array_equal(seen_as.D, camera.camera.D)
        gray = np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.width)
        view = detect(gray, camera.renderer.board, camera.camera)
        assert view.ok, (view.refused, view.detail)
        # The true T_sensor_obj at the exposure (no clock offset, no latency in the stamp).
        p, q = sim_node.cell.sensor_poses(*sim_node._trajectory.link_poses(
            np.array([stamp - origin])))
        truth = Pose(p[0], q[0]) @ camera.object_to_board
        # Rendered corners found to about 0.1 px: the pose to a small fraction of a degree
        # and a few millimetres along the line of sight at 0.5-1 m.
        assert np.degrees(quat.angle_between(view.pose.quaternion, truth.quaternion)) < 0.3
        assert np.linalg.norm(view.pose.position - truth.position) < 0.005
    assert checked >= 6


@pytest.mark.parametrize('robot', ['scara', 'gantry'])
def test_the_stops_of_every_robot_show_the_camera_the_board(repo_root, robot):
    # A SCARA's stops were drawn without the camera's view in mind: 7 of 50 eye-in-hand
    # stops showed too little of the board to find it.
    from quatcal_ros.ros.sim_cell import IMAGE_INCIDENCE_DEG, IMAGE_VIEW_ANGLE_DEG, SimCamera
    from quatcal_ros.vision.detect import detect
    camera = SimCamera(str(repo_root / 'config' / 'sim_board.yaml'), 1)
    for setup, seed in itertools.product(sim.SETUPS, range(5)):
        rng = np.random.default_rng(seed)
        cell = sim.random_cell(rng, setup)
        trajectory = sim.StopAndGo(rng, cell, n_stops=10, robot=robot,
                                   max_view_angle_deg=IMAGE_VIEW_ANGLE_DEG,
                                   max_incidence_deg=IMAGE_INCIDENCE_DEG)
        for k in range(10):
            stop = trajectory.stop(k)
            p, q = cell.sensor_poses(stop.position[None], stop.quaternion[None])
            gray = camera.renderer.render(Pose(p[0], q[0]) @ camera.object_to_board, rng)
            view = detect(gray, camera.renderer.board, camera.camera)
            assert view.ok, (setup, seed, k, view.refused, view.detail)


def test_the_robot_reports_each_stop_off_by_its_own_error(context, namespace):
    """link_*_noise: a repeatable error per stop in link_pose; the sensor sees the truth."""
    values = {'seed': 3, 'link_rate_hz': 100.0, 'sensor_rate_hz': 20.0, 'still_s': 0.5,
              'move_s': 0.3, 'drop_probability': 0.0, 'rotation_noise_deg': 0.0,
              'translation_noise_m': 0.0, 'latency_s': 0.0,
              'link_rotation_noise_deg': 0.3, 'link_translation_noise_m': 0.002}
    sim_node = SimCell(context=context, namespace=namespace,
                       parameter_overrides=_overrides(**values))
    recorder = Recorder(context, namespace)
    executor = SingleThreadedExecutor(context=context)
    for node in (sim_node, recorder.node):
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: len(recorder.link) >= 250, 30.0)
    finally:
        executor.shutdown()
        sim_node.destroy_node()
        recorder.node.destroy_node()
    trajectory, origin = sim_node._trajectory, sim_node._origin_ns
    apart = {}
    for _, msg in recorder.link:
        t = conv.stamp_ns_from_header(msg.header) - origin
        k, _, s = trajectory.segments([t])
        if s[0] == 0.0:   # standing still at stop k
            p, q = trajectory.link_poses([t])
            reported = conv.pose_from_msg(msg)
            apart.setdefault(int(k[0]), []).append(
                (*(reported.position - p[0]),
                 np.degrees(quat.angle_between(reported.quaternion, q[0]))))
    assert len(apart) >= 3
    for k, offsets in apart.items():
        offsets = np.array(offsets)
        np.testing.assert_allclose(offsets - offsets[0], 0.0, atol=1e-9)   # the same each time
        assert 0.0 < offsets[0, 3] < 5 * np.sqrt(3) * 0.3          # degrees, chi with 3 dof
        assert 0.0 < np.linalg.norm(offsets[0, :3]) < 5 * np.sqrt(3) * 0.002
    assert len({tuple(np.round(o[0], 12)) for o in apart.values()}) == len(apart)
    # The sensor sees the true link pose.
    for _, msg in recorder.sensor[:20]:
        t = conv.stamp_ns_from_header(msg.header) - origin
        p, q = sim_node.cell.sensor_poses(*trajectory.link_poses([t]))
        np.testing.assert_allclose(conv.pose_from_msg(msg).position, p[0], atol=1e-9)


@pytest.mark.parametrize('overrides, error, message', [
    ({'setup': 'on_the_table'}, ValueError, 'setup'),
    ({'robot': 'hexapod'}, ValueError,
     "^parameter robot must be one of arm, scara, gantry, not 'hexapod'$"),
    ({'mounting_xyz': [0.1, 0.2]}, ValueError, 'mounting_xyz'),
    ({'mounting_xyz': [0.1, 0.2, 0.3]}, ValueError, 'give both'),
    ({'drop_probability': 1.5}, ValueError,
     r'^parameter drop_probability must be between 0 and 1, not 1\.5$'),
    ({'link_rate_hz': 0.0}, ValueError, 'parameter link_rate_hz must be between'),
    ({'link_rate_hz': 'fast'}, ValueError,
     "^parameter link_rate_hz must be a number, not 'fast'$"),
    ({'seed': -1}, ValueError, '^parameter seed must be between 0 and 2147483647, not -1$'),
    ({'tf_mode': 1}, ValueError, '^parameter tf_mode must be true or false, not 1$'),
    ({'mounting_xyz': '0 0 0.1'}, ValueError,
     r'^parameter mounting_xyz must be a list of numbers, such as \'\[0\.0, 0\.0, 0\.1\]\', '
     r'not \'0 0 0\.1\'$'),
    ({'camera_images': True}, ValueError, 'camera_images needs board_file'),
    # A misspelt name was ignored without a word (tf_mod:=true published no TF).
    ({'tf_mod': True}, ValueError, r'no such parameter: tf_mod \(did you mean tf_mode\?\); '
                                   r'`sim_cell --help`'),
])
def test_bad_parameters_are_named(context, overrides, error, message):
    with pytest.raises(error, match=message):
        SimCell(context=context, parameter_overrides=_overrides(**overrides))


def test_integers_are_taken_for_real_numbers(context):
    # -p sensor_rate_hz:=30 (the README's defaults are written so) and -p
    # mounting_xyz:='[0, 0, 1]' are integers to ROS, which refused them for real numbers.
    node = SimCell(context=context, parameter_overrides=_overrides(
        sensor_rate_hz=30, mounting_xyz=[0, 0, 1], mounting_rpy_deg=[0.0, 90.0, 0.0]))
    try:
        assert node.config.sensor_rate_hz == 30.0
        assert node.get_parameter('sensor_rate_hz').type_ == Parameter.Type.DOUBLE
        np.testing.assert_array_equal(node.config.mounting.position, [0.0, 0.0, 1.0])
    finally:
        node.destroy_node()


def test_a_launch_files_global_parameters_are_no_typos(context):
    # A params file's /** section for every node of a robot: map_frame is like marker_frame,
    # base_frame_id like base_frame, but no misspelling of them (the node refused to start).
    node = SimCell(context=context, parameter_overrides=_overrides(
        map_frame='map', base_frame_id='base', odom_frame='odom'))
    node.destroy_node()


def test_parameters_are_described_with_ranges(context):
    node = SimCell(context=context)
    try:
        descriptor = node.describe_parameter('rotation_noise_deg')
        assert descriptor.description and descriptor.read_only
        assert descriptor.floating_point_range[0].to_value == 10.0
        assert node.describe_parameter('n_stops').integer_range[0].from_value == 0
        assert node.get_parameter('rotation_noise_deg').value == 0.2
        assert node.get_parameter('sensor_frame').value == 'camera'
    finally:
        node.destroy_node()


def test_program_logs_the_truth_and_stops_cleanly_on_ctrl_c(repo_root, process_domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(process_domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    process = subprocess.Popen(
        [sys.executable, '-m', 'quatcal_ros.ros.sim_cell', '--ros-args', '-p', 'n_stops:=2',
         '-p', 'still_s:=0.2', '-p', 'move_s:=0.3'],
        cwd=repo_root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(process.stdout), daemon=True)
    reader.start()
    try:
        # Ctrl-C once it has visited its stops (the wait is generous: startup under load).
        deadline = time.monotonic() + 60.0
        while not any('visited all 2 stops' in line for line in lines):
            assert process.poll() is None, ''.join(lines)
            assert time.monotonic() < deadline, 'no "visited all 2 stops":\n' + ''.join(lines)
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        process.wait(timeout=30)
        reader.join(timeout=10)
    finally:
        process.kill()
    output = ''.join(lines)
    assert process.returncode == 0, output
    assert 'ground truth eye_in_hand tool0 -> camera: quaternion (x, y, z, w) = (' in output
    assert 'Traceback' not in output


def test_program_exits_2_on_bad_parameters(repo_root, process_domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(process_domain_id))
    result = subprocess.run(
        [sys.executable, '-m', 'quatcal_ros.ros.sim_cell', '--ros-args', '-p', 'setup:=sideways'],
        cwd=repo_root, env=env, capture_output=True, text=True, timeout=30)
    assert result.returncode == 2
    assert 'sideways' in result.stderr + result.stdout
