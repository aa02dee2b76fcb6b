"""`python -m quatcal_ros solve SAMPLES.csv`: DESIGN.md contracts 2 and 3, run as users run it."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, sensor_covariance_factors
from quatcal_ros.core.pose import inverse_perturbation, Pose, residual_order, Sample
from quatcal_ros.files.samples_csv import COLUMNS, COVARIANCE_COLUMNS, format_samples, \
    parse_samples, parse_samples_and_rows
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.sim import simulation


def run_solve(repo_root, *args):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.run([sys.executable, '-m', 'quatcal_ros', 'solve', *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def write_cell_csv(path, seed, n, **noise):
    """Write n samples of a random cell to `path`; return (cell, path, outliers)."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples, outliers = simulation.samples(rng, cell, n, **noise)
    path.write_text(format_samples(samples))
    return cell, path, outliers


@pytest.fixture
def cell_csv(tmp_path):
    return write_cell_csv(tmp_path / 'samples.csv', 21, 20, rotation_noise_deg=0.3,
                          outlier_fraction=0.1)


def test_solve_prints_the_contract_json(repo_root, cell_csv):
    cell, path, outliers = cell_csv
    done = run_solve(repo_root, path)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    r = out['rotation']
    q = quat.wxyz_from_xyzw([r['x'], r['y'], r['z'], r['w']])
    error = np.degrees(quat.angle_between(q, cell.mounting.quaternion))
    assert error < 3 * out['uncertainty_deg']
    assert out['samples'] == 20 and out['motions'] == 190
    assert sorted(e['sample'] for e in out['rejected'] if 'sample' in e) == outliers
    # contract 3: every entry {"motion": [i, j], "reason"} (extended with the sample)
    assert outliers and all(len(e['motion']) == 2 and e['reason'] for e in out['rejected'])
    np.testing.assert_allclose(out['matrix'], quat.matrix_from_quaternion(q), atol=1e-12)


def test_solve_options(repo_root, cell_csv):
    _, path, _ = cell_csv
    for args in (['--pairs', 'consecutive'], ['--no-robust'], ['--min-motion-deg', '2']):
        done = run_solve(repo_root, path, *args)
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)['samples'] == 20


def test_solve_eye_to_hand(repo_root, tmp_path):
    rng = np.random.default_rng(22)
    cell = simulation.random_cell(rng, 'eye_to_hand')
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.2)
    path = tmp_path / 'eth.csv'
    path.write_text(format_samples(samples))
    done = run_solve(repo_root, path, '--setup', 'eye_to_hand')
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    q = quat.wxyz_from_xyzw([out['rotation'][k] for k in 'xyzw'])
    assert np.degrees(quat.angle_between(q, cell.mounting.quaternion)) < 1.0
    assert out['setup'] == 'eye_to_hand' and not out['warnings']


GOOD_ROW = '1.0,0,0,0,0,0,0,1,0,0,1,0,0,0,1'


@pytest.mark.parametrize('text, expected', [
    ('', 'empty file'),
    ('stamp,link_x\n1,2\n', 'row 1 (header): missing column(s) link_y'),
    (';'.join(COLUMNS) + '\n' + GOOD_ROW.replace(',', ';') + '\n',
     'row 1 (header): missing column(s) stamp, link_x, link_y, link_z, link_qx, link_qy, '
     'link_qz, link_qw, sensor_x, sensor_y, sensor_z, sensor_qx, sensor_qy, sensor_qz, '
     "sensor_qw (the header is one column separated by ';': columns must be separated by "
     'commas); expected stamp,'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW.replace('1.0,', 'abc,', 1) + '\n',
     "row 2, field stamp: 'abc' is not a number"),
    (','.join(COLUMNS) + '\n' + GOOD_ROW + '\n' + GOOD_ROW[:-1] + 'nan\n',
     'row 3, field sensor_qw: nan is not a finite number'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW.replace(',1,0,0,1,', ',0,0,0,1,', 1) + '\n',
     'row 2, fields link_qx..link_qw: the quaternion has norm 0'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW[:-1] + '2\n',
     'row 2, fields sensor_qx..sensor_qw: the quaternion has norm 2'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW + '\n' + '1.0,0,0\n', 'row 3, field link_z: missing'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW + '\n' + GOOD_ROW.replace('1.0,0,', '2.0,0.1,', 1)
     + '\n', '2 sample(s); at least 3'),
    (','.join(COLUMNS) + '\n' + (GOOD_ROW + '\n') * 3,
     '1 sample(s) (2 more repeat earlier ones exactly); at least 3'),
    ('# a comment\n' + ','.join(COLUMNS) + ',link_x\n' + GOOD_ROW + ',1\n',
     'row 2 (header): column(s) link_x more than once'),
    # a value too many, at the end (dropped silently before) or inside (the next fields
    # shifted: blamed on a quaternion)
    (','.join(COLUMNS) + '\n' + GOOD_ROW + ',7\n',
     'row 2: 16 fields, the header has 15: a value too many, or a decimal comma?'),
    (','.join(COLUMNS) + '\n' + GOOD_ROW.replace(',', ',0,5,', 1) + '\n',
     'row 2: 17 fields, the header has 15'),
    # no header row: said so, and a pose stream (as the ETH recording's) named
    (GOOD_ROW + '\n', 'row 1 (header): missing column(s) stamp, link_x, link_y, link_z, '
     'link_qx, link_qy, link_qz, link_qw, sensor_x, sensor_y, sensor_z, sensor_qx, sensor_qy, '
     'sensor_qz, sensor_qw (the first row is 15 numbers, not column names); expected'),
    ('1.0,0.5,0,0.3,0,0,0,1\n' * 3, '(the first row is 8 numbers, not column names, and 8 a '
     'row are one pose stream (a stamp, a position, a quaternion), not samples of a link and '
     'a sensor pose: give two pose streams to replay as topics of a bag)'),
])
def test_bad_input_exits_2_naming_row_and_field(repo_root, tmp_path, text, expected):
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    done = run_solve(repo_root, path)
    assert done.returncode == 2
    assert expected in done.stderr and str(path) in done.stderr
    assert 'Traceback' not in done.stderr and done.stdout == ''


