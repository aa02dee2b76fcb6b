"""
Samples saved by easy_handeye2 and moveit_calibration, read by `solve`.

The files are written here from simulated cells, field by field as those tools write them
(independently of files.importers' own writers): easy_handeye2's .samples is the YAML of
easy_handeye2_msgs/SampleList (robot = tf lookup base -> effector for eye_in_hand, effector ->
base for eye_on_base; tracking = tracking_base -> marker); moveit_calibration's samples YAML
is a list of {effector_wrt_world, object_wrt_sensor}, each 16 numbers of a 4x4 matrix in
row-major order (handeye_control_widget saveSamplesBtnClicked).
"""

import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Sample
from quatcal_ros.files import importers
from quatcal_ros.files.samples_csv import COLUMNS, format_samples
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.sim import simulation
import yaml


def run_solve(repo_root, *args):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.run([sys.executable, '-m', 'quatcal_ros', 'solve', *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def matrix(pose):
    """4x4 homogeneous matrix of a Pose, built from its quaternion (w, x, y, z)."""
    w, x, y, z = pose.quaternion
    H = np.eye(4)
    H[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    H[:3, 3] = pose.position
    return H


def transform_entry(H):
    """geometry_msgs/Transform as message_to_yaml writes it, from a 4x4 matrix."""
    x, y, z, w = quat.xyzw_from_wxyz(quat.quaternion_from_matrix(H[:3, :3]))
    return {'translation': {'x': float(H[0, 3]), 'y': float(H[1, 3]), 'z': float(H[2, 3])},
            'rotation': {'x': float(x), 'y': float(y), 'z': float(z), 'w': float(w)}}


def easy_handeye2_text(samples, calibration_type, name_type=None):
    """Return a .samples file as easy_handeye2 saves it; name_type: its calibration_type."""
    entries = []
    for sample in samples:
        base_effector = matrix(sample.link)
        robot = base_effector if calibration_type == 'eye_in_hand' \
            else np.linalg.inv(base_effector)
        entries.append({'robot': transform_entry(robot),
                        'tracking': transform_entry(matrix(sample.sensor))})
    parameters = {'name': '', 'calibration_type': name_type or '', 'robot_base_frame': '',
                  'robot_effector_frame': '', 'tracking_base_frame': '',
                  'tracking_marker_frame': '', 'freehand_robot_movement': False,
                  'move_group_namespace': '/', 'move_group': 'manipulator'}
    if name_type:
        parameters.update(robot_base_frame='panda_link0', robot_effector_frame='panda_link8',
                          tracking_base_frame='camera_color_optical_frame',
                          tracking_marker_frame='aruco_marker')
    return yaml.safe_dump({'parameters': parameters, 'samples': entries}, sort_keys=False)


def moveit_text(samples):
    """Return a moveit_calibration samples YAML: 16 numbers row-major per matrix."""
    return yaml.safe_dump([{'effector_wrt_world': matrix(s.link).ravel().tolist(),
                            'object_wrt_sensor': matrix(s.sensor).ravel().tolist()}
                           for s in samples], sort_keys=False)


def cell_samples(seed, setup, n=15):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng, setup)
    samples, _ = simulation.samples(rng, cell, n, rotation_noise_deg=0.1,
                                    translation_noise_m=0.0005)
    return cell, samples


def assert_recovers(out, cell):
    """Check that the printed result is the simulated mounting (rotation, translation)."""
    r = out['rotation']
    q = quat.wxyz_from_xyzw([r['x'], r['y'], r['z'], r['w']])
    error_deg = np.degrees(quat.angle_between(q, cell.mounting.quaternion))
    assert error_deg < max(3.0 * out['uncertainty_deg'], 0.05), (error_deg, out)
    t = np.array([out['translation'][k] for k in 'xyz'])
    assert np.linalg.norm(t - cell.mounting.position) < 0.005
    assert not out['warnings']


# --- easy_handeye2 ---------------------------------------------------------------------------

@pytest.mark.parametrize('setup, calibration_type', [('eye_in_hand', 'eye_in_hand'),
                                                     ('eye_to_hand', 'eye_on_base')])
def test_solve_easy_handeye2_samples_naming_the_setup(repo_root, tmp_path, setup,
                                                      calibration_type):
    cell, samples = cell_samples(71, setup)
    path = tmp_path / 'cell.samples'
    path.write_text(easy_handeye2_text(samples, calibration_type, name_type=calibration_type))
    done = run_solve(repo_root, path)   # the setup and the frames come from the file
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out['setup'] == setup and out['samples'] == len(samples)
    assert_recovers(out, cell)
    parent = 'panda_link8' if setup == 'eye_in_hand' else 'panda_link0'
    assert out['static_transform_publisher'].endswith(
        f'--frame-id {parent} --child-frame-id camera_color_optical_frame')


@pytest.mark.parametrize('name', ['inverted.samples', 'inverted.yaml'])
def test_invert_sensor_holds_for_every_format(tmp_path, capsys, name):
    """--invert-sensor on an easy_handeye2 or moveit file was dropped: 23 deg of residual."""
    from quatcal_ros.tools.cli import solve_main
    cell, samples = cell_samples(72, 'eye_in_hand')
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    path = tmp_path / name
    path.write_text(easy_handeye2_text(inverted, 'eye_in_hand', 'eye_in_hand')
                    if name.endswith('.samples')
                    else moveit_text(inverted))
    assert solve_main([str(path), '--invert-sensor']) == 0
    out = json.loads(capsys.readouterr().out)
    assert_recovers(out, cell)


def test_solve_easy_handeye2_samples_without_parameters(repo_root, tmp_path):
    """easy_handeye2 leaves the parameters of a saved SampleList empty: --setup says it."""
    cell, samples = cell_samples(72, 'eye_to_hand')
    path = tmp_path / 'eob.samples'
    path.write_text(easy_handeye2_text(samples, 'eye_on_base'))
    done = run_solve(repo_root, path, '--setup', 'eye_to_hand')
    assert done.returncode == 0, done.stderr
    assert_recovers(json.loads(done.stdout), cell)
    with_setup = json.loads(done.stdout)
    # Without --setup: easy_handeye2's inverted robot transform makes eye_in_hand's motions
    # those of eye_to_hand, so the numbers are the same; the warning says what to pass.
    done = run_solve(repo_root, path)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out['setup'] == 'eye_in_hand'
    assert any('does not name its calibration_type' in w and '--setup eye_to_hand' in w
               for w in out['warnings'])
    for key in ('rotation', 'translation'):
        np.testing.assert_allclose(list(out[key].values()), list(with_setup[key].values()),
                                   atol=1e-6)


def test_solve_refuses_a_setup_that_contradicts_the_file(repo_root, tmp_path):
    _, samples = cell_samples(73, 'eye_to_hand', n=5)
    path = tmp_path / 'eob.samples'
    path.write_text(easy_handeye2_text(samples, 'eye_on_base', name_type='eye_on_base'))
    done = run_solve(repo_root, path, '--setup', 'eye_in_hand')
    assert done.returncode == 2
    assert 'parameters.calibration_type' in done.stderr and 'eye_on_base' in done.stderr


def test_read_easy_handeye2_samples_gives_link_and_sensor_poses(tmp_path):
    _, samples = cell_samples(74, 'eye_to_hand', n=4)
    path = tmp_path / 'x.yaml'   # any name: recognised by its content
    path.write_text(easy_handeye2_text(samples, 'eye_on_base', name_type='eye_on_base'))
    read = importers.read_easy_handeye2_samples(path)
    assert len(read) == 4
    for got, want in zip(read, samples):
        np.testing.assert_allclose(matrix(got.link), matrix(want.link), atol=1e-12)
        np.testing.assert_allclose(matrix(got.sensor), matrix(want.sensor), atol=1e-12)
    loaded = importers.load_samples(path)
    assert loaded.file_format == 'easy_handeye2' and loaded.setup == 'eye_to_hand'
    assert loaded.frames['tracking_marker_frame'] == 'aruco_marker'
    assert [s.stamp_ns for s in read] == [0, 10 ** 9, 2 * 10 ** 9, 3 * 10 ** 9]


def test_our_writers_match_the_documented_layouts(tmp_path):
    """Check that importers' own writers give what the tools write (to hand samples over)."""
    _, samples = cell_samples(75, 'eye_to_hand', n=3)
    ours = yaml.safe_load(importers.format_easy_handeye2_samples(samples, 'eye_to_hand'))
    theirs = yaml.safe_load(easy_handeye2_text(samples, 'eye_on_base'))
    for a, b in zip(ours['samples'], theirs['samples'], strict=True):
        for key in ('robot', 'tracking'):
            for part in ('translation', 'rotation'):
                got, want = a[key][part], b[key][part]
                assert list(got) == list(want)
                sign = 1.0 if part == 'translation' or got['w'] * want['w'] >= 0 else -1.0
                np.testing.assert_allclose([got[k] for k in got],
                                           [sign * want[k] for k in want], atol=1e-12)
    assert list(ours['parameters']) == list(theirs['parameters'])
    moveit = yaml.safe_load(importers.format_moveit_samples(samples))
    np.testing.assert_allclose(moveit[0]['effector_wrt_world'],
                               matrix(samples[0].link).ravel(), atol=1e-12)


# --- moveit_calibration ----------------------------------------------------------------------

@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
def test_solve_moveit_samples_yaml(repo_root, tmp_path, setup):
    cell, samples = cell_samples(76, setup)
    path = tmp_path / 'moveit_samples.yaml'
    path.write_text(moveit_text(samples))
    done = run_solve(repo_root, path, '--setup', setup)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out['samples'] == len(samples)
    assert_recovers(out, cell)


def test_moveit_json_reproduces_the_published_eye_to_hand_result(repo_root, datasets_dir):
    """
    moveit_calibration's own test data (pose_samples.json), as its solver test reads it.

    Reference (SOURCE.md): camera in the base frame at (0.659, -0.249, 0.830) m, rotation
    Rx(0.230) Ry(-2.540) Rz(1.950), a solver's output printed to 3 decimals.
    """
    path = datasets_dir / 'moveit_pose_samples' / 'pose_samples.json'
    reference = quat.multiply(quat.multiply(quat.from_axis_angle([1, 0, 0], 0.230),
                                            quat.from_axis_angle([0, 1, 0], -2.540)),
                              quat.from_axis_angle([0, 0, 1], 1.950))
    for extra in ([], ['--format', 'moveit-json']):
        done = run_solve(repo_root, path, '--setup', 'eye_to_hand', *extra)
        assert done.returncode == 0, done.stderr
        out = json.loads(done.stdout)
        r = out['rotation']
        q = quat.wxyz_from_xyzw([r['x'], r['y'], r['z'], r['w']])
        assert np.degrees(quat.angle_between(q, reference)) < 0.5
        t = [out['translation'][k] for k in 'xyz']
        assert np.linalg.norm(np.subtract(t, [0.659, -0.249, 0.830])) < 0.005
        assert out['samples'] == 50 and not out['warnings']
        assert '--frame-id base_link --child-frame-id camera' in out['static_transform_publisher']


# --- format detection ------------------------------------------------------------------------

def test_formats_are_detected_by_name_and_content(tmp_path):
    _, samples = cell_samples(77, 'eye_in_hand', n=3)
    cases = {
        'a.samples': (easy_handeye2_text(samples, 'eye_in_hand'), 'easy_handeye2'),
        'b.yml': (moveit_text(samples), 'moveit'),
        'c.yaml': (easy_handeye2_text(samples, 'eye_in_hand'), 'easy_handeye2'),
        'd.json': (json.dumps([[matrix(s.link).tolist(), matrix(s.sensor).tolist()]
                               for s in samples]), 'moveit-json'),
        'e.txt': (format_samples(samples), 'csv'),
        'f.csv': (format_samples(samples), 'csv'),
    }
    for name, (text, expected) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        loaded = importers.load_samples(path)
        assert loaded.file_format == expected, name
        assert len(loaded.samples) == 3
        for got, want in zip(loaded.samples, samples):
            np.testing.assert_allclose(matrix(got.link), matrix(want.link), atol=1e-9)
            np.testing.assert_allclose(matrix(got.sensor), matrix(want.sensor), atol=1e-9)
    # --format overrides the name: a moveit YAML called .samples.
    path = tmp_path / 'moveit.samples'
    path.write_text(moveit_text(samples))
    assert len(importers.load_samples(path, 'moveit').samples) == 3
    with pytest.raises(BadInputError, match='expected a mapping with samples'):
        importers.load_samples(path)


# --- bad input -------------------------------------------------------------------------------

def bad_easy_handeye2(samples, change):
    document = yaml.safe_load(easy_handeye2_text(samples, 'eye_in_hand'))
    change(document)
    return yaml.safe_dump(document, sort_keys=False)


def bad_moveit(samples, change):
    document = yaml.safe_load(moveit_text(samples))
    change(document)
    return yaml.safe_dump(document, sort_keys=False)


def set_path(document, path, value):
    for key in path[:-1]:
        document = document[key]
    document[path[-1]] = value


def delete_path(document, path):
    for key in path[:-1]:
        document = document[key]
    del document[path[-1]]


BAD_INPUTS = [
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['samples', 2, 'robot', 'rotation', 'w'], 'abc'),
     "bad.samples, entry samples[2], field robot.rotation.w: 'abc' is not a number"),
    ('bad.samples', 'easy_handeye2',   # a string as a CSV cell: float() read it as 5
     lambda d: set_path(d, ['samples', 2, 'robot', 'rotation', 'w'], '0_5'),
     "bad.samples, entry samples[2], field robot.rotation.w: '0_5' is not a number"),
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['samples', 1, 'tracking', 'translation', 'y'], float('nan')),
     'bad.samples, entry samples[1], field tracking.translation.y: nan is not a finite'),
    ('bad.samples', 'easy_handeye2',
     lambda d: delete_path(d, ['samples', 0, 'tracking']),
     'bad.samples, entry samples[0]: missing tracking'),
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['samples', 0, 'robot', 'rotation'],
                        {'x': 0.0, 'y': 0.0, 'z': 0.0, 'w': 2.0}),
     'bad.samples, entry samples[0], field robot.rotation: the quaternion has norm 2'),
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['parameters', 'calibration_type'], 'eye_on_hand'),
     "field parameters.calibration_type: 'eye_on_hand' is not eye_in_hand or eye_on_base"),
    ('bad.yaml', 'moveit',
     lambda d: set_path(d, [1, 'object_wrt_sensor'], [1.0] * 12),
     'bad.yaml, entry [1], field object_wrt_sensor: expected 16 numbers'),
    ('bad.yaml', 'moveit',
     lambda d: set_path(d, [0, 'effector_wrt_world', 15], 2.0),
     'bad.yaml, entry [0], field effector_wrt_world: the last row is'),
    ('bad.yaml', 'moveit',
     lambda d: set_path(d, [2, 'effector_wrt_world', 0], 3.0),
     'bad.yaml, entry [2], field effector_wrt_world: the upper-left 3x3 block is not a '
     'rotation'),
    ('bad.yaml', 'moveit',   # a flipped axis (it was asked whether it was transposed)
     lambda d: [set_path(d, [2, 'effector_wrt_world', k], -d[2]['effector_wrt_world'][k])
                for k in (0, 4, 8)],
     'bad.yaml, entry [2], field effector_wrt_world: the upper-left 3x3 block is a reflection '
     '(determinant -1), not a rotation: one axis of a frame is flipped'),
    ('bad.yaml', 'moveit',
     lambda d: set_path(d, [2, 'effector_wrt_world', 5], None),
     'bad.yaml, entry [2], field effector_wrt_world[1][1]: None is not a number'),
    # A position a solver cannot take (1e300 crashed it, 1e100 solved to nonsense, exit 0).
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['samples', 2, 'robot', 'translation', 'x'], 1e300),
     'bad.samples, entry samples[2], field robot.translation: [1e+300, '),
    ('bad.yaml', 'moveit',
     lambda d: set_path(d, [1, 'object_wrt_sensor', 3], -2000.0),
     'bad.yaml, entry [1], field object_wrt_sensor, last column: [-2000.0, '),
    # Once written into the static_transform_publisher command as "{'nested': ...}".
    ('bad.samples', 'easy_handeye2',
     lambda d: set_path(d, ['parameters', 'robot_effector_frame'], {'nested': ['junk', 1]}),
     'bad.samples, field parameters.robot_effector_frame: expected a frame name, got dict '
     "{'nested': ['junk', 1]}"),
]


