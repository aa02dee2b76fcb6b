"""Tests of files.session_record: the journal's state, result files, the moved-marker watch."""

from dataclasses import replace
import errno

import numpy as np
import pytest
from quatcal_ros.core import calibration
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import exports, journal, persistence
from quatcal_ros.files.journal import JournalHeader
from quatcal_ros.files.session_record import MoveWatch, SamplesJournal, save_result
from quatcal_ros.sim import simulation
import yaml

HEADER = JournalHeader('eye_in_hand', 'tool0', 'camera')


def cell_samples(n, seed=3, noise_deg=0.05):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, n, rotation_noise_deg=noise_deg,
                                    translation_noise_m=0.0005)
    return cell, samples


def assert_same(got, expected):
    assert [s.stamp_ns for s in got] == [s.stamp_ns for s in expected]
    for ours, theirs in zip(got, expected):
        np.testing.assert_array_equal(ours.link.position, theirs.link.position)
        np.testing.assert_allclose(ours.sensor.quaternion, theirs.sensor.quaternion,
                                   atol=1e-15)   # renormalised on reading


@pytest.fixture(scope='module')
def result():
    return calibration.calibrate(cell_samples(12)[1])


def test_save_result_writes_every_file_asked_for(tmp_path, result):
    saved = save_result(result, ('tool0', 'camera'), 'eye_in_hand',
                        result_file=tmp_path / 'r.yaml', easy_handeye2_file=tmp_path / 'e.calib',
                        easy_handeye2_frames={'robot_base_frame': 'base'},
                        extra={'source': {'bag': 'b'}})
    assert saved.ok and [what for what, _ in saved.written] == ['result', 'easy_handeye2']
    document = persistence.read_result_yaml(tmp_path / 'r.yaml')
    assert document['parent_frame'] == 'tool0' and document['source'] == {'bag': 'b'}
    calib = yaml.safe_load((tmp_path / 'e.calib').read_text())
    assert calib['parameters']['robot_base_frame'] == 'base'
    assert calib['parameters']['name'] == 'e'


def test_a_file_that_cannot_be_written_is_named_and_the_others_are_written(tmp_path, result):
    blocked = tmp_path / 'not_a_dir'
    blocked.write_text('a file where a directory should be')
    saved = save_result(result, ('tool0', 'camera'), 'eye_in_hand',
                        result_file=blocked / 'r.yaml', easy_handeye2_file=tmp_path / 'e.calib')
    assert not saved.ok
    ((what, target, error),) = saved.failed
    assert what == 'result' and target == blocked / 'r.yaml' and isinstance(error, OSError)
    assert saved.written == [('easy_handeye2', tmp_path / 'e.calib')]


def test_choose_frames_takes_the_first_name_given_of_each():
    assert exports.choose_frames('eye_in_hand') == ('tool0', 'camera')
    assert exports.choose_frames('eye_to_hand', (None, ''), ('base', 'cam')) == ('base', 'cam')
    assert exports.choose_frames('eye_in_hand', ('link', None), ('x', 'cam')) == ('link', 'cam')
    assert exports.choose_frames('eye_in_hand', None, ('', 'cam')) == ('tool0', 'cam')


def test_move_watch_warns_once_when_the_marker_moves():
    cell, samples = cell_samples(16, seed=5, noise_deg=0.02)
    bump = Pose.create([0.0, 0.0, 0.0], [np.cos(0.05), np.sin(0.05), 0.0, 0.0])  # ~5.7 deg
    moved = samples[:10] + [replace(s, sensor=s.sensor @ bump) for s in samples[10:]]
    q_z = cell.mounting.quaternion
    watch = MoveWatch()
    assert watch.check(moved[:10], q_z, 'eye_in_hand') == []
    ((level, text),) = watch.check(moved, q_z, 'eye_in_hand')
    assert level == 'warning' and watch.move.first == 10
    assert text == watch.warning(len(moved)) and 'has the marker or the sensor moved?' in text
    assert watch.check(moved, q_z, 'eye_in_hand') == []        # said once
    # A move lasts: more samples of the moved marker keep it.
    more = moved + [replace(s, sensor=s.sensor @ bump) for s in cell_samples(
        22, seed=5, noise_deg=0.02)[1][16:]]
    for n in range(17, 23):
        assert watch.check(more[:n], q_z, 'eye_in_hand') == []
    assert watch.warning(22).startswith('the residual rose from') and watch.move.first == 10
    watch.reset()
    assert watch.move is None and watch.warning(len(moved)) is None