def test_option_help_names_other_options_as_options():
    # It named them as the node's parameters (validation_max_translation_mm).
    import argparse
    from quatcal_ros.tools.options import add_setting_options
    parser = argparse.ArgumentParser()
    add_setting_options(parser, 'solve')
    helps = {action.dest: action.help for action in parser._actions}
    assert helps['validation_max_rotation_deg'].endswith(
        'is at most this angle and --validation-max-translation-mm; 0 to 180 deg; default 1.0')
    assert 'validation_max' not in ' '.join(map(str, helps.values()))


def test_empty_fields_after_a_row_are_a_trailing_comma():
    from quatcal_ros.files.samples_csv import parse_samples
    rows = [GOOD_ROW, GOOD_ROW.replace('1.0,', '2.0,', 1) + ',', GOOD_ROW + ', ,']
    samples = parse_samples(','.join(COLUMNS) + '\n' + '\n'.join(rows) + '\n', 'a.csv')
    assert [sample.stamp_ns for sample in samples] == [10 ** 9, 2 * 10 ** 9, 10 ** 9]


def covariance_samples(n=12, seed=31):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    covariances = simulation.pnp_like_covariance()[None] * np.linspace(1.0, 9.0, n)[:, None, None]
    return simulation.samples(rng, cell, n, sensor_covariance=covariances,
                              report_covariance=True)[0]


def test_sensor_covariance_columns_round_trip_and_weight_the_solve(repo_root, tmp_path):
    samples = covariance_samples()
    samples[3] = Sample(samples[3].stamp_ns, samples[3].link,
                        Pose(samples[3].sensor.position, samples[3].sensor.quaternion))
    text = format_samples(samples)
    assert text.split('\n', 1)[0] == ','.join(COLUMNS + COVARIANCE_COLUMNS)
    assert text.split('\n')[4].count(',') == len(COLUMNS) - 1   # sample 3: none
    read = parse_samples(text)
    for before, after in zip(samples, read, strict=True):
        if before.sensor.covariance is None:
            assert after.sensor.covariance is None
        else:
            np.testing.assert_array_equal(after.sensor.covariance, before.sensor.covariance)
    # Every sample with its covariance: solve uses them, as calibrate does.
    samples = covariance_samples()
    path = tmp_path / 'with_covariance.csv'
    path.write_text(format_samples(samples))
    done = run_solve(repo_root, path)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result['noise_model']['sample_covariances'] == 'input'
    expected = calibrate(samples)
    assert quat.angle_between([result['rotation'][k] for k in 'wxyz'], expected.quaternion) \
        < 1e-12
    # Some rows without: none is used, and the warning says so (they were dropped silently).
    path.write_text(text)
    result = json.loads(run_solve(repo_root, path).stdout)
    assert result['noise_model']['sample_covariances'] == 'none'
    assert any(warning.startswith(f'{len(samples) - 1} of {len(samples)} samples give their '
                                  'own sensor covariance: one is used only when every sample')
               for warning in result['warnings'])