@pytest.mark.parametrize('name, kind, change, message', BAD_INPUTS)
def test_bad_entries_are_named(tmp_path, name, kind, change, message):
    _, samples = cell_samples(78, 'eye_in_hand', n=4)
    path = tmp_path / name
    make = bad_easy_handeye2 if kind == 'easy_handeye2' else bad_moveit
    path.write_text(make(samples, change))
    with pytest.raises(BadInputError) as caught:
        importers.load_samples(path)
    assert message in str(caught.value)
    assert str(path) in str(caught.value)


def test_yaml_is_read_as_plain_data_only(tmp_path):
    path = tmp_path / 'evil.samples'
    path.write_text('!!python/object/apply:os.system ["echo pwned"]\n')
    with pytest.raises(BadInputError, match='refused: not plain data'):
        importers.load_samples(path)
    path.write_text('samples: [\n')
    with pytest.raises(BadInputError, match='line 2: not readable YAML'):
        importers.load_samples(path)
    path = tmp_path / 'other.yaml'
    path.write_text('joint_names: [a, b]\njoint_values: [[0, 1]]\n')
    with pytest.raises(BadInputError, match='not a samples file this tool knows'):
        importers.load_samples(path)
    # A file of no format the name tells, that is not YAML either (a README): what solve
    # reads, not only the YAML parser's complaint.
    path = tmp_path / 'SOURCE.md'
    path.write_text('# Source\n\nThe poses of [x](y).\n- one\nnot: a: mapping\n')
    with pytest.raises(BadInputError) as raised:
        importers.load_samples(path)
    assert str(raised.value).startswith(f'{path}: not a samples file this tool knows: expected')
    assert str(raised.value).endswith('pass --format to say which (read as YAML: line 5: not '
                                      'readable YAML: mapping values are not allowed here)')


