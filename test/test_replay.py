"""`python -m quatcal_ros replay BAG_DIR ...`: DESIGN.md contract 3 on rosbag2 recordings."""

import csv
import dataclasses
import io
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import journal
from quatcal_ros.files.persistence import read_result_yaml
from quatcal_ros.files.samples_csv import read_samples
from quatcal_ros.ros import conversions
from quatcal_ros.ros.bag import ReplayReport, TF_TYPE, TYPESTORE, write_bag
from quatcal_ros.sim import simulation as sim
from quatcal_ros.stream.session import Session, SessionConfig
from quatcal_ros.tools.cli import _few_samples, replay_main, solve_main
from quatcal_ros.tools.progress import Progress
import yaml

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TRANSFORM_STAMPED = 'geometry_msgs/msg/TransformStamped'
MS = 1_000_000


def run_replay(repo_root, *args):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.run([sys.executable, '-m', 'quatcal_ros', 'replay', *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def run_solve(repo_root, *args):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.run([sys.executable, '-m', 'quatcal_ros', 'solve', *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def rotation(out):
    r = out['rotation']
    return quat.wxyz_from_xyzw([r['x'], r['y'], r['z'], r['w']])


def assert_recovers(done, truth):
    assert done.returncode == 0, done.stderr
    assert 'Traceback' not in done.stderr
    out = json.loads(done.stdout)
    error = np.degrees(quat.angle_between(rotation(out), truth.quaternion))
    assert error < 3 * out['uncertainty_deg'], (error, out['uncertainty_deg'])
    return out


def msg(kind, pose, stamp, frame, child=None):
    if kind == POSE_STAMPED:
        return conversions.pose_stamped_msg(pose, stamp, frame, typestore=TYPESTORE)
    return conversions.transform_stamped_msg(pose, stamp, frame, child, typestore=TYPESTORE)


def tf_message(*transforms):
    return TYPESTORE.types[TF_TYPE](transforms=list(transforms))


@pytest.fixture(scope='module')
def streams():
    """Simulate a stop-and-go run: 10 stops, link 200 Hz, camera 30 Hz (late, 5 % dropped)."""
    rng = np.random.default_rng(50)
    cell = sim.random_cell(rng)
    return sim.stop_and_go_streams(rng, cell, 10, link_rate_hz=200.0, rotation_noise_deg=0.2,
                                   translation_noise_m=0.001)


def topic_messages(streams, kind):
    """Link T_base_tool0 on /link_pose, sensor T_camera_marker on /sensor_pose."""
    link = [('/link_pose', stamp + MS, msg(kind, pose, stamp, 'base', 'tool0'))
            for stamp, pose in streams.link]
    sensor = [('/sensor_pose', delivered, msg(kind, pose, stamp, 'camera', 'marker'))
              for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    return sorted(link + sensor, key=lambda m: m[1])


@pytest.fixture(scope='module')
def bags(tmp_path_factory, streams):
    """Write the run as PoseStamped (sqlite3) and as TransformStamped (mcap) bags."""
    root = tmp_path_factory.mktemp('replay')
    write_bag(root / 'pose', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              topic_messages(streams, POSE_STAMPED), 'sqlite3')
    write_bag(root / 'transform', {'/link_pose': TRANSFORM_STAMPED,
                                   '/sensor_pose': TRANSFORM_STAMPED},
              topic_messages(streams, TRANSFORM_STAMPED), 'mcap')
    return root


def test_pose_stamped_bag_gives_the_mounting_and_the_samples_solve_agrees(
        repo_root, bags, streams, tmp_path):
    csv_path, yaml_path = tmp_path / 'out' / 'samples.csv', tmp_path / 'out' / 'result.yaml'
    done = run_replay(repo_root, bags / 'pose', '--link-topic', '/link_pose', '--sensor-topic',
                      '/sensor_pose', '--samples-out', csv_path, '--result-out', yaml_path,
                      '--parent-frame', 'tool0')
    out = assert_recovers(done, streams.truth)
    assert out['samples'] == 10 and out['motions'] == 45 and out['warnings'] == []
    assert 'replay: ' in done.stderr and '10 samples (auto capture)' in done.stderr
    with open(csv_path) as stream:
        assert len(list(csv.reader(stream))) == 11
    solved = run_solve(repo_root, csv_path)
    assert solved.returncode == 0, solved.stderr
    assert_allclose(rotation(json.loads(solved.stdout)), rotation(out), atol=1e-9)
    document = read_result_yaml(yaml_path)
    assert document['parent_frame'] == 'tool0' and document['child_frame'] == 'camera'
    assert document['setup'] == 'eye_in_hand'
    assert document['quality']['samples'] == 10
    assert document['source']['link'] == '/link_pose'
    assert_allclose(document['quaternion_xyzw'], quat.xyzw_from_wxyz(rotation(out)))
    # --parent-frame given and the child frame named by the messages: no note. Without the
    # option, the note says which frame the messages lack (it named the option as if given).
    assert 'note:' not in done.stderr
    done = run_replay(repo_root, bags / 'pose', *TOPICS, '--result-out', yaml_path)
    assert done.returncode == 0, done.stderr
    assert ('replay: note: the messages name no parent frame for the result (a PoseStamped '
            "names only the frame it is in, not a child frame): 'tool0' written to "
            f'{yaml_path}; --parent-frame sets it') in done.stderr, done.stderr
    assert 'no child frame' not in done.stderr


def test_a_pose_bag_replay_loads_no_opencv(repo_root, bags):
    """A pose replay does without OpenCV (15 MB resident): only bags of images need it."""
    bag = str(bags / 'pose')
    code = ('import runpy, sys\n'
            f'sys.argv = ["quatcal_ros", "replay", {bag!r}, "--link-topic",\n'
            '            "/link_pose", "--sensor-topic", "/sensor_pose", "--quiet"]\n'
            'try:\n'
            '    runpy.run_module("quatcal_ros", run_name="__main__")\n'
            'except SystemExit as stop:\n'
            '    assert not stop.code, stop.code\n'
            'loaded = [m for m in ("cv2", "matplotlib", "rclpy") if m in sys.modules]\n'
            'sys.exit(f"loaded {loaded}" if loaded else 0)\n')
    done = subprocess.run([sys.executable, '-c', code], cwd=repo_root, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert '"rotation"' in done.stdout


@pytest.mark.parametrize('option', ['--samples-out', '--journal-out', '--result-out',
                                    '--report'])
def test_an_output_into_the_bag_is_refused_and_the_bag_kept(bags, option, capsys):
    """--samples-out BAG/x.db3 once replaced the recording with a CSV."""
    (database,) = [p for p in (bags / 'pose').iterdir() if p.suffix in ('.db3', '.mcap')]
    for target in (database, bags / 'pose' / 'metadata.yaml'):
        before = target.read_bytes()
        argv = [str(bags / 'pose'), '--link-topic', '/link_pose', '--sensor-topic',
                '/sensor_pose', option, str(target)]
        assert replay_main(argv) == 2
        assert f'{option} {target}: that is an input file' in capsys.readouterr().err
        assert target.read_bytes() == before


def test_the_replay_writes_a_journal_the_node_resumes(bags, tmp_path, capsys):
    journal_path = tmp_path / 'samples.csv'
    journal_path.write_text('an earlier file\n')
    argv = [str(bags / 'pose'), '--link-topic', '/link_pose', '--sensor-topic', '/sensor_pose',
            '--journal-out', str(journal_path), '--child-frame', 'camera_optical']
    assert replay_main(argv) == 0
    printed = capsys.readouterr()
    out = json.loads(printed.out)
    # moved aside and the journal written: a warning (it once said error, with exit 0)
    assert 'replay: warning: ' in printed.err and 'error' not in printed.err
    contents = journal.read_journal(journal_path)
    assert len(contents.samples) == out['samples'] == 10
    assert contents.header == journal.JournalHeader('eye_in_hand', 'tool0', 'camera_optical',
                                                    False, sensor_time_offsets=(0.0,))
    # The offset the samples were paired with (a node resuming with another one says so).
    assert replay_main(argv + ['--quiet', '--sensor-time-offset', '-0.02']) == 0
    assert journal.read_journal(journal_path).header.sensor_time_offsets == (-0.02,)
    capsys.readouterr()
    (aside,) = [p for p in tmp_path.iterdir() if p.name.startswith('samples.csv.corrupt-')]
    assert aside.read_text() == 'an earlier file\n'    # moved aside, never overwritten
    # Over the journal of the first run: moved aside, without the node's resume:=true advice
    # (no offline tool resumes one).
    assert replay_main(argv + ['--quiet']) == 0
    said = capsys.readouterr().err
    assert 'held 10 samples of an earlier session: moved to ' in said, said
    assert 'resume:=true' not in said, said


def test_samples_are_those_of_the_session_fed_by_hand(bags, streams, tmp_path, capsys):
    """The replay (collecting, then one estimate) captures what the node's session would."""
    status = replay_main([str(bags / 'pose'), '--link-topic', '/link_pose', '--sensor-topic',
                          '/sensor_pose', '--samples-out', str(tmp_path / 's.csv'), '--quiet'])
    assert status == 0
    session = Session()   # the default options: the refined estimator
    fed = [(stamp + MS, 0, stamp, pose) for stamp, pose in streams.link]
    fed += [(delivered, 1, stamp, pose)
            for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    for _, stream, stamp, pose in sorted(fed, key=lambda m: m[:2]):
        (session.add_link_pose if stream == 0 else session.add_sensor_pose)(stamp, pose)
    replayed = read_samples(tmp_path / 's.csv')
    assert len(replayed) == len(session.samples) == 10
    for ours, theirs in zip(replayed, session.samples):
        assert abs(ours.stamp_ns - theirs.stamp_ns) < 1000   # the CSV holds seconds
        assert_allclose(ours.link.quaternion, theirs.link.quaternion, atol=1e-12)
        assert_allclose(ours.sensor.position, theirs.sensor.position, atol=1e-12)
    out = json.loads(capsys.readouterr().out)
    session.estimate()
    assert_allclose(rotation(out), session.result.quaternion, atol=1e-6)


def test_transform_stamped_mcap_bag(repo_root, bags, streams, tmp_path):
    done = run_replay(repo_root, bags / 'transform', '--link-topic', '/link_pose',
                      '--sensor-topic', '/sensor_pose', '--result-out', tmp_path / 'r.yaml',
                      '--quiet')
    out = assert_recovers(done, streams.truth)
    assert out['samples'] == 10 and done.stderr == ''
    document = read_result_yaml(tmp_path / 'r.yaml')
    assert (document['parent_frame'], document['child_frame']) == ('tool0', 'camera')


def test_tf_bag_with_static_frames_in_both_chains(repo_root, streams, tmp_path):
    """
    /tf and /tf_static, as robot_state_publisher and a marker detector publish them.

    Link: base_link -(static)-> robot_base -> shoulder -> tool0 (two joints, one message);
    sensor: camera -(static)-> camera_optical -> marker (the detector); plus unrelated frames.
    """
    rng = np.random.default_rng(51)
    base_mount, optical = (Pose(rng.uniform(-0.5, 0.5, 3), sim.random_quaternions(rng, 1)[0])
                           for _ in range(2))
    messages = [('/tf_static', streams.link[0][0], tf_message(
        conversions.transform_stamped_msg(base_mount, 0, 'base_link', 'robot_base',
                                          typestore=TYPESTORE),
        conversions.transform_stamped_msg(optical, 0, 'camera', 'camera_optical',
                                          typestore=TYPESTORE)))]
    for stamp, pose in streams.link:
        shoulder = Pose(pose.position / 2, quat.IDENTITY)
        messages.append(('/tf', stamp + MS, tf_message(
            msg(TRANSFORM_STAMPED, shoulder, stamp, 'robot_base', 'shoulder'),
            msg(TRANSFORM_STAMPED, shoulder.inverse() @ pose, stamp, 'shoulder', 'tool0'),
            msg(TRANSFORM_STAMPED, pose, stamp, 'map', 'odom'))))
    for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns):
        messages.append(('/tf', delivered, tf_message(
            msg(TRANSFORM_STAMPED, optical.inverse() @ pose, stamp, 'camera_optical',
                'marker'))))
    messages.sort(key=lambda m: m[1])
    write_bag(tmp_path / 'tf', {'/tf': TF_TYPE, '/tf_static': TF_TYPE}, messages, 'mcap')
    # Leading slashes (tf1's style) name the same frames and stay out of the outputs.
    done = run_replay(repo_root, tmp_path / 'tf', '--link-frames', '/base_link', '/tool0',
                      '--sensor-frames', 'camera', 'marker', '--result-out',
                      tmp_path / 'r.yaml', '--easy-handeye2-out', tmp_path / 'cell.calib')
    out = assert_recovers(done, streams.truth)
    # easy_handeye2's file too (only solve wrote it), with the frames the TF input named.
    calib = yaml.safe_load((tmp_path / 'cell.calib').read_text())
    assert calib['transform']['rotation'] == out['rotation']
    assert calib['transform']['translation'] == out['translation']
    assert {key: calib['parameters'][key] for key in (
        'robot_base_frame', 'robot_effector_frame', 'tracking_base_frame',
        'tracking_marker_frame')} == {'robot_base_frame': 'base_link',
                                      'robot_effector_frame': 'tool0',
                                      'tracking_base_frame': 'camera',
                                      'tracking_marker_frame': 'marker'}
    assert out['static_transform_publisher'].endswith('--frame-id tool0 --child-frame-id camera')
    assert out['samples'] == 10 and out['warnings'] == []
    assert f'{len(streams.link)} link and {len(streams.sensor)} sensor poses' in done.stderr
    document = read_result_yaml(tmp_path / 'r.yaml')
    assert (document['parent_frame'], document['child_frame']) == ('tool0', 'camera')
    # The link frames given the wrong way round compose too (the inverse pose): the warnings
    # advised eye_to_hand, not the frames.
    swapped = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'tool0', 'base_link',
                         '--sensor-frames', 'camera', 'marker', '--quiet')
    assert swapped.returncode == 0, swapped.stderr
    said = json.loads(swapped.stdout)['warnings']
    assert said[0] == (
        'TF input: the link frames look swapped: the base frame given, tool0, hangs below '
        'the effector frame given, base_link, in the TF tree; a link pose is the effector in '
        'the robot base frame (base base_link, effector tool0?)'), said
    # The cause comes first, on stderr too: it was last in the JSON, and stderr gave only
    # the advice it makes wrong (set setup to eye_to_hand).
    errors = swapped.stderr.splitlines()
    assert errors[0].startswith(f'replay: warning: {tmp_path / "tf"}: TF input: the link frames '
                                'look swapped'), swapped.stderr
    assert any('set setup to eye_to_hand' in line for line in errors[1:]), swapped.stderr


def test_a_tf_bag_gives_the_joint_the_tree_can_take(repo_root, streams, tmp_path, capsys):
    """
    The sensor frame the detector names (camera_optical) hangs from camera in the bag.

    The command, the URDF joint and the xacro macro were tool0 -> camera_optical: pasted,
    a second parent. They are tool0 -> camera, the mounting composed with the static
    camera -> camera_optical; the result file's transform stays the calibrated one.
    """
    optical = Pose.create([0.01, 0.02, 0.0], [0.5, -0.5, 0.5, -0.5])
    messages = [('/tf_static', streams.link[0][0], tf_message(
        conversions.transform_stamped_msg(optical, 0, 'camera', 'camera_optical',
                                          typestore=TYPESTORE)))]
    messages += [('/tf', stamp + MS, tf_message(msg(TRANSFORM_STAMPED, pose, stamp,
                                                    'base_link', 'tool0')))
                 for stamp, pose in streams.link]
    messages += [('/tf', delivered, tf_message(msg(TRANSFORM_STAMPED, optical.inverse() @ pose,
                                                   stamp, 'camera_optical', 'marker')))
                 for (stamp, pose), delivered in zip(streams.sensor,
                                                     streams.sensor_delivery_ns)]
    write_bag(tmp_path / 'tf', {'/tf': TF_TYPE, '/tf_static': TF_TYPE},
              sorted(messages, key=lambda m: m[1]), 'mcap')
    done = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                      '--sensor-frames', 'camera_optical', 'marker', '--result-out',
                      tmp_path / 'r.yaml', '--journal-out', tmp_path / 'journal.csv')
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    command = out['static_transform_publisher']
    assert command.endswith('--frame-id tool0 --child-frame-id camera'), command
    values = [float(v) for v in re.findall(r'--(?:x|y|z|qx|qy|qz|qw) (\S+)', command)]
    joined = Pose.create(values[:3], quat.wxyz_from_xyzw(values[3:]))
    calibrated = Pose.create([out['translation'][k] for k in 'xyz'], rotation(out))
    assert_allclose(joined.position, (calibrated @ optical.inverse()).position, atol=1e-9)
    assert np.degrees(quat.angle_between(joined.quaternion, streams.truth.quaternion)) < \
        3 * out['uncertainty_deg']
    document = read_result_yaml(tmp_path / 'r.yaml')
    assert (document['parent_frame'], document['child_frame']) == ('tool0', 'camera_optical')
    note = ('<!-- camera_optical already hangs from camera in TF: the mounting composed with '
            'the static camera -> camera_optical -->')
    for text in (out['urdf'], document['urdf'], document['xacro']):
        assert note in text and '<child link="camera"/>' in text, text
        assert 'camera_optical_mount' not in text
    # The journal records the static chain: solved later, it gives the same joint; solved
    # for another sensor frame, the calibrated edge (the chain is camera_optical's).
    assert solve_main([str(tmp_path / 'journal.csv'), '--result-out',
                       str(tmp_path / 'again.yaml')]) == 0
    solved = json.loads(capsys.readouterr().out)
    assert solved['static_transform_publisher'].endswith('--child-frame-id camera')
    assert note in solved['urdf'] and note in read_result_yaml(tmp_path / 'again.yaml')['urdf']
    again = [float(v) for v in re.findall(r'--(?:x|y|z|qx|qy|qz|qw) (\S+)',
                                          solved['static_transform_publisher'])]
    assert_allclose(again, values, atol=1e-6)   # (the same samples, solved again)
    assert solve_main([str(tmp_path / 'journal.csv'), '--child-frame', 'lens']) == 0
    solved = json.loads(capsys.readouterr().out)
    assert solved['static_transform_publisher'].endswith('--frame-id tool0 --child-frame-id lens')
    assert 'already hangs' not in solved['urdf']


def test_a_joint_that_would_break_the_tree_is_said_in_the_json_and_the_result_file(
        repo_root, streams, tmp_path):
    # The camera hangs from a moving frame on /tf: any joint to it gives it a second parent.
    messages = [('/tf', stamp + MS, tf_message(msg(TRANSFORM_STAMPED, pose, stamp,
                                                   'base_link', 'tool0')))
                for stamp, pose in streams.link]
    messages += [('/tf', stamp + MS, tf_message(msg(TRANSFORM_STAMPED, Pose.identity(), stamp,
                                                    'shoulder', 'camera')))
                 for stamp, _ in streams.link]
    messages += [('/tf', delivered, tf_message(msg(TRANSFORM_STAMPED, pose, stamp, 'camera',
                                                   'marker')))
                 for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    write_bag(tmp_path / 'tf', {'/tf': TF_TYPE}, sorted(messages, key=lambda m: m[1]), 'mcap')
    done = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                      '--sensor-frames', 'camera', 'marker', '--result-out',
                      tmp_path / 'r.yaml')
    said = [w for w in json.loads(done.stdout)['warnings'] if w.startswith('TF: ')]
    assert len(said) == 1 and 'second parent' in said[0], done.stdout
    # The result file said it in its URDF comment alone.
    assert said == [w for w in read_result_yaml(tmp_path / 'r.yaml')['warnings']
                    if w.startswith('TF: ')]


def replay_with_marker_on_tf(repo_root, tmp_path, streams, messages):
    """Replay TF `messages` and the marker on /tf (camera -> marker), base_link -> tool0."""
    messages = messages + [
        ('/tf', delivered, tf_message(msg(TRANSFORM_STAMPED, pose, stamp, 'camera', 'marker')))
        for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    write_bag(tmp_path / 'tf', {'/tf': TF_TYPE, '/tf_static': TF_TYPE},
              sorted(messages, key=lambda m: m[1]), 'mcap')
    return run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                      '--sensor-frames', 'camera', 'marker')


def test_a_static_transform_sent_again_holds_from_where_it_is_in_the_bag(repo_root, streams,
                                                                         tmp_path):
    """
    A /tf_static edge republished with a new value mid-bag (a robot base re-measured).

    A live listener applies each value from when it arrives; the replay once applied the last
    value to the whole bag: the first half's link poses were off by the change.
    """
    rng = np.random.default_rng(53)
    mounts = [Pose(rng.uniform(-0.5, 0.5, 3), sim.random_quaternions(rng, 1)[0])]
    mounts.append(Pose(mounts[0].position + 0.1,
                       quat.multiply(quat.from_rotation_vector(np.radians([20.0, 0, 0])),
                                     mounts[0].quaternion)))
    middle = streams.link[len(streams.link) // 2][0]
    messages = [('/tf_static', at, tf_message(conversions.transform_stamped_msg(
        mount, 0, 'base_link', 'robot_base', typestore=TYPESTORE)))
        for at, mount in ((streams.link[0][0], mounts[0]), (middle - MS // 2, mounts[1]))]
    for stamp, pose in streams.link:   # the joints as measured under the mount of the time
        mount = mounts[stamp >= middle]
        messages.append(('/tf', stamp + MS, tf_message(
            msg(TRANSFORM_STAMPED, mount.inverse() @ pose, stamp, 'robot_base', 'tool0'))))
    done = replay_with_marker_on_tf(repo_root, tmp_path, streams, messages)
    out = assert_recovers(done, streams.truth)
    # (measured: 0.12 deg RMS; with the last value everywhere 14.7 deg, and two warnings)
    assert out['warnings'] == [] and out['residual_rms_deg'] < 1.0


@pytest.mark.parametrize('static_topic', [True, False])
def test_a_tf_bag_missing_a_static_frame_names_it_and_tf_static(repo_root, streams, tmp_path,
                                                                static_topic):
    """The camera -> optical transform was not recorded: say which frame and suggest why."""
    rng = np.random.default_rng(52)
    optical = Pose(rng.uniform(-0.5, 0.5, 3), sim.random_quaternions(rng, 1)[0])
    messages = [('/tf', stamp, tf_message(msg(TRANSFORM_STAMPED, pose, stamp, 'base_link',
                                              'tool0')))
                for stamp, pose in streams.link]
    messages += [('/tf', delivered, tf_message(msg(TRANSFORM_STAMPED, optical.inverse() @ pose,
                                                   stamp, 'camera_optical', 'marker')))
                 for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    topics = {'/tf': TF_TYPE}
    if static_topic:   # holding another static transform only
        topics['/tf_static'] = TF_TYPE
        messages.append(('/tf_static', streams.link[0][0], tf_message(
            conversions.transform_stamped_msg(Pose.identity(), 0, 'world', 'base_link',
                                              typestore=TYPESTORE))))
    write_bag(tmp_path / 'tf', topics, sorted(messages, key=lambda m: m[1]), 'mcap')
    done = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                      '--sensor-frames', 'camera', 'marker')
    assert done.returncode == 2
    assert ('no sensor poses from TF camera -> marker (camera and marker are not connected in '
            'the transform tree: camera is in no transform received)') in done.stderr
    if static_topic:
        assert 'No transform on /tf_static names camera either: check the frame name' \
            in done.stderr
        # Not asked for: it said the bag had no /tf_static.
        only_tf = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                             '--sensor-frames', 'camera', 'marker', '--tf-topics', '/tf')
        assert only_tf.returncode == 2
        assert ('The bag has /tf_static, but --tf-topics did not ask for it: fixed frames'
                in only_tf.stderr), only_tf.stderr
    else:
        assert 'The bag has no /tf_static' in done.stderr
        assert 'ros2 bag record /tf /tf_static' in done.stderr


def test_tf_frames_that_cannot_move_are_named(repo_root, streams, tmp_path):
    """A link chain of static transforms only, or one frame twice: 'no link poses' and why."""
    messages = [('/tf_static', streams.link[0][0], tf_message(msg(
        TRANSFORM_STAMPED, streams.link[0][1], 0, 'base_link', 'tool0')))]
    done = replay_with_marker_on_tf(repo_root, tmp_path, streams, messages)
    assert done.returncode == 2
    assert ('no link poses from TF base_link -> tool0 (every transform between base_link and '
            'tool0 is static: no pose moves') in done.stderr
    same = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'tool0', '/tool0',
                      '--sensor-frames', 'camera', 'marker')
    assert same.returncode == 2
    assert 'the frames tool0 -> tool0 are one frame: its pose never moves' in same.stderr


@pytest.fixture(scope='module')
def eth_bag(eth_streams, tmp_path_factory):
    """Convert the ETH robot-arm recording to a bag: link 50 Hz, camera in target 30 Hz."""
    messages = [(topic, stamp, msg(POSE_STAMPED, pose, stamp, frame))
                for (topic, frame), recorded in zip((('/link', 'base_link'),
                                                     ('/camera', 'target')), eth_streams)
                for stamp, pose in recorded]
    path = tmp_path_factory.mktemp('eth') / 'eth'
    write_bag(path, {'/link': POSE_STAMPED, '/camera': POSE_STAMPED},
              sorted(messages, key=lambda m: m[1]))
    return path


def test_eth_real_recording_replays_in_continuous_mode(repo_root, eth_bag):
    done = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic', '/camera',
                      '--invert-sensor', '--capture', 'continuous')
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out['residual_rms_deg'] < 1.0 and out['samples'] > 30
    # Taken in motion, the samples need the streams' time offset (20 ms here, which moves
    # the answer by 1.3 times its uncertainty): said, with how far 10 ms moves them.
    (moving,) = [w for w in out['warnings'] if 'taken while the link turned' in w]
    assert moving == ('the samples were taken while the link turned (median 8.1 deg/s between '
                      'them): each 10 ms by which the sensor stamps are off moves them by about '
                      '0.081 deg (the uncertainty: 0.16 deg); --estimate-time-offset measures '
                      'the offset (or give it, --sensor-time-offset)')
    # Auto mode finds no stop in this recording and falls back, saying so.
    auto = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic', '/camera',
                      '--invert-sensor')
    assert auto.returncode == 0, auto.stderr
    fallback = json.loads(auto.stdout)
    assert any('no still samples in auto mode' in w for w in fallback['warnings'])
    assert_allclose(rotation(fallback), rotation(out), atol=1e-12)
    strict = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic',
                        '/camera', '--invert-sensor', '--no-fallback')
    assert strict.returncode == 2 and 'use --capture continuous' in strict.stderr
    assert 'Traceback' not in strict.stderr


def test_poses_to_bag_writes_the_recordings_bag_from_its_files(repo_root, eth_bag, tmp_path,
                                                               datasets_dir, capsys):
    # The ETH recording is two files of timed poses: poses_to_bag gives replay the bag of this
    # module's own conversion (eth_streams reads the files as poses_to_bag does; its bag was
    # built with float stamps, off by up to about 128 ns, once: the tolerances below).
    from quatcal_ros.tools.poses_to_bag import interpreter, main
    folder, out = datasets_dir / 'ethz_robot_arm_real', tmp_path / 'eth'
    assert main([str(folder / 'link_hinge_in_base.csv'), str(folder / 'ir_camera_in_target.csv'),
                 str(out), '--link-topic', '/link', '--sensor-topic', '/camera',
                 '--sensor-frame-id', 'target']) == 0
    printed = capsys.readouterr().out
    assert printed == (
        f'{out}: 2817 link poses on /link, 1703 sensor poses on /camera (sqlite3). Replay it '
        f'with:\n  {interpreter()} -m quatcal_ros replay {out} --link-topic /link '
        '--sensor-topic /camera\n')
    # The command it prints runs as it is (a bare `python` was not this Python).
    command = printed.splitlines()[1].split() + ['--invert-sensor', '--capture', 'continuous']
    assert command[0] != 'python' and subprocess.run(
        command, capture_output=True, cwd=os.getcwd()).returncode == 0
    options = ('--link-topic', '/link', '--sensor-topic', '/camera', '--invert-sensor',
               '--capture', 'continuous')
    ours, theirs = (run_replay(repo_root, bag, *options) for bag in (out, eth_bag))
    assert ours.returncode == theirs.returncode == 0, ours.stderr + theirs.stderr
    ours, theirs = json.loads(ours.stdout), json.loads(theirs.stdout)
    assert ours['samples'] == theirs['samples']
    assert_allclose(rotation(ours), rotation(theirs), atol=1e-7)
    assert_allclose([ours['translation'][k] for k in 'xyz'],
                    [theirs['translation'][k] for k in 'xyz'], atol=1e-8)   # metres
    assert ours['residual_rms_deg'] == pytest.approx(theirs['residual_rms_deg'], abs=1e-6)
    # Never over a bag, nor into a folder that exists.
    assert main([str(folder / 'link_hinge_in_base.csv'), str(folder / 'ir_camera_in_target.csv'),
                 str(out)]) == 2
    assert f'poses_to_bag: error: {out} exists: give a new directory' in capsys.readouterr().err


def test_eth_time_offset_is_estimated_applied_and_reported(repo_root, eth_bag):
    done = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic', '/camera',
                      '--invert-sensor', '--capture', 'continuous', '--estimate-time-offset')
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    found = out['time_offset']
    # Measured on this recording (test_time_offset.py): the camera stamps are ~22 ms late.
    assert -0.040 < found['sensor_offset_s'] < -0.005
    assert 'searched_around_s' not in found   # logged at their stamps: one clock
    assert found['residual_with_deg'] < found['residual_without_deg']
    assert any(w.startswith('time offset: sensor stamps shifted by') for w in out['warnings'])
    assert not any('taken while the link turned' in w for w in out['warnings'])
    # Auto capture finds no stop here: it falls back with the search too (it once exited 2).
    auto = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic', '/camera',
                      '--invert-sensor', '--estimate-time-offset')
    assert auto.returncode == 0, auto.stderr
    fallback = json.loads(auto.stdout)
    assert any('no still samples in auto mode' in w for w in fallback['warnings'])
    assert fallback['time_offset'] == found
    assert_allclose(rotation(fallback), rotation(out), atol=1e-12)
    fixed = run_replay(repo_root, eth_bag, '--link-topic', '/link', '--sensor-topic', '/camera',
                       '--invert-sensor', '--capture', 'continuous',
                       '--sensor-time-offset', str(found['sensor_offset_s']))
    assert fixed.returncode == 0, fixed.stderr
    assert_allclose(rotation(json.loads(fixed.stdout)), rotation(out), atol=1e-9)
    assert not any('taken while the link turned' in w
                   for w in json.loads(fixed.stdout)['warnings'])


def test_malformed_messages_are_skipped_and_reported(repo_root, streams, tmp_path):
    messages = topic_messages(streams, POSE_STAMPED)
    sensor = [m for m in messages if m[0] == '/sensor_pose']
    sensor[3][2].pose.position.y = float('nan')
    for m in sensor[10:12]:
        m[2].pose.orientation.x = m[2].pose.orientation.y = 0.0
        m[2].pose.orientation.z = m[2].pose.orientation.w = 0.0
    write_bag(tmp_path / 'bad', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              messages)
    done = run_replay(repo_root, tmp_path / 'bad', '--link-topic', '/link_pose',
                      '--sensor-topic', '/sensor_pose')
    out = assert_recovers(done, streams.truth)
    warnings = '\n'.join(out['warnings'])
    assert '/sensor_pose: 1 message(s) skipped (non_finite): pose.position.y is nan' in warnings
    assert '/sensor_pose: 2 message(s) skipped (zero_quaternion): pose.orientation has norm ' \
        '0.00' in warnings


@pytest.mark.parametrize('shift, status', [((1.0, 1.0, 1.0), 0), ((0.0, 0.0, 1.0), 3)])
def test_motions_about_one_axis(repo_root, tmp_path, shift, status):
    """
    Stops turned about one axis only (as a SCARA's): solved with the offset along it named.

    Unless the link moves only along that axis: then nothing fixes the rotation (exit 3).
    """
    rng = np.random.default_rng(52)
    cell = sim.random_cell(rng)
    axis = [0.0, 0.0, 1.0]
    messages = []
    for k, angle in enumerate(np.radians([0.0, 20.0, 45.0, 70.0, 95.0])):
        link = Pose(cell.home.position + 0.02 * k * np.asarray(shift),
                    quat.multiply(quat.from_axis_angle(axis, angle), cell.home.quaternion))
        sensor = cell.sensor_pose(link)
        start = sim.DEFAULT_START_NS + k * 2 * 10**9
        for j in range(100):   # a second still at each stop, link 100 Hz, camera 25 Hz
            stamp = start + j * 10 * MS
            messages.append(('/link_pose', stamp, msg(POSE_STAMPED, link, stamp, 'base')))
            if j % 4 == 0:
                messages.append(('/sensor_pose', stamp + 20 * MS,
                                 msg(POSE_STAMPED, sensor, stamp, 'camera')))
    write_bag(tmp_path / 'one_axis', {'/link_pose': POSE_STAMPED,
                                      '/sensor_pose': POSE_STAMPED},
              sorted(messages, key=lambda m: m[1]))
    done = run_replay(repo_root, tmp_path / 'one_axis', '--link-topic', '/link_pose',
                      '--sensor-topic', '/sensor_pose')
    assert done.returncode == status, done.stderr
    assert 'Traceback' not in done.stderr
    if status == 3:
        assert 'cannot be determined' in done.stderr and 'Nor can the translations fix it: ' \
            'move the link to positions spread' in done.stderr, done.stderr   # (said once)
        return
    result = json.loads(done.stdout)
    (unobservable,) = result['unobservable']
    assert unobservable['what'] == 'translation'
    assert np.degrees(quat.angle_between(quat.wxyz_from_xyzw(
        [result['rotation'][k] for k in 'xyzw']), cell.mounting.quaternion)) < 1e-3


@pytest.fixture(scope='module')
def error_bags(tmp_path_factory, bags):
    """Broken and unusable recordings for the error cases."""
    root = tmp_path_factory.mktemp('errors')
    string = TYPESTORE.types['std_msgs/msg/String']
    write_bag(root / 'chatter', {'/chatter': 'std_msgs/msg/String',
                                 '/link_pose': POSE_STAMPED, '/tf': TF_TYPE},
              [('/chatter', 1, string(data='hello')),
               ('/link_pose', 2, msg(POSE_STAMPED, Pose.identity(), 2, 'base')),
               ('/tf', 3, tf_message())])
    write_bag(root / 'empty', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED}, [])
    (root / 'not_a_bag').mkdir()
    (root / 'not_a_bag' / 'notes.txt').write_text('hello')
    shutil.copytree(bags / 'pose', root / 'bad_metadata')
    (root / 'bad_metadata' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {')
    shutil.copytree(bags / 'pose', root / 'bad_db3')
    for data in (root / 'bad_db3').glob('*.db3'):
        data.write_bytes(b'this is not an sqlite database' * 100)
    shutil.copytree(bags / 'transform', root / 'cut_mcap')
    for data in (root / 'cut_mcap').glob('*.mcap'):
        data.write_bytes(data.read_bytes()[:5000])
    return root


TOPICS = ('--link-topic', '/link_pose', '--sensor-topic', '/sensor_pose')


@pytest.mark.parametrize('bag_name, args, expected', [
    ('pose', ('--link-topic', '/joint_states', '--sensor-topic', '/sensor_pose'),
     [r'no topic /joint_states \(link poses\)',
      r'/link_pose \(geometry_msgs/msg/PoseStamped, \d+ messages\)']),
    ('chatter', ('--link-topic', '/link_pose', '--sensor-topic', '/chatter'),
     ['topic /chatter \\(sensor poses\\) has type std_msgs/msg/String']),
    ('chatter', ('--link-topic', '/tf', '--sensor-topic', '/link_pose'),
     ['topic /tf \\(link poses\\) holds tf2_msgs/TFMessage: give --link-frames']),
    ('pose', ('--link-frames', 'base', 'tool0', '--sensor-topic', '/sensor_pose'),
     [r'no TF topic \(/tf, /tf_static\) in the bag']),
    ('empty', TOPICS, ['empty: the bag holds no messages']),
    ('not_a_bag', TOPICS, ['not_a_bag: not a rosbag2 directory: no metadata.yaml and no .db3 '
                           'or .mcap file in it; it holds notes.txt']),
    ('missing', TOPICS, ['missing: no such file or directory']),
    ('bad_metadata', TOPICS, ['bad_metadata: cannot open the bag']),
    ('bad_db3', TOPICS, ['bad_db3: cannot open the bag']),
    ('cut_mcap', TOPICS, ['cut_mcap: ']),
    ('pose', TOPICS + ('--still-window-s', '-1'),
     ['argument --still-window-s: must be between 0.05 and 10, not -1']),
    ('pose', ('--link-topic', '/link_pose'), ['one of the arguments --sensor-topic '
                                              '--sensor-frames --image-topic is required']),
])
def test_bad_input_exits_2_naming_the_problem(repo_root, bags, error_bags, bag_name, args,
                                              expected):
    path = (bags if bag_name == 'pose' else error_bags) / bag_name
    done = run_replay(repo_root, path, *args)
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert done.stdout == '' and 'Traceback' not in done.stderr
    for pattern in expected:
        assert re.search(pattern, done.stderr), (pattern, done.stderr)


class FakeTerminal(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self):
        return True


def test_one_file_of_a_split_bag_is_refused_naming_the_folder(repo_root, bags, tmp_path):
    # Given its first storage file, the replay once read that part alone, with exit 0.
    folder = tmp_path / 'split'
    shutil.copytree(bags / 'pose', folder)
    (first,) = folder.glob('*.db3')
    shutil.copy(first, folder / 'second_part.db3')
    done = run_replay(repo_root, first, *TOPICS)
    assert done.returncode == 2, done.stderr
    assert f'one of the 2 storage files of the bag in {folder}' in done.stderr
    assert f'give the folder, {folder}, to replay all of it' in done.stderr


def test_a_folder_without_its_index_names_its_storage_file(repo_root, bags, tmp_path):
    folder = tmp_path / 'unindexed'
    shutil.copytree(bags / 'pose', folder)
    (folder / 'metadata.yaml').unlink()
    (storage,) = folder.glob('*.db3')
    done = run_replay(repo_root, folder, *TOPICS)
    assert done.returncode == 2
    assert f'its storage file replays without it: {storage}' in done.stderr
    assert run_replay(repo_root, storage, *TOPICS, '--quiet').returncode == 0


def test_progress_bar_is_throttled_and_only_on_terminals():
    stream = FakeTerminal()
    progress = Progress(1000, 'replay', stream=stream, interval_s=3600.0)
    for done in range(0, 1000, 10):
        progress.update(done, lambda: 'samples 1, motions 0')
    progress.close(1000, 'samples 3, motions 3')
    lines = stream.getvalue().split('\r')
    assert len(lines) == 3   # '', the first update, the final state
    assert lines[-1].startswith('replay: 1000/1000 (100 %)  samples 3, motions 3  [')
    assert stream.getvalue().endswith('\n')
    quiet = io.StringIO()
    progress = Progress(10, 'replay', stream=quiet)
    progress.update(5)
    progress.close(10)
    assert quiet.getvalue() == '' and not progress.enabled
    assert not Progress(10, stream=FakeTerminal(), enabled=False).enabled
    untouched = FakeTerminal()
    Progress(10, stream=untouched).close()   # nothing drawn: no empty line either
    assert untouched.getvalue() == ''


@pytest.mark.parametrize('fill, at', [(b'\0', 0.5), (b'\xff', 0.5)])
def test_a_damaged_recording_exits_2_unless_a_partial_replay_is_asked(
        repo_root, streams, tmp_path, fill, at):
    """Zeros in an mcap chunk lose messages silently in rosbags; other bytes stop it."""
    write_bag(tmp_path / 'bag', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              topic_messages(streams, POSE_STAMPED), 'mcap')
    (storage,) = (tmp_path / 'bag').glob('*.mcap')
    data = bytearray(storage.read_bytes())
    start = int(len(data) * at)
    data[start:start + 4096] = fill * 4096
    storage.write_bytes(bytes(data))
    args = ('--link-topic', '/link_pose', '--sensor-topic', '/sensor_pose', '--quiet')
    done = run_replay(repo_root, tmp_path / 'bag', *args)
    assert done.returncode == 2 and done.stdout == '', done.stderr
    assert 'the recording is damaged' in done.stderr and 'Traceback' not in done.stderr
    assert done.stderr.rstrip().endswith('; pass --partial to use what could be read')
    partial = run_replay(repo_root, tmp_path / 'bag', *args, '--partial')
    if partial.returncode == 0:
        warnings = json.loads(partial.stdout)['warnings']
        assert any(w.startswith('partial replay: the recording is damaged, read only /link_pose')
                   for w in warnings), warnings
    else:   # too little left to solve: still named
        assert partial.returncode in (2, 3) and 'Traceback' not in partial.stderr


def replay_changed(repo_root, streams, folder, topic, change, *options):
    """Return the replay of a pose bag whose messages on `topic` went through change(msg)."""
    messages = topic_messages(streams, POSE_STAMPED)
    first = messages[0][2]
    for where, _, msg in messages:
        if where == topic:
            change(msg, first)
    write_bag(folder, {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED}, messages)
    return run_replay(repo_root, folder, '--link-topic', '/link_pose', '--sensor-topic',
                      '/sensor_pose', '--quiet', *options)


def test_a_time_offset_that_cannot_be_searched_names_the_bag(repo_root, streams, tmp_path):
    seen = []

    def restarted(msg, first):   # the link clock starts over halfway, the sensor's does not
        seen.append(1)
        if len(seen) > 3000:
            msg.header.stamp.sec -= 100
    done = replay_changed(repo_root, streams, tmp_path / 'restart', '/link_pose', restarted,
                          '--estimate-time-offset')
    assert done.returncode == 2, done.stderr
    assert (f"{tmp_path / 'restart'}: cannot estimate the time offset: the link stamps start "
            'over 1 time(s) and the sensor stamps 0 time(s)') in done.stderr, done.stderr


def test_a_stream_with_only_bad_messages_is_named_with_why(repo_root, streams, tmp_path):
    def zero_quaternion(msg, first):
        msg.pose.orientation.x = msg.pose.orientation.y = 0.0
        msg.pose.orientation.z = msg.pose.orientation.w = 0.0
    done = replay_changed(repo_root, streams, tmp_path / 'bad', '/link_pose', zero_quaternion)
    assert done.returncode == 2, done.stderr
    assert 'no link poses from /link_pose' in done.stderr
    assert ('not used: /link_pose: 6601 message(s) skipped (zero_quaternion): '
            'pose.orientation has norm 0') in done.stderr


def test_sensor_poses_in_the_link_poses_frame_are_warned_of(repo_root, streams, tmp_path):
    def in_the_base_frame(msg, first):
        msg.header.frame_id = 'base'
    done = replay_changed(repo_root, streams, tmp_path / 'base', '/sensor_pose',
                          in_the_base_frame)
    assert done.returncode == 0, done.stderr
    assert [w for w in json.loads(done.stdout)['warnings'] if 'frame' in w] == [
        "the link poses and the sensor poses are both in frame 'base' (header.frame_id): a "
        'link pose is the link in the robot base frame, a sensor pose the object in the '
        "sensor's own frame (T_sensor_obj, as a detector publishes it); sensor poses "
        'transformed into the base frame cannot show the mounting']


def test_a_topic_none_of_whose_messages_read_asks_about_its_type(repo_root, streams, tmp_path):
    """metadata.yaml naming another type: 'damaged, pass --partial' did not help."""
    write_bag(tmp_path / 'lie', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              topic_messages(streams, POSE_STAMPED))
    metadata = tmp_path / 'lie' / 'metadata.yaml'
    metadata.write_text(metadata.read_text().replace(
        'type: geometry_msgs/msg/PoseStamped', 'type: geometry_msgs/msg/TransformStamped', 1))
    done = run_replay(repo_root, tmp_path / 'lie', '--link-topic', '/link_pose',
                      '--sensor-topic', '/sensor_pose', '--quiet')
    assert done.returncode == 2 and 'Traceback' not in done.stderr, done.stderr
    assert ('(none: does metadata.yaml give the topic the type its messages have?)'
            in done.stderr)


def test_too_few_samples_names_what_was_not_used(repo_root, streams, tmp_path):
    """A sensor driver that froze its stamp: the error asked about clocks, not the stamps."""
    def frozen(msg, first):
        msg.header.stamp = first.header.stamp
    earlier = tmp_path / 'samples.csv'   # from an earlier, good replay
    earlier.write_text('kept\n')
    done = replay_changed(repo_root, streams, tmp_path / 'frozen', '/sensor_pose', frozen,
                          '--samples-out', earlier, '--journal-out', tmp_path / 'journal.csv')
    assert done.returncode == 2, done.stderr
    assert '; not used: /sensor_pose: ' in done.stderr
    assert 'message(s) skipped (duplicate_stamp)' in done.stderr
    # A failed replay writes no output: the earlier file stays, and the error says so.
    assert '(--samples-out and --journal-out not written)' in done.stderr
    assert earlier.read_text() == 'kept\n' and not (tmp_path / 'journal.csv').exists()


def test_a_clock_offset_beyond_the_pairing_window_is_named_with_its_correction(
        repo_root, streams, tmp_path):
    # Sensor stamps 3 s ahead: the stamp ranges overlap, yet nothing pairs (the error once
    # asked whether they overlap, and the option took at most 1 s).
    def ahead(msg, first):
        msg.header.stamp.sec += 3
    done = replay_changed(repo_root, streams, tmp_path / 'ahead', '/sensor_pose', ahead)
    assert done.returncode == 2
    # The bag's log times show it (the sensor messages logged 30 ms after their exposure).
    assert ("they overlap, and against the bag's log times the sensor stamps run 2.97 s ahead "
            'of the link stamps: the clocks are offset; --sensor-time-offset -2.97 corrects '
            'it') in done.stderr, done.stderr
    corrected = run_replay(repo_root, tmp_path / 'ahead', *TOPICS, '--sensor-time-offset',
                           '-3.0', '--quiet')
    assert corrected.returncode == 0 and json.loads(corrected.stdout)['samples'] == 10
    # The search for an offset looks within 0.5 s of the one given (the two options were
    # exclusive) and says so, with the residual there; without one, it says to give one.
    measured = run_replay(repo_root, tmp_path / 'ahead', *TOPICS, '--sensor-time-offset',
                          '-2.8', '--estimate-time-offset', '--quiet')
    assert measured.returncode == 0, measured.stderr
    found = json.loads(measured.stdout)['time_offset']
    assert found['searched_around_s'] == -2.8
    # Measured -2.9974 s: the cross-correlation is 2.6 ms off on these stop-and-go streams
    # whatever the centre (-2.8, -3.0, -3.2 s, or none on the stamps unshifted).
    assert abs(found['sensor_offset_s'] + 3.0) < 0.005
    # Still samples: 0.2 s off changes few of them, and the residual little (here not at all:
    # both 0.1165 deg, to rounding).
    assert found['residual_with_deg'] <= found['residual_at_given_deg'] + 1e-9
    assert found['residual_at_given_deg'] < 1.0
    said = [w for w in json.loads(measured.stdout)['warnings'] if w.startswith('time offset')]
    at_given = found['residual_at_given_deg']
    assert f'searched around the given -2.800 s, where the RMS residual is {at_given:.3f} deg' \
        in said[0]
    # Without one, the bag's log times give it: the sensor messages were logged as they came
    # (30 ms after their exposure), 3 s before their stamps; the link's 1 ms after theirs.
    alone = run_replay(repo_root, tmp_path / 'ahead', *TOPICS, '--estimate-time-offset',
                       '--quiet')
    assert alone.returncode == 0, alone.stderr
    out = json.loads(alone.stdout)
    assert out['time_offset']['searched_around_s'] == -2.97
    assert abs(out['time_offset']['sensor_offset_s'] + 3.0) < 0.005
    assert ("the sensor stamps run 2.97 s ahead of the link stamps against the bag's log "
            'times: the time offset was searched around -2.97 s') in out['warnings']
    # Stamps on one clock: no centre, as before (the ETH recording, below, searches around 0).


def test_topics_given_without_a_leading_slash_are_the_bags(repo_root, streams, tmp_path):
    # 'robot/tool0_pose' was refused although the bag's topics, listed, held /robot/tool0_pose.
    write_bag(tmp_path / 'poses', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              topic_messages(streams, POSE_STAMPED))
    done = run_replay(repo_root, tmp_path / 'poses', '--link-topic', 'link_pose',
                      '--sensor-topic', 'sensor_pose', '--quiet')
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)['samples'] == 10


def test_a_clock_offset_within_the_pairing_window_is_named_from_the_log_times(
        repo_root, streams, tmp_path):
    # Sensor stamps 1.5 s ahead: the poses pair, with the wrong partners, and the answer came
    # out wrong with a warning to widen the sensor's still bands.
    def ahead(msg, first):
        msg.header.stamp.sec += 1
        msg.header.stamp.nanosec += 500_000_000
        if msg.header.stamp.nanosec >= 1_000_000_000:
            msg.header.stamp.sec += 1
            msg.header.stamp.nanosec -= 1_000_000_000
    done = replay_changed(repo_root, streams, tmp_path / 'ahead', '/sensor_pose', ahead)
    said = ("the sensor stamps run 1.47 s ahead of the link stamps against the bag's log "
            'times: the clocks are offset, and poses may have been paired with the wrong '
            'partners; --sensor-time-offset -1.47 corrects it')
    assert any(w.startswith(said) for w in json.loads(done.stdout)['warnings']), done.stdout
    corrected = run_replay(repo_root, tmp_path / 'ahead', *TOPICS, '--sensor-time-offset',
                           '-1.47', '--quiet')
    assert not any('log times' in w for w in json.loads(corrected.stdout)['warnings'])
    given = run_replay(repo_root, tmp_path / 'ahead', *TOPICS, '--sensor-time-offset', '-0.5',
                       '--quiet')
    assert any(w.startswith('the sensor stamps run 0.97 s ahead of the link stamps (with '
                            "--sensor-time-offset -0.5) against the bag's log times")
               for w in json.loads(given.stdout)['warnings']), given.stdout


def test_a_clock_offset_is_read_from_the_log_times_whenever_each_stream_began(
        repo_root, streams, tmp_path):
    # Sensor stamps 3 s ahead, and the camera started 2 s after the robot: the first stamps
    # put the offset at 5 s (what the error suggested before it read the log times).
    messages = topic_messages(streams, POSE_STAMPED)
    first = messages[0][1]
    late = []
    for where, logged, message in messages:
        if where == '/sensor_pose':
            if logged < first + 2_000_000_000:
                continue
            message.header.stamp.sec += 3
        late.append((where, logged, message))
    write_bag(tmp_path / 'late', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              late)
    done = run_replay(repo_root, tmp_path / 'late', *TOPICS, '--quiet')
    assert done.returncode == 2
    assert ("against the bag's log times the sensor stamps run 2.97 s ahead of the link "
            'stamps: the clocks are offset; --sensor-time-offset -2.97 corrects it') \
        in done.stderr, done.stderr
    # The camera's first 2 s recorded but skipped (zero quaternions, as a detector that has
    # not seen the board yet might send): the stamps used start 2 s after the log times, and
    # the log times put the clocks 2 s off where they are not. They are not used then.
    skipped = []
    for where, logged, message in messages:
        if where == '/sensor_pose' and logged < first + 2_000_000_000:
            message.pose.orientation.w = message.pose.orientation.x = 0.0
            message.pose.orientation.y = message.pose.orientation.z = 0.0
        skipped.append((where, logged, message))
    write_bag(tmp_path / 'skipped', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              skipped)
    done = run_replay(repo_root, tmp_path / 'skipped', *TOPICS, '--sensor-time-offset', '3',
                      '--quiet')   # (a wrong offset given: nothing pairs)
    assert done.returncode == 2
    assert 'log times' not in done.stderr, done.stderr
    # Without log times (TF input) the first stamps are all there is, and the error says it
    # takes them at their word.
    report = dataclasses.replace(ReplayReport(), counters={'pairs': 0}, stamps={
        'link': [0, 60 * 10**9], 'sensor': [5 * 10**9, 65 * 10**9]})
    assert ('the sensor stamps run 5.0 s ahead of the link stamps throughout, beyond the '
            'pairing window: the clocks are offset; if that is the offset, '
            '--sensor-time-offset -5.0 corrects it') in _few_samples(Session(), report, None)
    # The offset the log times show, given already: not suggested again.
    given = Session(SessionConfig(sensor_offset_ns=-2_970_000_000))
    assert '--sensor-time-offset -5.0 corrects it' in _few_samples(given, report, -2.97e9)


def test_a_sensor_too_noisy_for_its_bands_is_named(repo_root, streams, tmp_path):
    # The robot stops as it should; the detections scatter by 1.5 deg, beyond the sensor's
    # 1 deg band: the error blamed the robot's stops alone.
    rng = np.random.default_rng(3)

    def noisy(msg, first):
        q = msg.pose.orientation
        turned = quat.multiply(quat.from_rotation_vector(np.radians(rng.normal(0, 1.5, 3))),
                               [q.w, q.x, q.y, q.z])
        q.w, q.x, q.y, q.z = (float(v) for v in turned)
    done = replay_changed(repo_root, streams, tmp_path / 'noisy', '/sensor_pose', noisy,
                          '--no-fallback')
    assert done.returncode == 2
    named = re.search(r'at \d+ paired poses the link stood still but the sensor pose moved '
                      r'beyond its bands \(1 deg, 0.005 m\): for a sensor that noisy widen '
                      r'them \((--sensor-still-rotation-deg \S+), '
                      r'(--sensor-still-translation-m \S+): what the scatter seen there '
                      r'takes\)', done.stderr)
    assert named, done.stderr
    # The bands it names take the stops.
    rng = np.random.default_rng(3)
    done = replay_changed(repo_root, streams, tmp_path / 'again', '/sensor_pose', noisy,
                          '--no-fallback', *named[1].split(), *named[2].split())
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)['samples'] >= 10