@pytest.mark.parametrize('change, expected', [
    (lambda cells: cells[:-1], "field sensor_cov_rz_rz: '' is not a number (give all 21"),
    (lambda cells: cells[:-1] + ['nan'], 'field sensor_cov_rz_rz: nan is not a finite number'),
    (lambda cells: ['-1'] + cells[1:], 'the covariance is not positive definite'),
    (lambda cells: ['5e-324'] + cells[1:], 'the covariance is nearly singular'),
    (lambda cells: cells[:2] + ['1e308'] + cells[3:], 'the covariance is not positive definite'),
])
def test_bad_sensor_covariances_are_named(change, expected):
    text = format_samples(covariance_samples(3))
    header, first, *rest = text.splitlines()
    cells = first.split(',')
    first = ','.join(cells[:len(COLUMNS)] + change(cells[len(COLUMNS):]))
    with pytest.raises(BadInputError, match='cov.csv, row 2') as raised:
        parse_samples('\n'.join([header, first, *rest]) + '\n', 'cov.csv')
    assert expected in str(raised.value)
    with pytest.raises(BadInputError, match='covariance column.s. sensor_cov_x_x missing'):
        parse_samples(header.replace(',sensor_cov_x_x', '') + '\n', 'cov.csv')


def test_comment_lines_are_skipped_after_the_header_too():
    # Only those before the header were: '# left out' was 'not a number' in field stamp.
    text = format_samples(covariance_samples(4))
    header, *rows = text.splitlines()
    commented = [header, rows[0], '# ' + rows[1], '  # a note', *rows[2:]]
    kept = parse_samples('\n'.join(commented) + '\n')
    assert format_samples(kept) == '\n'.join([header, rows[0], *rows[2:]]) + '\n'
    # A quote in a comment opened a CSV field that swallowed the rows up to the next quote.
    quoted = [header, rows[0], '#left out,"robot slipped', rows[1], rows[2], '# "end', rows[3]]
    samples, lines = parse_samples_and_rows('\n'.join(quoted) + '\n')
    assert format_samples(samples) == '\n'.join([header, *rows[:4]]) + '\n'
    assert lines == [2, 4, 5, 7]


def test_a_misspelt_column_is_named_with_the_one_meant():
    # The missing one was named, not the typo beside it; a misspelt optional column was lost
    # (a covariance column: all 21 or none, blamed on the one it stood for).
    text = format_samples(covariance_samples(3))
    header, *rows = text.splitlines()
    for wrong, right, expected in (
            ('link_qw', 'link_w', 'missing column(s) link_qw; unknown column(s) link_w (did you '
                                  'mean link_qw?); expected stamp,'),
            ('sensor_cov_x_y', 'sensor_cov_y_x', 'row 1 (header): unknown column(s) '
                                                 'sensor_cov_y_x (did you mean sensor_cov_x_y?)'),
            ('stamp', 'Stamp', 'missing column(s) stamp; unknown column(s) Stamp (did you mean '
                               'stamp?)')):
        misspelt = header.replace(f',{wrong},', f',{right},').replace(f'{wrong},', f'{right},', 1)
        with pytest.raises(BadInputError) as raised:
            parse_samples('\n'.join([misspelt, *rows]) + '\n', 'cov.csv')
        assert expected in str(raised.value), raised.value
    # Another column is ignored: a note, or velocities beside the poses.
    extra = [f'{row},seen twice,0.1' for row in rows]
    assert len(parse_samples('\n'.join([header + ',note,link_vx', *extra]) + '\n')) == 3


def test_missing_file_and_bad_arguments_exit_2(repo_root, tmp_path):
    done = run_solve(repo_root, tmp_path / 'nope.csv')
    assert done.returncode == 2 and 'cannot read' in done.stderr
    done = run_solve(repo_root, tmp_path / 'nope.csv', '--setup', 'sideways')
    assert done.returncode == 2 and 'invalid choice' in done.stderr


def test_undetermined_rotation_exits_3_with_the_reason(repo_root, tmp_path):
    rng = np.random.default_rng(23)
    cell = simulation.random_cell(rng)
    samples = []
    for k, angle in enumerate([0, 25, 50, 75]):
        link = cell.home @ Pose.create([0, 0, 0.01 * k],
                                       quat.from_axis_angle([0, 0, 1], np.radians(angle)))
        samples.append(Sample(k * 10 ** 9, link, cell.sensor_pose(link)))
    path = tmp_path / 'one_axis.csv'
    path.write_text(format_samples(samples))
    done = run_solve(repo_root, path)
    assert done.returncode == 3
    assert 'Case 1' in done.stderr and 'perpendicular' in done.stderr


def test_solve_on_a_journal_takes_its_setup_and_frames(repo_root, tmp_path):
    from quatcal_ros.files.journal import Journal, JournalHeader
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 8, rotation_noise_deg=0.05)
    path = tmp_path / 'samples.csv'
    header = JournalHeader('eye_in_hand', 'tool0', 'camera_color_optical_frame')
    written = Journal.create(path, header)
    for sample in samples:
        written.append(sample)
    written.close()
    done = run_solve(repo_root, path)
    assert done.returncode == 0, done.stderr
    line = json.loads(done.stdout)['static_transform_publisher']
    assert line.endswith('--frame-id tool0 --child-frame-id camera_color_optical_frame')
    # Solved as the other setup (what a convention warning asks for), it says so and does
    # not label the answer with the recording's frames (it once did, silently)
    done = run_solve(repo_root, path, '--setup', 'eye_to_hand')
    result = json.loads(done.stdout)
    assert any('recorded with setup eye_in_hand; it is solved as eye_to_hand' in w
               for w in result['warnings'])
    assert '--frame-id tool0 ' not in result['static_transform_publisher']


