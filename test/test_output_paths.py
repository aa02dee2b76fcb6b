"""Output paths that would destroy an input or cannot be written are named before any write."""

import os

from quatcal_ros.tools.output_paths import output_problem


def test_a_new_file_in_a_dataset_folder_is_fine_its_own_files_are_not(tmp_path):
    for name in ('robot_poses.csv', 'camera_info.yaml', 'board.yaml'):
        (tmp_path / name).write_text('')
    (tmp_path / 'images').mkdir()
    (tmp_path / 'images' / 'a.png').write_bytes(b'')
    report = tmp_path / 'report.html'
    assert output_problem([('dataset', tmp_path)], {'--report': str(report)}) is None
    report.write_text('the first run')    # the same command again: still fine
    assert output_problem([('dataset', tmp_path)], {'--report': str(report)}) is None
    for inside in ('board.yaml', 'images/a.png', 'images/new.png', 'images'):
        text = output_problem([('dataset', tmp_path)], {'--report': str(tmp_path / inside)})
        assert text.startswith(f'--report {tmp_path / inside}: that is an input file'), inside


def test_a_bag_given_as_its_storage_file_protects_its_folder_files(tmp_path):
    bag = tmp_path / 'run'
    bag.mkdir()
    for name in ('metadata.yaml', 'run_0.db3', 'run_1.db3'):
        (bag / name).write_text('')
    given = [('bag', bag / 'run_0.db3')]
    for name in ('metadata.yaml', 'run_0.db3', 'run_1.db3'):
        assert output_problem(given, {'--samples-out': str(bag / name)}) is not None, name
    assert output_problem(given, {'--samples-out': str(bag / 'samples.csv')}) is None
    # The folder given: nothing is written in it.
    assert output_problem([('bag', bag)], {'--samples-out': str(bag / 'samples.csv')}) is not None


def test_paths_through_links_home_and_loops_are_compared_without_raising(tmp_path, monkeypatch):
    monkeypatch.setenv('HOME', str(tmp_path))
    samples = tmp_path / 'cell.csv'
    samples.write_text('')
    os.symlink(samples, tmp_path / 'link.csv')
    assert output_problem([('file', '~/cell.csv')], {'--report': str(tmp_path / 'link.csv')})
    os.symlink(tmp_path / 'loop', tmp_path / 'loop')
    outputs = {'--report': '~nosuchuser/r.html', '--other': str(tmp_path / 'loop')}
    assert output_problem([('file', tmp_path / 'loop')], outputs)
    same = {'--a': str(tmp_path / 'r.html'), '--b': str(tmp_path / 'r.html')}
    assert output_problem([('file', samples)], same) == (
        f'--a and --b name the same file {tmp_path / "r.html"}: one would replace the other')
    assert output_problem([('file', None)], {'--a': None}) is None


def test_an_output_that_cannot_be_written_is_named(tmp_path):
    """A device or a directory, or a parent that is a file: refused before anything is written."""
    (tmp_path / 'file').write_text('')
    for path, why in (('/dev/null', 'exists and is not a regular file'),
                      (str(tmp_path), 'exists and is not a regular file'),
                      (str(tmp_path / 'file' / 'sub' / 'r.html'),
                       f'{tmp_path / "file"} is a file, not a folder')):
        assert output_problem([('file', None)], {'--report': path}) == (
            f'--report {path}: {why}: choose another path, nothing was written')
    assert output_problem([('file', None)], {'--report': str(tmp_path / 'new' / 'r.html')}) is None
    os.symlink(tmp_path / 'loop', tmp_path / 'loop')
    for path in (tmp_path / 'loop', tmp_path / 'loop' / 'sub' / 'r.html'):
        assert output_problem([('file', None)], {'--report': str(path)}) == (
            f'--report {path}: {tmp_path / "loop"} is a symbolic link that leads back to '
            'itself: choose another path, nothing was written')