def test_a_marker_that_moves_during_the_bag_is_warned_about(tmp_path, capsys):
    # The live node's moved-marker watch, run by replay over the whole bag: the marker turns
    # by 3 deg while the robot moves to its 13th of 16 stops.
    rng = np.random.default_rng(52)
    cell = sim.random_cell(rng)
    run = sim.stop_and_go_streams(rng, cell, 16, link_rate_hz=100.0, rotation_noise_deg=0.05,
                                  translation_noise_m=0.0005)
    moved_at = (run.stills[11][1] + run.stills[12][0]) // 2
    turn = Pose(np.zeros(3), quat.from_axis_angle(np.array([0.6, 0.0, 0.8]), np.radians(3.0)))
    sensor = [(stamp, pose @ turn if stamp > moved_at else pose) for stamp, pose in run.sensor]
    moved = dataclasses.replace(run, sensor=sensor)
    for name, streams in (('still', run), ('moved', moved)):
        write_bag(tmp_path / name, {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
                  topic_messages(streams, POSE_STAMPED), 'sqlite3')
        assert replay_main([str(tmp_path / name), '--link-topic', '/link_pose',
                            '--sensor-topic', '/sensor_pose', '--quiet']) == 0
        out = json.loads(capsys.readouterr().out)
        assert out['samples'] == 16
        warned = [w for w in out['warnings'] if 'has the marker or the sensor moved' in w]
        assert len(warned) == (name == 'moved'), out['warnings']
    assert 'from sample 12 on' in warned[0]


def test_a_marker_that_flips_for_single_frames_costs_no_stop(repo_root, streams, tmp_path):
    # One sensor message in eight flipped by 30 deg: stops were lost without a word; now every
    # stop gives its sample and the summary counts the frames left out.
    rng = np.random.default_rng(52)
    flip = quat.from_axis_angle([1.0, 0.0, 0.0], np.radians(30.0))
    flips = rng.random(len(streams.sensor)) < 0.125
    sensor = [(stamp, Pose(pose.position, quat.multiply(pose.quaternion, flip)) if flipped
               else pose) for (stamp, pose), flipped in zip(streams.sensor, flips)]
    write_bag(tmp_path / 'flips', {'/link_pose': POSE_STAMPED, '/sensor_pose': POSE_STAMPED},
              topic_messages(dataclasses.replace(streams, sensor=sensor), POSE_STAMPED),
              'sqlite3')
    done = run_replay(repo_root, tmp_path / 'flips', *TOPICS)
    out = assert_recovers(done, streams.truth)
    assert out['samples'] == 10, done.stderr
    left = int(re.search(r'; (\d+) sensor poses left out of still samples: they jumped over 2x '
                         r'the sensor bands\)', done.stderr).group(1))
    assert 0 < left <= flips.sum()


def test_a_detector_that_hangs_the_camera_under_the_marker_is_not_called_swapped(
        repo_root, streams, tmp_path):
    # Some detectors publish marker -> camera (to place the camera in the tree). The frames
    # are given right and the poses compose; it was said to look swapped all the same.
    messages = [('/tf', stamp + MS, tf_message(msg(TRANSFORM_STAMPED, pose, stamp, 'base_link',
                                                   'tool0')))
                for stamp, pose in streams.link]
    messages += [('/tf', delivered, tf_message(msg(TRANSFORM_STAMPED, pose.inverse(), stamp,
                                                   'marker', 'camera')))
                 for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    write_bag(tmp_path / 'tf', {'/tf': TF_TYPE}, sorted(messages, key=lambda m: m[1]), 'mcap')
    done = run_replay(repo_root, tmp_path / 'tf', '--link-frames', 'base_link', 'tool0',
                      '--sensor-frames', 'camera', 'marker', '--tf-topics', '/tf')
    out = assert_recovers(done, streams.truth)
    assert not any('look swapped' in text for text in out['warnings']), out['warnings']


def test_a_result_from_a_frame_to_itself_is_refused_before_reading(repo_root, bags, tmp_path):
    done = run_replay(repo_root, bags / 'pose', *TOPICS, '--parent-frame', 'cam',
                      '--child-frame', '/cam')
    assert done.returncode == 2
    assert "the result would be a transform from frame 'cam' to itself" in done.stderr
    assert 'messages in' not in done.stderr   # (nothing read)
    # One option naming the frame the messages name for the other (the sensor's 'camera').
    done = run_replay(repo_root, bags / 'pose', *TOPICS, '--parent-frame', 'camera',
                      '--result-out', tmp_path / 'one_frame.yaml')
    assert done.returncode == 2, done.stdout
    assert "the result would be a transform from frame 'camera' to itself" in done.stderr
    assert not (tmp_path / 'one_frame.yaml').exists()