def test_solve_on_a_journal_takes_its_invert_sensor(tmp_path, capsys):
    """A node run with invert_sensor:=true: solve of its journal once needed --invert-sensor."""
    from quatcal_ros.files.journal import Journal, JournalHeader
    from quatcal_ros.tools.cli import solve_main
    rng = np.random.default_rng(8)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 8, rotation_noise_deg=0.05)
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    path = tmp_path / 'samples.csv'
    written = Journal.create(path, JournalHeader('eye_in_hand', 'tool0', 'camera', True))
    for sample in inverted:
        written.append(sample)
    written.close()

    def solved(*options):
        assert solve_main([str(path), *options]) == 0
        return json.loads(capsys.readouterr().out)
    result = solved()
    q = [result['rotation'][k] for k in 'wxyz']
    assert np.degrees(quat.angle_between(q, cell.mounting.quaternion)) < 0.2
    assert result['warnings'] == []
    assert solved('--invert-sensor')['rotation'] == result['rotation']
    # Told otherwise: solved so, and said (the convention check names the fix too).
    result = solved('--no-invert-sensor')
    assert any('the journal was recorded with invert_sensor true; it is solved with false, '
               'as the options say' in warning for warning in result['warnings'])
    # Both: the last one had won, silently.
    for both in (['--invert-sensor', '--no-invert-sensor'], ['--no-invert', '--invert']):
        with pytest.raises(SystemExit) as raised:
            solve_main([str(path), *both])
        assert raised.value.code == 2
        assert ('--invert-sensor and --no-invert-sensor say opposite things: give one'
                in capsys.readouterr().err)