def test_solve_exits_2_naming_the_entry(repo_root, tmp_path):
    _, samples = cell_samples(79, 'eye_in_hand', n=4)
    path = tmp_path / 'bad.samples'
    path.write_text(bad_easy_handeye2(
        samples, lambda d: set_path(d, ['samples', 3, 'robot', 'translation', 'x'], 'oops')))
    done = run_solve(repo_root, path)
    assert done.returncode == 2 and done.stdout == ''
    assert "entry samples[3], field robot.translation.x: 'oops' is not a number" in done.stderr
    done = run_solve(repo_root, tmp_path / 'missing.yaml')
    assert done.returncode == 2 and 'missing.yaml: cannot read' in done.stderr


def test_a_file_of_another_format_is_said_in_a_users_words(tmp_path):
    # A CSV read with --format moveit was 'expected a list of samples ..., got str'.
    path = tmp_path / 'samples.csv'
    path.write_text(','.join(COLUMNS) + '\n' + '1.0,0,0,0,0,0,0,1,0,0,1,0,0,0,1\n')
    with pytest.raises(BadInputError) as caught:
        importers.load_samples(path, 'moveit')
    assert str(caught.value) == (
        f'{path}: expected a list of samples with effector_wrt_world and object_wrt_sensor, '
        'got plain text, not YAML or JSON structure (a samples CSV? --format csv reads one)')
    path.write_text('samples: 3\nother: 1\n')
    with pytest.raises(BadInputError, match=r'got a mapping with samples, other$'):
        importers.load_samples(path, 'moveit')


