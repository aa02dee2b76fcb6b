"""
The result in easy_handeye2's calibration layout and as a static_transform_publisher line.

The layout is that of easy_handeye2's message easy_handeye2_msgs/HandeyeCalibration as its
handeye_calibration.save_calibration writes it (rosidl_runtime_py.message_to_yaml), and that
easy_handeye2 reads back with set_message_fields, which refuses unknown keys.
"""

import argparse
from dataclasses import dataclass
import json
import os
import shlex
import subprocess
import sys

import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import exports
from quatcal_ros.files.samples_csv import format_samples
from quatcal_ros.sim import simulation
import yaml

# Fields of easy_handeye2_msgs/HandeyeCalibrationParameters, in message order.
EASY_HANDEYE2_PARAMETERS = ('name', 'calibration_type', 'robot_base_frame',
                            'robot_effector_frame', 'tracking_base_frame',
                            'tracking_marker_frame', 'freehand_robot_movement',
                            'move_group_namespace', 'move_group')


@dataclass
class FakeResult:
    """The fields of calibration.CalibrationResult the exports read."""

    quaternion: np.ndarray
    translation: np.ndarray
    method: str = 'refined'
    samples: int = 12
    uncertainty_deg: float = 0.05
    translation_uncertainty_mm: float = 0.4


@pytest.fixture(scope='module')
def solved():
    """Return a simulated eye-in-hand cell, its samples and calibrate()'s result."""
    rng = np.random.default_rng(61)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 15, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    return cell, samples, calibrate(samples, CalibrationOptions())


def test_easy_handeye2_layout_round_trip(solved):
    cell, _, result = solved
    text = exports.easy_handeye2_yaml(result, 'tool0', 'camera_link', 'eye_in_hand',
                                      name='cell', robot_base_frame='base_link',
                                      tracking_marker_frame='marker')
    assert text.startswith('# ')   # what made it and how good it is, as comments
    document = yaml.safe_load(text)
    # Exactly the message's fields: easy_handeye2's set_message_fields refuses any other key.
    assert list(document) == ['parameters', 'transform']
    assert tuple(document['parameters']) == EASY_HANDEYE2_PARAMETERS
    assert list(document['transform']) == ['translation', 'rotation']
    assert list(document['transform']['translation']) == ['x', 'y', 'z']
    assert list(document['transform']['rotation']) == ['x', 'y', 'z', 'w']
    parameters = document['parameters']
    assert parameters['name'] == 'cell'
    assert parameters['calibration_type'] == 'eye_in_hand'
    assert parameters['robot_effector_frame'] == 'tool0'     # the parent frame
    assert parameters['robot_base_frame'] == 'base_link'
    assert parameters['tracking_base_frame'] == 'camera_link'   # the child (sensor) frame
    assert parameters['tracking_marker_frame'] == 'marker'
    assert parameters['freehand_robot_movement'] is True
    transform = document['transform']
    t = [transform['translation'][k] for k in 'xyz']
    q = quat.wxyz_from_xyzw([transform['rotation'][k] for k in 'xyzw'])
    np.testing.assert_allclose(t, result.translation, rtol=0, atol=1e-15)
    assert np.degrees(quat.angle_between(q, result.quaternion)) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)
    # The transform is the mounting T_link_sensor: close to the simulated ground truth.
    assert np.linalg.norm(np.asarray(t) - cell.mounting.position) < 0.003
    assert np.degrees(quat.angle_between(q, cell.mounting.quaternion)) < 0.3


def test_a_line_break_in_a_frame_name_stays_in_its_comment():
    """The name went into the header comment as it was: the file gained a top-level key."""
    result = FakeResult(quat.IDENTITY, np.array([0.6, -0.25, 0.83]))
    for child in ('camera\nmove_group: evil', 'camera\x85move_group: evil',
                  'camera\u2028move_group: evil'):
        document = yaml.safe_load(exports.easy_handeye2_yaml(result, 'tool0', child))
        assert list(document) == ['parameters', 'transform']
    assert document['parameters']['tracking_base_frame'].startswith('camera')