@pytest.mark.parametrize('torn', ['cut', 'all_fields'])
def test_solve_on_a_journal_drops_the_line_a_crash_interrupted(tmp_path, capsys, torn):
    # What the node's resume drops, solve drops too, and says so: a last line without its end
    # of line (a torn number can still leave every field: 0.7071 cut to 0.).
    from quatcal_ros.files.journal import Journal, JournalHeader
    from quatcal_ros.tools.cli import solve_main
    rng = np.random.default_rng(9)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 8, rotation_noise_deg=0.05)
    path = tmp_path / 'samples.csv'
    written = Journal.create(path, JournalHeader('eye_in_hand', 'tool0', 'camera', False))
    for sample in samples:
        written.append(sample)
    written.close()
    last = path.read_text().splitlines()[-1]
    cut = last[:len(last) // 2] if torn == 'cut' else last[:last.rindex('.') + 1]
    with open(path, 'a') as journal:
        journal.write(cut)   # a ninth sample, torn
    assert solve_main([str(path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result['samples'] == 8
    assert any('without an end of line) was being written when the node stopped: dropped'
               in warning for warning in result['warnings']), result['warnings']
    # Too few samples left: the error comes after what was dropped, not alone ('2 sample(s)').
    lines = path.read_text().splitlines(keepends=True)
    path.write_text(''.join(lines[:4]) + cut)
    assert solve_main([str(path)]) == 2
    err = capsys.readouterr().err
    assert 'was being written when the node stopped: dropped' in err.split('\n')[0], err
    assert '2 sample(s); at least 3 are needed' in err, err


def test_a_reader_that_leaves_early_gets_no_traceback(repo_root, cell_csv):
    # `solve ... | head -2`: the pipe closes before the JSON is written
    _, path, _ = cell_csv
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    done = subprocess.Popen([sys.executable, '-m', 'quatcal_ros', 'solve', str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    done.stdout.close()
    error = done.stderr.read().decode()
    assert done.wait(timeout=60) == 1
    assert 'Traceback' not in error and 'BrokenPipeError' not in error, error


def test_the_tools_run_numpys_blas_on_one_thread(repo_root):
    """The entry points set the thread count before numpy loads its BLAS."""
    env = {k: v for k, v in os.environ.items() if not k.endswith('_NUM_THREADS')}
    code = ('import sys\n'
            'from quatcal_ros import __main__ as tools\n'
            'tools.single_threaded_blas()\n'
            'import numpy, threadpoolctl\n'
            'print(max(p["num_threads"] for p in threadpoolctl.threadpool_info()))\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          cwd=repo_root, env=env, check=True)
    assert done.stdout.strip() == '1'


def test_the_tool_list_names_every_tool_in_one_column(capsys):
    from quatcal_ros import __main__ as tools
    assert tools.main(['--help']) == 0
    listed = capsys.readouterr().out.split('tools:\n')[1].splitlines()
    assert [line.split()[0] for line in listed] == list(tools.TOOLS)
    columns = {len(line) - len(line[2:].split(' ', 1)[1].lstrip()) for line in listed}
    assert len(columns) == 1   # every description starts in the same column
    # A misspelt tool names the one meant.
    assert tools.main(['solv', 'x.csv']) == 2
    assert capsys.readouterr().err.startswith(
        "quatcal_ros: unknown tool 'solv' (did you mean solve?)\nusage:")


def test_every_tool_entry_sets_the_thread_count(monkeypatch, capsys):
    from quatcal_ros import __main__ as tools
    for name in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(SystemExit):
        tools.main(['solve', '--help'])
    assert os.environ['OPENBLAS_NUM_THREADS'] == '1'
    monkeypatch.setenv('OPENBLAS_NUM_THREADS', '2')   # the user's choice stays
    tools.single_threaded_blas()
    assert os.environ['OPENBLAS_NUM_THREADS'] == '2'


def test_ten_thousand_samples_solve_in_bounded_memory(tmp_path, capsys):
    """
    O(samples) memory: 10,000 samples (all pairs: 50 million motions, never formed).

    Traced peak (numpy's buffers included) below 300 MB; the all-pairs arrays of the old
    solver took 1.49 GiB and raised MemoryError.
    """
    import tracemalloc

    from quatcal_ros.tools.cli import solve_main
    cell, path, _ = write_cell_csv(tmp_path / 'big.csv', 4, 10000, rotation_noise_deg=0.5,
                                   translation_noise_m=0.001)
    tracemalloc.start()
    try:
        assert solve_main([str(path)]) == 0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    out = json.loads(capsys.readouterr().out)
    assert out['samples'] == 10000 and out['motions'] == 10000 * 9999 // 2
    assert peak < 300e6, f'traced peak {peak / 1e6:.0f} MB'
    truth = cell.mounting.quaternion
    found = quat.wxyz_from_xyzw([out['rotation'][k] for k in 'xyzw'])
    assert np.degrees(quat.angle_between(found, truth)) < 3 * out['uncertainty_deg']


def test_the_next_pose_follows_the_planner_options(repo_root, tmp_path):
    cell, path, _ = write_cell_csv(tmp_path / 'samples.csv', 5, 12, rotation_noise_deg=0.3,
                                   translation_noise_m=0.002)
    last = parse_samples(path.read_text())[-1].link
    for limit in (15.0, 60.0):
        done = run_solve(repo_root, path, '--plan-max-rotation-deg', limit)
        assert done.returncode == 0, done.stderr
        proposal = json.loads(done.stdout)['next_pose']
        q = [proposal['orientation'][k] for k in 'wxyz']
        assert np.degrees(quat.angle_between(q, last.quaternion)) <= limit + 1e-6
        assert proposal['expected_uncertainty_deg'] < proposal['current_uncertainty_deg']
    done = run_solve(repo_root, path, '--plan-view-cone-deg', 90)
    assert done.returncode == 2 and 'plan-view-cone-deg' in done.stderr


def test_a_file_appended_to_itself_gives_the_answer_of_the_file(tmp_path, capsys):
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'once.csv', 8, 12, rotation_noise_deg=0.3,
                                translation_noise_m=0.002)
    twice = tmp_path / 'twice.csv'
    text = path.read_text()
    twice.write_text(text + text.split('\n', 1)[1])   # the rows again, without the header
    assert solve_main([str(path)]) == 0
    once = json.loads(capsys.readouterr().out)
    assert solve_main([str(twice)]) == 0
    doubled = json.loads(capsys.readouterr().out)
    assert doubled['samples'] == 12
    assert doubled['uncertainty_deg'] == once['uncertainty_deg']
    assert doubled['rotation'] == once['rotation']
    warning, = [w for w in doubled['warnings'] if 'repeat earlier ones exactly' in w]
    assert warning.startswith('12 sample(s) repeat earlier ones exactly')
    # By file rows, as the errors give them (the header is row 1): they were numbered from 0.
    assert '(row = the row it repeats, rows of the file as its errors count them: 14 = 2, ' \
        '15 = 3, 16 = 4' in warning and ', ...)' in warning
    assert warning.endswith('the sample numbers elsewhere in this output count the samples '
                            'kept, in file order')
    # A file without rows (moveit's YAML, easy_handeye2's) numbers its samples from 0.
    from quatcal_ros.tools.cli import _copies_warning
    assert '(sample = the one it repeats, numbered from 0 in the file: 3 = 1)' in \
        _copies_warning({3: 1})[0]


def test_an_output_that_is_the_input_is_refused_and_nothing_is_written(tmp_path, capsys):
    """--report victim.csv once replaced the samples file with the report page."""
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'victim.csv', 8, 6)
    before = path.read_bytes()
    for option in ('--report', '--easy-handeye2-out'):
        assert solve_main([str(path), option, f'{tmp_path}/./victim.csv']) == 2
        err = capsys.readouterr().err
        assert f'{option} {tmp_path}/./victim.csv: that is an input file' in err
        assert path.read_bytes() == before
    assert solve_main([str(path), '--report', str(tmp_path / 'r.html'),
                       '--easy-handeye2-out', str(tmp_path / 'r.html')]) == 2
    assert '--report and --easy-handeye2-out name the same file' in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['victim.csv']


def test_a_column_the_reader_does_not_use_may_come_twice(tmp_path, capsys):
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 6)
    header, *rows = path.read_text().splitlines()
    path.write_text('\n'.join([header + ',note,note'] + [row + ',a,b' for row in rows]) + '\n')
    assert solve_main([str(path)]) == 0, capsys.readouterr().err


def test_an_empty_samples_path_is_not_the_current_folder(capsys):
    from quatcal_ros.tools.cli import solve_main
    assert solve_main(['']) == 2
    assert 'the samples path is empty' in capsys.readouterr().err


@pytest.mark.parametrize('content', ['metadata.yaml', 'run_0.mcap', 'run_0.db3'])
def test_a_bag_folder_given_to_solve_is_named_with_replay(tmp_path, capsys, content):
    # It said 'robot_poses.csv missing' (an image folder's), with --invert-sensor that
    # camera images cannot be inverted.
    from quatcal_ros.tools.cli import solve_main
    (tmp_path / 'bag').mkdir()
    (tmp_path / 'bag' / content).write_text('')
    for options in ([], ['--invert-sensor']):
        assert solve_main([str(tmp_path / 'bag'), *options]) == 2
        assert (f'{tmp_path / "bag"} is a rosbag2 recording, not a samples file or an image '
                'dataset folder: replay reads it') in capsys.readouterr().err


def test_an_output_below_a_file_says_the_parent_is_a_file(tmp_path, capsys):
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 6)
    (tmp_path / 'notes.txt').write_text('a file\n')
    assert solve_main([str(path), '--easy-handeye2-out', str(tmp_path / 'notes.txt' / 'x')]) == 2
    err = capsys.readouterr().err
    assert f'{tmp_path / "notes.txt"} is a file, not a folder: choose another path' in err


def test_no_output_is_written_when_another_cannot_be(tmp_path, capsys):
    """--easy-handeye2-out was written, then --report /dev/null failed with exit 2."""
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 6)
    assert solve_main([str(path), '--easy-handeye2-out', str(tmp_path / 'r.calib'),
                       '--report', '/dev/null']) == 2
    assert ('--report /dev/null: exists and is not a regular file: choose another path, '
            'nothing was written') in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['cell.csv']


def test_a_huge_number_is_shown_cut_in_the_error(tmp_path, capsys):
    """A 5000-digit field was echoed in full: a 5 KB error line."""
    from quatcal_ros.tools.cli import solve_main
    path = tmp_path / 'big.csv'
    path.write_text(','.join(COLUMNS) + '\n' + GOOD_ROW.replace('1.0', '9' * 5000, 1) + '\n')
    assert solve_main([str(path)]) == 2
    err = capsys.readouterr().err
    assert 'row 2, field stamp: 9999' in err and '... is not a finite number' in err
    assert len(err) < 300


def test_solve_writes_the_result_file_the_node_writes(tmp_path, capsys, monkeypatch):
    # Only the node and replay wrote it: an offline solve had no file with the quality, both
    # estimates, the validation and the URDF joint.
    from quatcal_ros.files.persistence import read_result_yaml
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 12, rotation_noise_deg=0.3)
    target = tmp_path / 'out' / 'calibration.yaml'
    monkeypatch.chdir(tmp_path)   # the samples named relative: the file says where they are
    assert solve_main(['cell.csv', '--result-out', str(target), '--parent-frame', 'tool0',
                       '--child-frame', 'camera_optical', '--validation-max-rotation-deg',
                       '0.001']) == 0
    printed = capsys.readouterr()
    out = json.loads(printed.out)
    # A failed validation is said on stderr too (only the JSON and the file said it).
    assert printed.err == ('solve: warning: cell.csv: validation failed: leave-one-out prediction '
                           'errors (RMS) above the thresholds: rotation '
                           f'{out["validation"]["rms_rotation_deg"]:.3f} deg > 0.001 deg\n')
    saved = read_result_yaml(target)   # (in a folder made for it)
    assert (saved['parent_frame'], saved['child_frame']) == ('tool0', 'camera_optical')
    assert saved['format'] == 'quatcal_ros/mounting' and saved['setup'] == 'eye_in_hand'
    assert saved['quaternion_xyzw'] == pytest.approx(
        [out['rotation'][k] for k in 'xyzw'], abs=1e-6)
    assert saved['quality']['samples'] == out['samples'] == 12
    assert saved['source'] == {'samples': str(path)}   # (absolute: 'cell.csv' named no file)
    # The warnings saved are those printed: the failed validation's too.
    assert saved['warnings'] == out['warnings'] and saved['validation']['verdict'] == 'fail'
    assert saved['warnings'][0].startswith('validation failed')
    assert '<child link="camera_optical"/>' in saved['urdf']
    # An output that is the input is refused, as the others are.
    assert solve_main([str(path), '--result-out', str(path)]) == 2
    assert '--result-out' in capsys.readouterr().err


def test_a_result_from_a_frame_to_itself_is_refused_and_leading_slashes_dropped(tmp_path,
                                                                                capsys):
    # --parent-frame camera (the child's default) wrote a joint and a command from camera to
    # camera, exit 0; '/tool0' kept its slash, which tf2 refuses in a frame id.
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 8, rotation_noise_deg=0.3)
    assert solve_main([str(path), '--parent-frame', 'camera',
                       '--result-out', str(tmp_path / 'r.yaml')]) == 2
    err = capsys.readouterr().err
    assert "the result would be a transform from frame 'camera' to itself" in err
    assert not (tmp_path / 'r.yaml').exists()
    assert solve_main([str(path), '--parent-frame', '/tool0', '--child-frame', '/cam']) == 0
    command = json.loads(capsys.readouterr().out)['static_transform_publisher']
    assert command.endswith('--frame-id tool0 --child-frame-id cam')
    # Frames TF cannot take (they went into the command, the URDF joint and the files).
    for frame, option, shown in (('/', '--parent-frame', "'/'"),
                                 ('cam\nera', '--child-frame', "'cam\\nera'"),
                                 (' ', '--child-frame', "' '")):
        assert solve_main([str(path), option, frame]) == 2
        assert (f'{shown} is not a frame TF can take (empty, or with a space or a control '
                f'character): give the frame as {option}') in capsys.readouterr().err