def test_a_rise_that_does_not_last_is_withdrawn():
    """Noisier samples for a while (taken while moving): not a move once they agree again."""
    cell, samples = cell_samples(22, seed=5, noise_deg=0.02)
    bump = Pose.create([0.0, 0.0, 0.0], [np.cos(0.05), np.sin(0.05), 0.0, 0.0])
    bumped = samples[:10] + [replace(s, sensor=s.sensor @ bump) for s in samples[10:14]] + \
        samples[14:]
    q_z = cell.mounting.quaternion
    watch = MoveWatch()
    said = {n: watch.check(bumped[:n], q_z, 'eye_in_hand') for n in range(10, 23)}
    assert [level for level, _ in said[13]] == ['warning']
    # 14, 15 and 16 agree with the samples before 10 again: withdrawn with the 17th sample.
    assert said[17] == [('info', 'moved-marker warning withdrawn: the last 3 samples agree '
                                 'with those before sample 10 again; the rise from sample 10 '
                                 'on did not last (noisier samples, not a move)')]
    assert all(not said[n] for n in said if n not in (13, 17))
    assert watch.move is None and watch.warning(22) is None


def test_a_rise_where_capture_became_continuous_says_so():
    cell, samples = cell_samples(16, seed=5, noise_deg=0.02)
    bump = Pose.create([0.0, 0.0, 0.0], [np.cos(0.05), np.sin(0.05), 0.0, 0.0])
    noisier = samples[:10] + [replace(s, sensor=s.sensor @ bump) for s in samples[10:]]
    watch = MoveWatch()
    watch.capture_continuous(10)
    ((level, text),) = watch.check(noisier, cell.mounting.quaternion, 'eye_in_hand')
    assert level == 'warning'
    assert text.startswith('the residual rose from ')
    assert text.endswith(' over the last 6 samples (from sample 10 on, where capture_mode '
                         'became continuous at sample 10): samples taken while moving are '
                         'noisier than still ones, the more so with a time offset between the '
                         'streams (sensor_time_offset_s). If nothing moved, this passes once '
                         'still samples come again (capture_mode auto); if the marker or the '
                         'sensor moved, call ~/reset and recollect')
    watch.reset()
    assert watch.continuous_from == []
    # A rise long after the change is not its doing.
    watch.capture_continuous(4)
    ((level, text),) = watch.check(noisier, cell.mounting.quaternion, 'eye_in_hand')
    assert 'has the marker or the sensor moved?' in text and 'continuous' not in text


def test_journal_problem_is_kept_until_the_samples_are_on_disk(tmp_path, monkeypatch):
    _, samples = cell_samples(3)
    record = SamplesJournal(tmp_path / 'samples.csv', HEADER, resume=False)
    real_write = journal.os.write

    def full_disk(fd, data):
        raise OSError(errno.ENOSPC, 'No space left on device')
    monkeypatch.setattr(journal.os, 'write', full_disk)
    ((level, text),) = record.append(samples[:1])
    assert level == 'error' and '1 captured sample(s) not yet saved' in text
    assert record.problem == text
    assert record.saved == 0 and record.count == 1
    monkeypatch.setattr(journal.os, 'write', real_write)
    assert record.append(samples[1:2]) == [
        ('info', f'the 1 captured sample(s) that could not be written are now saved to '
                 f'{tmp_path / "samples.csv"}')]
    assert record.sync() == [] and record.append(samples[2:3]) == []
    assert record.problem is None and record.count == record.saved == 3
    assert len(journal.read_journal(tmp_path / 'samples.csv').samples) == 3
    record.close()