def test_easy_handeye2_eye_to_hand_is_eye_on_base():
    q = quat.normalize(np.array([-0.2, 0.5, 0.1, 0.8]))   # w < 0: written with w >= 0
    result = FakeResult(q, np.array([0.6, -0.25, 0.83]))
    document = yaml.safe_load(exports.easy_handeye2_yaml(
        result, 'base_link', 'camera', 'eye_to_hand', robot_effector_frame='tool0'))
    parameters = document['parameters']
    assert parameters['calibration_type'] == 'eye_on_base'
    assert parameters['robot_base_frame'] == 'base_link'      # the parent frame
    assert parameters['robot_effector_frame'] == 'tool0'
    assert parameters['tracking_base_frame'] == 'camera'
    assert parameters['name'] == 'quatcal_eye_to_hand'
    rotation = document['transform']['rotation']
    np.testing.assert_allclose([rotation[k] for k in 'wxyz'], -q, atol=1e-15)
    assert document['transform']['translation'] == {'x': 0.6, 'y': -0.25, 'z': 0.83}


def test_easy_handeye2_refuses_what_it_cannot_write():
    result = FakeResult(quat.IDENTITY.copy(), np.zeros(3))
    with pytest.raises(ValueError, match='setup'):
        exports.easy_handeye2_yaml(result, 'a', 'b', 'eye_on_base')
    with pytest.raises(ValueError, match='translation'):
        exports.easy_handeye2_yaml(FakeResult(quat.IDENTITY.copy(), None), 'a', 'b')
    with pytest.raises(ValueError, match='not finite'):
        exports.static_transform_publisher_command(
            FakeResult(quat.IDENTITY.copy(), np.array([0.0, np.nan, 0.0])), 'a', 'b')


def test_easy_handeye2_name_is_the_file_stem():
    assert exports.easy_handeye2_name('~/.ros2/easy_handeye2/calibrations/ur5.calib') == 'ur5'
    assert exports.easy_handeye2_name('/tmp/cell.yaml') == 'cell'


def parse_static_transform_publisher(line):
    """Parse the line as tf2_ros static_transform_publisher (Jazzy) parses its flags."""
    words = shlex.split(line)
    assert words[:4] == ['ros2', 'run', 'tf2_ros', 'static_transform_publisher']
    parser = argparse.ArgumentParser()
    for flag in ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw'):
        parser.add_argument(f'--{flag}', type=float, required=True)
    parser.add_argument('--frame-id', required=True)
    parser.add_argument('--child-frame-id', required=True)
    return parser.parse_args(words[4:])


def test_static_transform_publisher_line_parses_back(solved):
    _, _, result = solved
    line = exports.static_transform_publisher_command(result, 'tool0', 'camera')
    args = parse_static_transform_publisher(line)
    assert (args.frame_id, args.child_frame_id) == ('tool0', 'camera')
    np.testing.assert_allclose([args.x, args.y, args.z], result.translation, rtol=0,
                               atol=1e-10)
    q = quat.wxyz_from_xyzw([args.qx, args.qy, args.qz, args.qw])
    assert np.degrees(quat.angle_between(q, result.quaternion)) < 1e-6
    # The transform it broadcasts, parent <- child, is the result's.
    broadcast = Pose.create([args.x, args.y, args.z], q).as_matrix()
    np.testing.assert_allclose(broadcast[:3, :3], result.matrix, atol=1e-8)
    assert line.index('--x') < line.index('--qw') < line.index('--frame-id')


def test_static_transform_publisher_numbers_and_frames():
    result = FakeResult(quat.IDENTITY.copy(), np.array([-1e-18, 0.1, -2.5]))
    line = exports.static_transform_publisher_command(result, 'my base', 'cam/optical')
    assert ' -0 ' not in line and '--x 0 ' in line   # no negative zero
    args = parse_static_transform_publisher(line)
    assert (args.frame_id, args.child_frame_id) == ('my base', 'cam/optical')   # quoted
    assert (args.x, args.y, args.z, args.qw) == (0.0, 0.1, -2.5, 1.0)
    arguments = exports.static_transform_publisher_arguments(result, 'a', 'b')
    assert arguments[-4:] == ['--frame-id', 'a', '--child-frame-id', 'b']


def test_default_frames():
    assert exports.default_frames('eye_in_hand') == ('tool0', 'camera')
    assert exports.default_frames('eye_to_hand') == ('base_link', 'camera')
    with pytest.raises(ValueError):
        exports.default_frames('eye_on_base')


# --- through `python -m quatcal_ros solve` ----------------------------------------------------