def test_an_estimate_not_to_use_is_said_on_stderr_and_in_the_result_file(repo_root, tmp_path):
    # Exit 0 (the contract) with nothing on stderr: a script that redirected stdout wrote a
    # result file 45 degrees off and heard nothing. The file had no `usable` either.
    samples = repo_root / 'data' / 'moveit_pose_samples' / 'pose_samples.json'
    done = run_solve(repo_root, samples, '--result-out', tmp_path / 'r.yaml')   # eye_in_hand
    assert done.returncode == 0
    assert json.loads(done.stdout)['usable'] is False
    assert 'warning: ' in done.stderr and 'the estimate says not to use it ("usable": false)' \
        in done.stderr
    from quatcal_ros.files.persistence import read_result_yaml
    assert read_result_yaml(tmp_path / 'r.yaml')['usable'] is False
    right = run_solve(repo_root, samples, '--setup', 'eye_to_hand')
    assert right.returncode == 0 and 'usable' not in right.stderr


@pytest.mark.parametrize('inverted', [False, True])
def test_the_json_and_the_result_file_say_whether_the_sensor_poses_were_inverted(
        tmp_path, capsys, inverted):
    # A --samples-out CSV records no convention: the result says which one solved it.
    from quatcal_ros.files.persistence import read_result_yaml
    from quatcal_ros.tools.cli import solve_main
    _, path, _ = write_cell_csv(tmp_path / 'cell.csv', 8, 8)
    options = ['--invert-sensor'] if inverted else []
    assert solve_main([str(path), '--result-out', str(tmp_path / 'r.yaml'), *options]) == 0
    assert json.loads(capsys.readouterr().out)['invert_sensor'] is inverted
    assert read_result_yaml(tmp_path / 'r.yaml')['invert_sensor'] is inverted