BILLION_LAUGHS = ('a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n' + ''.join(
    f'{b}: &{b} [*{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}]\n'
    for a, b in zip('abcdefgh', 'bcdefghi')))


@pytest.mark.parametrize('suffix, text, words', [
    ('.samples', BILLION_LAUGHS, 'line 2: not readable YAML: an alias (*a)'),
    ('.samples', '[' * 5000 + ']' * 5000, 'nested deeper than 64 levels'),
    ('.samples', 'samples: ' + '9' * 5000, 'an integer of 5000 digits'),
    ('.json', '[' * 100000 + ']' * 100000, 'not readable JSON: nested too deeply'),
    ('.json', '[' + '9' * 5000 + ']', 'an integer of 5000 digits'),
    ('.samples', '\x08', 'not readable YAML: unacceptable character #x0008'),
])
def test_hostile_files_are_refused_in_bounded_time_naming_the_file(
        tmp_path, suffix, text, words):
    path = tmp_path / ('hostile' + suffix)
    path.write_text(text)
    with pytest.raises(BadInputError, match=r'hostile') as caught:
        importers.load_samples(path)
    assert words in str(caught.value)


def test_hostile_file_exits_2_without_a_traceback(repo_root, tmp_path):
    path = tmp_path / 'laughs.samples'
    path.write_text(BILLION_LAUGHS)
    done = run_solve(repo_root, path)
    assert done.returncode == 2 and 'Traceback' not in done.stderr
    assert 'laughs.samples, line 2: not readable YAML: an alias' in done.stderr