def test_a_reset_that_failed_does_not_crash_the_next_sample(tmp_path, monkeypatch):
    _, samples = cell_samples(2)
    path = tmp_path / 'samples.csv'
    record = SamplesJournal(path, HEADER, resume=False)
    record.append(samples[:1])

    def cannot_move(*args, **kwargs):
        raise OSError(errno.EROFS, 'Read-only file system')
    monkeypatch.setattr(journal, 'move_aside', cannot_move)
    assert 'could not start a new samples journal' in record.restart()
    assert record.problem is not None
    monkeypatch.undo()
    # The journal's file is still there: the next sample goes into it, nothing crashes.
    assert record.append(samples[1:]) == [] and record.sync() == []
    assert len(journal.read_journal(path).samples) == 2
    record.close()


def test_a_journal_deleted_while_the_node_runs_is_re_created_in_order(tmp_path):
    _, samples = cell_samples(4)
    path = tmp_path / 'samples.csv'
    record = SamplesJournal(path, HEADER, resume=False)
    record.append(samples[:2], samples[:2])
    path.unlink()                                   # someone cleans up ~/.ros
    ((level, text),) = record.append(samples[2:3], samples[:3])
    assert level == 'error' and 're-created with all 3 samples' in text
    assert record.append(samples[3:], samples) == [] and record.sync() == []
    assert_same(journal.read_journal(path).samples, samples)
    record.close()


@pytest.mark.parametrize('new_header', [False, True])
def test_a_file_put_in_the_journals_place_is_moved_aside_not_overwritten(tmp_path, new_header):
    """And a setup change meanwhile (it once wrote our first line into that file, used it)."""
    _, samples = cell_samples(3)
    path = tmp_path / 'samples.csv'
    record = SamplesJournal(path, HEADER, resume=False)
    record.append(samples[:1], samples[:1])
    path.unlink()
    path.write_text("somebody else's notes\n")
    header = replace(HEADER, setup='eye_to_hand') if new_header else HEADER
    assert record.set_header(header) == []
    assert path.read_text() == "somebody else's notes\n"
    record.append(samples[1:], samples)   # re-created (with the new header), the file aside
    contents = journal.read_journal(path)
    assert contents.header == header
    assert_same(contents.samples, samples)
    (aside,) = [p for p in tmp_path.iterdir() if '.previous-' in p.name]
    assert aside.read_text() == "somebody else's notes\n"
    record.close()


@pytest.mark.parametrize('device', ['null', 'fifo'])
def test_a_path_that_is_not_a_regular_file_is_never_replaced(tmp_path, result, device):
    import os
    if device == 'fifo':
        device = tmp_path / 'fifo'
        os.mkfifo(device)
    else:   # /dev/null, through a link of our own: a regression replaces the link, not it
        device = tmp_path / 'null'
        device.symlink_to('/dev/null')
    before = os.stat(device)
    saved = save_result(result, ('tool0', 'camera'), 'eye_in_hand', result_file=device)
    ((_, _, error),) = saved.failed
    assert 'not a regular file' in str(error)
    with pytest.raises(journal.JournalRefused, match='not a regular file'):
        SamplesJournal(device, HEADER, resume=False)
    after = os.stat(device)
    assert (after.st_ino, after.st_mode, after.st_rdev) == \
        (before.st_ino, before.st_mode, before.st_rdev)


def test_a_new_header_that_could_not_be_written_is_written_with_the_next_sample(
        tmp_path, monkeypatch):
    """A full disk at a setup change once left the old setup in the journal for good."""
    _, samples = cell_samples(3)
    path = tmp_path / 'samples.csv'
    record = SamplesJournal(path, HEADER, resume=False)
    record.append(samples[:1], samples[:1])
    real_write = journal.atomic_write_text

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, 'No space left on device')
    monkeypatch.setattr(journal, 'atomic_write_text', full_disk)
    changed = replace(HEADER, setup='eye_to_hand')
    ((level, text),) = record.set_header(changed)
    assert level == 'error' and text.startswith(
        'the new setup, frames or TF joint are not yet recorded')
    assert record.problem == text and journal.read_journal(path).header == HEADER
    monkeypatch.setattr(journal, 'atomic_write_text', real_write)
    assert record.append(samples[1:2], samples[:2]) == [] and record.sync() == []
    assert record.problem is None
    contents = journal.read_journal(path)
    assert contents.header == changed
    assert_same(contents.samples, samples[:2])
    # and ~/reset starts the new journal with it too
    record.restart()
    assert journal.read_journal(path).header == changed
    record.close()