def test_inverted_sensor_covariances_exact_along_one_axis_solve(repo_root, tmp_path):
    # A covariance exact to a nanometre in position and 0.1 rad in rotation passes the
    # file's check; carried to the inverted poses as a formed product it lost its smallest
    # eigenvalue to rounding, and `solve --invert-sensor` said the solver failed (exit 3).
    rng = np.random.default_rng(0)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 10, rotation_noise_deg=0.5,
                                 translation_noise_m=0.001)[0]
    exact = np.diag([1e-9 ** 2] * 3 + [0.1 ** 2] * 3)   # ROS order: position first
    inverted = [Sample(s.stamp_ns, s.link, Pose(s.sensor.inverse().position,
                                                s.sensor.inverse().quaternion, exact))
                for s in samples]
    path = tmp_path / 'inverted.csv'
    path.write_text(format_samples(inverted))
    done = run_solve(repo_root, path, '--invert-sensor')
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)['noise_model']['sample_covariances'] == 'input'
    factors = sensor_covariance_factors(inverted, invert_sensor=True)
    assert np.all(np.isfinite(factors)) and np.all(np.diagonal(factors, axis1=1, axis2=2) > 0)
    # Ordinary covariances: the factor is the Cholesky factor of the product, to rounding.
    ordinary = [Sample(s.stamp_ns, s.link, Pose(s.sensor.position, s.sensor.quaternion, c))
                for s, c in zip(inverted, (s.sensor.covariance for s in covariance_samples(10)))]
    rotations = quat.matrix_from_quaternion(np.array([s.sensor.quaternion for s in ordinary]))
    A = inverse_perturbation(rotations, np.array([s.sensor.position for s in ordinary]))
    C = residual_order(np.array([s.sensor.covariance for s in ordinary]))
    expected = np.linalg.cholesky(A @ C @ np.transpose(A, (0, 2, 1)))
    found = sensor_covariance_factors(ordinary, invert_sensor=True)
    np.testing.assert_allclose(found, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize('covariance, expected', [
    (np.diag([1e-6] * 3 + [1e-4, 1e-4, 0.0]), 'not positive definite'),
    (np.full((6, 6), np.nan), 'NaN or inf'),
    (np.eye(3), 'not 6x6'),
    (np.outer(np.arange(1.0, 7.0), np.arange(1.0, 7.0)), 'not positive definite'),   # rank 1
    (np.eye(6) + np.triu(np.full((6, 6), 0.1), 1), 'not symmetric'),
])
def test_unusable_covariances_given_to_the_solver_are_named(covariance, expected):
    # The file and message readers refuse them; a program that builds samples itself got
    # numpy's LinAlgError, 'SVD did not converge' or an IndexError.
    samples = covariance_samples(6)
    samples = [Sample(s.stamp_ns, s.link, Pose(s.sensor.position, s.sensor.quaternion,
                                               covariance if k == 4 else s.sensor.covariance))
               for k, s in enumerate(samples)]
    with pytest.raises(ValueError, match=f'sample 4: its sensor covariance is unusable: '
                                         f'{expected}'):
        calibrate(samples)


def test_a_mounting_bumped_halfway_is_named_as_the_replay_and_the_node_name_it(
        repo_root, tmp_path):
    # Ten samples, then the sensor turned 10 deg on its mount: the estimate lies between the
    # two mountings, 5 deg from either, reporting 1.2 deg; only a failed validation said so.
    rng = np.random.default_rng(0)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 20, rotation_noise_deg=0.5,
                                 translation_noise_m=0.001)[0]
    bump = Pose(np.zeros(3), quat.from_axis_angle([1.0, 0.0, 0.0], np.radians(10.0)))
    moved = samples[:10] + [Sample(s.stamp_ns, s.link, bump.inverse() @ s.sensor)
                            for s in samples[10:]]
    for given, expected in ((samples, 0), (moved, 1)):
        path = tmp_path / 'samples.csv'
        path.write_text(format_samples(given))
        done = run_solve(repo_root, path)
        assert done.returncode == 0, done.stderr
        said = [text for text in json.loads(done.stdout)['warnings']
                if 'has the marker or the sensor moved?' in text]
        assert len(said) == expected, said
    assert said[0].endswith('(from sample 10 on): has the marker or the sensor moved? solve '
                            'the samples from sample 10 on, or record again'), said