def test_spreadsheet_csv_details(tmp_path):
    rng = np.random.default_rng(2)
    samples, _ = simulation.samples(rng, simulation.random_cell(rng), 4)
    text = format_samples(samples)
    path = tmp_path / 'bom.csv'
    path.write_text('\ufeff' + text, encoding='utf-8')   # what spreadsheets write
    assert len(importers.load_samples(path).samples) == 4
    header, first, *rest = text.splitlines()
    cells = first.split(',')
    for bad, words in (('0_455', "field link_x: '0_455' is not a number"),
                       ('\u0663', "field link_x: '\u0663' is not a number"),   # float(): 3
                       ('1e308', 'field link_x: 1e+308 m is not a position in a robot cell')):
        path.write_text('\n'.join([header, ','.join([cells[0], bad] + cells[2:]), *rest]))
        with pytest.raises(BadInputError, match='row 2') as caught:
            importers.load_samples(path)
        assert words in str(caught.value)


@pytest.mark.parametrize('read', ['samples_csv', 'yaml', 'robot_poses', 'import', 'result'])
@pytest.mark.parametrize('problem', ['missing', 'directory', 'late_binary'])
def test_every_reader_names_the_file_it_cannot_read(tmp_path, read, problem):
    """One way to open a user's file: the same error, also for bad bytes deep in the file."""
    from quatcal_ros.files import plain_yaml
    from quatcal_ros.files.importers import load_samples
    from quatcal_ros.files.persistence import read_result_yaml
    from quatcal_ros.files.samples_csv import read_samples
    from quatcal_ros.vision.dataset import read_robot_poses
    readers = {'samples_csv': read_samples, 'yaml': plain_yaml.load_file,
               'robot_poses': read_robot_poses, 'import': lambda path: load_samples(path, 'auto'),
               'result': read_result_yaml}
    path = tmp_path / 'input.csv'
    if problem == 'directory':
        path.mkdir()
    elif problem == 'late_binary':   # past the first read's buffer (robot poses: the header)
        text = (b'image,link_x,link_y,link_z,link_qx,link_qy,link_qz,link_qw\n'
                if read == 'robot_poses' else b'# a comment\n' * 20000)
        path.write_bytes(text + b'\xff\xfe\x00')
    expected = 'not a text file' if problem == 'late_binary' else 'cannot read'
    with pytest.raises(BadInputError, match=f'input.csv: {expected}'):
        readers[read](path)