def run_solve(repo_root, *args):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.run([sys.executable, '-m', 'quatcal_ros', 'solve', *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def test_solve_prints_the_line_and_writes_easy_handeye2(repo_root, solved, tmp_path):
    cell, samples, _ = solved
    path = tmp_path / 'samples.csv'
    path.write_text(format_samples(samples))
    calib = tmp_path / 'calibrations' / 'arm.calib'
    done = run_solve(repo_root, path, '--parent-frame', 'flange', '--child-frame', 'cam',
                     '--easy-handeye2-out', calib)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    args = parse_static_transform_publisher(out['static_transform_publisher'])
    assert (args.frame_id, args.child_frame_id) == ('flange', 'cam')
    np.testing.assert_allclose([args.x, args.y, args.z],
                               [out['translation'][k] for k in 'xyz'], rtol=0, atol=1e-10)
    np.testing.assert_allclose([args.qx, args.qy, args.qz, args.qw],
                               [out['rotation'][k] for k in 'xyzw'], rtol=0, atol=1e-9)
    document = yaml.safe_load(calib.read_text())
    assert document['parameters']['name'] == 'arm'
    assert document['parameters']['robot_effector_frame'] == 'flange'
    assert document['parameters']['tracking_base_frame'] == 'cam'
    assert document['transform']['rotation'] == out['rotation']
    assert document['transform']['translation'] == out['translation']
    assert np.linalg.norm([args.x - cell.mounting.position[0], args.y - cell.mounting.position[1],
                           args.z - cell.mounting.position[2]]) < 0.003


def test_solve_default_frames_follow_the_setup(repo_root, tmp_path):
    rng = np.random.default_rng(62)
    cell = simulation.random_cell(rng, 'eye_to_hand')
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    path = tmp_path / 'eth.csv'
    path.write_text(format_samples(samples))
    done = run_solve(repo_root, path, '--setup', 'eye_to_hand')
    assert done.returncode == 0, done.stderr
    args = parse_static_transform_publisher(json.loads(done.stdout)['static_transform_publisher'])
    assert (args.frame_id, args.child_frame_id) == ('base_link', 'camera')
    np.testing.assert_allclose([args.x, args.y, args.z], cell.mounting.position, atol=0.005)


def test_solve_reports_an_unwritable_easy_handeye2_file(repo_root, solved, tmp_path):
    _, samples, _ = solved
    path = tmp_path / 'samples.csv'
    path.write_text(format_samples(samples))
    blocker = tmp_path / 'file'
    blocker.write_text('')
    done = run_solve(repo_root, path, '--easy-handeye2-out', blocker / 'x.calib')
    assert done.returncode == 2
    assert f'x.calib: {blocker} is a file, not a folder' in done.stderr


def test_replay_prints_the_line_with_the_frames_of_the_messages(tmp_path, capsys):
    from quatcal_ros.ros import conversions
    from quatcal_ros.ros.bag import TYPESTORE, write_bag
    from quatcal_ros.tools.cli import replay_main
    rng = np.random.default_rng(63)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(rng, cell, 8, link_rate_hz=100.0,
                                             rotation_noise_deg=0.1,
                                             translation_noise_m=0.0005)
    kind = 'geometry_msgs/msg/TransformStamped'
    messages = [('/link', stamp, conversions.transform_stamped_msg(
        pose, stamp, 'base', 'flange', typestore=TYPESTORE)) for stamp, pose in streams.link]
    messages += [('/sensor', delivered, conversions.transform_stamped_msg(
        pose, stamp, 'cam', 'marker', typestore=TYPESTORE))
        for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    write_bag(tmp_path / 'bag', {'/link': kind, '/sensor': kind},
              sorted(messages, key=lambda m: m[1]), 'sqlite3')
    status = replay_main([str(tmp_path / 'bag'), '--link-topic', '/link', '--sensor-topic',
                          '/sensor', '--quiet'])
    assert status == 0
    out = json.loads(capsys.readouterr().out)
    args = parse_static_transform_publisher(out['static_transform_publisher'])
    assert (args.frame_id, args.child_frame_id) == ('flange', 'cam')
    np.testing.assert_allclose([args.x, args.y, args.z],
                               [out['translation'][k] for k in 'xyz'], rtol=0, atol=1e-10)


def test_the_urdf_joint_and_xacro_macro_hold_the_mounting():
    """Check rpy (URDF's Rz(yaw) Ry(pitch) Rx(roll), gimbal lock included) and the XML."""
    import xml.etree.ElementTree as ElementTree

    from quatcal_ros.core.calibration import Estimate
    rng = np.random.default_rng(3)
    quaternions = list(quat.normalize(rng.normal(size=(50, 4))))
    quaternions += [quat.from_axis_angle([0, 1, 0], np.pi / 2),
                    quat.multiply(quat.from_axis_angle([0, 0, 1], 0.3),
                                  quat.from_axis_angle([0, 1, 0], -np.pi / 2))]
    for q in quaternions:
        result = Estimate(q, np.array([0.01, -0.2, 0.35]), 0.1, 1.0)
        roll, pitch, yaw = exports.urdf_rpy(result)
        turn = [quat.matrix_from_quaternion(quat.from_axis_angle(axis, angle))
                for axis, angle in (([0, 0, 1], yaw), ([0, 1, 0], pitch), ([1, 0, 0], roll))]
        np.testing.assert_allclose(turn[0] @ turn[1] @ turn[2],
                                   quat.matrix_from_quaternion(q), atol=1e-9)
    joint = ElementTree.fromstring(exports.urdf_joint(result, 'tool0', 'camera'))
    assert joint.get('type') == 'fixed' and joint.find('parent').get('link') == 'tool0'
    assert joint.find('child').get('link') == 'camera'
    origin = joint.find('origin')
    np.testing.assert_allclose([float(v) for v in origin.get('xyz').split()], [0.01, -0.2, 0.35])
    np.testing.assert_allclose([float(v) for v in origin.get('rpy').split()],
                               exports.urdf_rpy(result), atol=1e-9)
    robot = ElementTree.fromstring(exports.xacro_macro(result, 'tool0', 'camera'))
    macro = robot.find('{http://www.ros.org/wiki/xacro}macro')
    assert macro.get('params') == 'parent:=tool0'
    assert macro.find('joint/parent').get('link') == '${parent}'


@pytest.mark.parametrize('child, name', [
    ('camera', 'camera_mount'), ('robot1/camera_link', 'robot1_camera_link_mount'),
    ('cam:optical', 'cam_optical_mount'), ('3d_camera', '_3d_camera_mount'),
    ('cam link', 'cam_link_mount'), ('cam${x}', 'cam__x__mount')])
def test_the_xacro_macro_can_be_called_for_any_frame_name(child, name):
    """
    Its name was CHILD_mount as it is: no <xacro:robot1/camera_link_mount/> can be written.

    And xacro evaluates ${...} and $(...) in attributes: a frame name holding one is escaped
    ($${, which xacro reads back as ${). Checked with xacro 2.1.1 itself by hand.
    """
    import xml.etree.ElementTree as ElementTree

    from quatcal_ros.core.calibration import Estimate
    result = Estimate(quat.IDENTITY, np.array([0.01, -0.2, 0.35]), 0.1, 1.0)
    text = exports.xacro_macro(result, 'tool${0}', child)
    macro = ElementTree.fromstring(text).find('{http://www.ros.org/wiki/xacro}macro')
    assert macro.get('name') == name and macro.get('params') == 'parent:=tool$${0}'
    ElementTree.fromstring(f'<r xmlns:xacro="x"><xacro:{name} parent="p"/></r>')   # callable
    assert macro.find('joint/child').get('link') == child.replace('${', '$${')


def test_a_joint_note_is_a_well_formed_xml_comment():
    # With TF input the joint is the one the tree can take, and says why above it; a frame
    # name with -- in it must not end the comment early.
    import xml.etree.ElementTree as ElementTree
    from types import SimpleNamespace
    result = SimpleNamespace(quaternion=[1.0, 0.0, 0.0, 0.0], translation=[0.1, 0.0, 0.2])
    note = 'cam---optical already hangs from camera in TF: the static camera -> cam---optical'
    joints = exports.description_joints(result, 'tool0', 'camera', note)
    for text in joints.values():
        assert '<!-- cam- - -optical already hangs from camera in TF' in text
        ElementTree.fromstring(text)   # well formed (a -- inside a comment is not)
    assert exports.description_joints(result, 'tool0', 'camera')['urdf'].startswith('<joint')