def test_a_stray_quote_is_named_at_its_row_not_swallowing_the_rows_after_it():
    # A quote opens a CSV field that runs over the ends of lines: one in a note took in the
    # rows after it, and the file solved with 3 of its 12 samples (or an error named the row
    # where the field ended).
    rows = [f'{k}.0,0,0,0,0,0,0,1,0,0,1,0,0,0,1,note {k}' for k in range(1, 13)]
    rows[2] = rows[2].replace('note 3', '"a note with one quote')
    text = '\n'.join([','.join(COLUMNS) + ',note', *rows]) + '\n'
    with pytest.raises(BadInputError) as raised:
        parse_samples(text, 'q.csv')
    assert str(raised.value).startswith('q.csv, row 4: a quote (") opens a field that takes '
                                        'in the rows after it, up to row 13'), raised.value
    # Quotes closed on their row are CSV as it should be, and so is a note over two lines.
    rows[2] = rows[2].replace('"a note with one quote', '"a note, quoted"')
    rows[5] = rows[5].replace('note 6', '"a note\nover two lines, as a spreadsheet writes it"')
    assert len(parse_samples('\n'.join([','.join(COLUMNS) + ',note', *rows]) + '\n')) == 12


@pytest.mark.parametrize('text', ['1_0', '\u0663'])
def test_an_option_number_is_read_as_a_file_number_is(text, capsys):
    # float() reads 1_0 as 10 and '\u0663' as 3; cells of a file were refused, options not.
    from quatcal_ros.tools.cli import solve_main
    with pytest.raises(SystemExit):
        solve_main(['x.csv', '--min-motion-deg', text])
    assert f'argument --min-motion-deg: {text!r} is not a number' in capsys.readouterr().err