def test_a_whole_file_reader_stops_at_its_bound(tmp_path):
    """A read stops past its bound (`solve /dev/zero` once read until the memory ran out)."""
    from quatcal_ros.files.text_input import read_text
    path = tmp_path / 'big.txt'
    path.write_text('x' * (3 * 1024 * 1024))
    assert len(read_text(path, limit=4 * 1024 * 1024)) == 3 * 1024 * 1024
    with pytest.raises(BadInputError, match='big.txt: larger than 2 MiB'):
        read_text(path, limit=2 * 1024 * 1024)


@pytest.mark.parametrize('read', ['samples_csv', 'import', 'robot_poses'])
def test_every_whole_file_reader_has_the_bound(tmp_path, monkeypatch, read):
    """The CSV readers too (`solve /dev/zero.csv` read rows until the memory ran out)."""
    from quatcal_ros.files import text_input
    from quatcal_ros.files.samples_csv import read_samples
    from quatcal_ros.vision.dataset import read_robot_poses
    readers = {'samples_csv': read_samples, 'import': importers.load_samples,
               'robot_poses': read_robot_poses}
    monkeypatch.setattr(text_input, 'MAX_TEXT_CHARACTERS', 1024 * 1024)
    path = tmp_path / 'big.csv'
    path.write_text('stamp,' + 'x' * (2 * 1024 * 1024) + '\n')
    with pytest.raises(BadInputError, match='big.csv: larger than 1 MiB'):
        readers[read](path)


def test_a_file_is_read_once_so_a_pipe_and_a_bom_journal_keep_everything(tmp_path):
    """
    A journal with a byte-order mark keeps its setup and frames; a pipe reads like a file.

    The reader once opened a CSV twice: the second read of a pipe found it empty, and a
    journal saved by an editor with a byte-order mark lost its header (solved eye-in-hand).
    """
    import os
    import threading
    from quatcal_ros.files.journal import JournalHeader
    rng = np.random.default_rng(4)
    samples, _ = simulation.samples(rng, simulation.random_cell(rng), 5)
    text = JournalHeader('eye_to_hand', 'base_link', 'cam').line() + '\n' + format_samples(samples)
    path = tmp_path / 'journal.csv'
    path.write_text('\ufeff' + text, encoding='utf-8')
    read = importers.load_samples(path)
    assert (read.setup, read.frames) == ('eye_to_hand', {'robot_base_frame': 'base_link',
                                                         'tracking_base_frame': 'cam'})
    assert len(read.samples) == 5
    fifo = tmp_path / 'pipe'
    os.mkfifo(fifo)
    writer = threading.Thread(target=fifo.write_text, args=(text,))
    writer.start()
    try:
        read = importers.load_samples(fifo)
    finally:
        writer.join()
    assert (read.setup, len(read.samples)) == ('eye_to_hand', 5)


def test_json_and_yaml_with_a_byte_order_mark_are_read(tmp_path):
    rng = np.random.default_rng(5)
    samples, _ = simulation.samples(rng, simulation.random_cell(rng), 4)
    pairs = [[s.link.as_matrix().tolist(), s.sensor.as_matrix().tolist()] for s in samples]
    for name, text in (('s.samples', importers.format_easy_handeye2_samples(samples)),
                       ('s.yaml', importers.format_moveit_samples(samples)),
                       ('s.json', json.dumps(pairs))):
        path = tmp_path / name
        path.write_text('\ufeff' + text, encoding='utf-8')
        assert len(importers.load_samples(path).samples) == 4


def test_an_earlier_eye_to_hand_journal_names_no_flange_as_the_base(tmp_path):
    """
    Earlier eye-to-hand journals wrote the flange's default name (tool0) for the base.

    `solve` passed it on as robot_base_frame: base -> camera hung off the moving flange.
    """
    from quatcal_ros.files.journal import JournalHeader
    _, samples = cell_samples(1, 'eye_to_hand', n=6)
    path = tmp_path / 'legacy.csv'
    path.write_text(JournalHeader('eye_to_hand', 'tool0', 'camera').line() + '\n'
                    + format_samples(samples))
    loaded = importers.load_samples(path)
    assert loaded.setup == 'eye_to_hand'
    assert loaded.frames == {'tracking_base_frame': 'camera'}
    assert 'link_frame tool0 is the default flange name, not the robot base' in \
        loaded.warnings[0]
    named = tmp_path / 'named.csv'
    named.write_text(JournalHeader('eye_to_hand', 'world', 'camera').line() + '\n'
                     + format_samples(samples))
    assert importers.load_samples(named).frames['robot_base_frame'] == 'world'


def test_a_huge_matrix_entry_is_refused_without_a_numpy_warning():
    # |R^T R - I| overflowed: numpy's RuntimeWarning on stderr before the clear refusal.
    huge = np.eye(4)
    huge[0, 1] = 1e200
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        with pytest.raises(BadInputError, match=r'not a rotation matrix \(\|R\^T R - I\| = inf'):
            importers.parse_moveit_json_samples(
                [[huge.ravel().tolist(), np.eye(4).ravel().tolist()]] * 3, 'x.json')
