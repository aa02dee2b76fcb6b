"""
Tests of quatcal_ros.files.journal: the crash-safe samples journal (no ROS).

A journal must give back every sample appended to it, survive a crash at any byte (losing at
most the line being written), and never overwrite or delete a file that holds data: corrupt
or foreign files and journals that are not resumed are moved aside with a timestamp.
"""

from dataclasses import replace
import errno
import json
import os
import re

from hypothesis import given, settings
from hypothesis import strategies as st
from journal_files import aside_files
from journal_files import write_journal
import numpy as np
from numpy.testing import assert_allclose
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import journal
from quatcal_ros.files.journal import JournalError, JournalHeader, JournalRefused
from quatcal_ros.files.samples_csv import COLUMNS, COVARIANCE_COLUMNS, format_samples
from quatcal_ros.sim import simulation
from quatcal_ros.tools import cli

HEADER = JournalHeader('eye_in_hand', 'tool0', 'camera')
NOW = 1_700_000_000.0   # a fixed wall time for the moved-aside names


def make_samples(n, seed=1):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, n, rotation_noise_deg=0.1,
                                    translation_noise_m=0.001)
    # stamps of today's clock to the nanosecond: as floats they moved by up to ~120 ns
    return [replace(s, stamp_ns=1_733_450_000_123_456_789 + k * 1_000_000_007)
            for k, s in enumerate(samples)]


def assert_same_samples(got, expected):
    assert len(got) == len(expected)
    for a, b in zip(got, expected):
        assert a.stamp_ns == b.stamp_ns       # the CSV stamp is exact decimal seconds
        assert_allclose(a.link.position, b.link.position, rtol=0, atol=0)
        assert_allclose(a.sensor.position, b.sensor.position, rtol=0, atol=0)
        assert_allclose(a.link.quaternion, b.link.quaternion, rtol=0, atol=1e-15)
        assert_allclose(a.sensor.quaternion, b.sensor.quaternion, rtol=0, atol=1e-15)


def started(path, header=HEADER, resume=False):
    opened, report = journal.start(path, header, resume, now=NOW)
    return opened, report


def written_journal(path, samples, header=HEADER):
    return write_journal(path, samples, header, now=NOW)


# --- format -----------------------------------------------------------------------------------

def test_header_line_round_trip_and_odd_frame_names():
    header = JournalHeader('eye_to_hand', 'base link,1', 'cam/optical=x%')
    line = header.line()
    assert line.startswith('# quatcal_ros samples journal v1 setup=eye_to_hand ')
    assert ',' not in line and line.count('=') == 3
    assert JournalHeader.parse(line) == header
    assert HEADER.line() == ('# quatcal_ros samples journal v1 setup=eye_in_hand '
                             'link_frame=tool0 sensor_frame=camera')   # an earlier version's
    inverted = JournalHeader('eye_in_hand', 'tool0', 'camera', True)
    assert inverted.line() == HEADER.line() + ' invert_sensor=true'
    assert JournalHeader.parse(inverted.line()) == inverted
    assert JournalHeader.parse(HEADER.line()).invert_sensor is None


def test_the_tf_joint_round_trips_in_the_header():
    # A frame with a comma is percent-encoded: the comma separates the numbers.
    chain = ('camera link,2', (0.01, -0.02, 0.1 / 3, 0.5, -0.5, 0.5, -0.5))
    header = JournalHeader('eye_in_hand', 'tool0', 'optical', False, chain)
    line = header.line()
    assert line.endswith(' invert_sensor=false static_chain=camera%20link%2C2,0.01,-0.02,'
                         f'{0.1 / 3!r},0.5,-0.5,0.5,-0.5')
    assert JournalHeader.parse(line) == header   # the numbers exactly (repr)
    # Not compared on resume: a node without the tree yet goes on with the journal.
    assert not header.differences(replace(HEADER, sensor_frame='optical'))


@pytest.mark.parametrize('value, problem', [
    ('camera_link,0,0,0,0,0,0', '6 numbers, 7 expected'),
    ('camera_link,0,0,0,0,0,0,2', 'the quaternion has norm 2, not 1 (tolerance 0.001)'),
    # just beyond the tolerance, the digits that show it (4 gave 'norm 1.001')
    ('camera_link,0,0,0,0,0,0,1.0011', 'the quaternion has norm 1.0011, not 1 (tolerance '
                                       '0.001)'),
    (',0,0,0,0,0,0,1', 'no frame'), ('%2F,0,0,0,0,0,0,1', 'no frame'),
    ('camera_link,0,0,nan,0,0,0,1', 'not 7 finite numbers'),
    ('camera_link,0,0,x,0,0,0,1', 'not 7 finite numbers'),
    ('camera_link,1_0,0,0,0,0,0,1', 'not 7 finite numbers'),
    ('camera_link,1e300,0,0,0,0,0,1', '[1e+300, 0.0, 0.0] m is not a position in a robot '
                                      'cell (at most 1000 m from the origin; positions are in '
                                      'metres)'),   # (was taken)
    ('camera,0,0,0,0,0,0,1', 'the frame is the sensor frame camera itself'),
    ('%2Fcamera,0,0,0,0,0,0,1', 'the frame is the sensor frame camera itself')])
def test_a_bad_tf_joint_in_the_header_is_refused(value, problem):
    # (the root the sensor frame itself: a hand-edited line gave a traceback in solve)
    with pytest.raises(JournalError) as raised:
        JournalHeader.parse(HEADER.line() + f' static_chain={value}', 'f.csv')
    assert str(raised.value) == (
        f"f.csv, row 1: static_chain='{value}' in the journal header: {problem} (expected "
        'FRAME,x,y,z,qx,qy,qz,qw: the top of the static chain above the sensor frame and the '
        'transform from it)')
    # A quaternion written to 4 digits by hand is one.
    assert JournalHeader.parse(HEADER.line() + ' static_chain=camera_link,0,0,0,0.7071,0,0,'
                               '0.7071').static_chain == ('camera_link', (0, 0, 0, 0.7071, 0, 0,
                                                                          0.7071))


@pytest.mark.parametrize('line, words', [
    ('stamp,link_x', 'not a quatcal_ros samples journal'),
    # The magic words alone, with or without a space: no version (one raised a ValueError)
    ('# quatcal_ros samples journal ', 'expected .* then its version, v1, and its settings'),
    ('# quatcal_ros samples journal', 'expected .* then its version, v1, and its settings'),
    ('# quatcal_ros samples journal v2 setup=eye_in_hand', "version 'v2'"),
    ('# quatcal_ros samples journal v1 setup=eye_in_hand link_frame=tool0', 'sensor_frame'),
    ('# quatcal_ros samples journal v1 setup=a link_frame=b sensor_frame=c colour=red',
     'colour'),
    ('# quatcal_ros samples journal v1 setup=eye_on_base link_frame=b sensor_frame=c',
     "row 1: setup='eye_on_base' in the journal header is not one of eye_in_hand, eye_to_hand"),
    ('# quatcal_ros samples journal v1 setup=eye_in_hand link_frame=b sensor_frame=c '
     'invert_sensor=yes', "row 1: invert_sensor='yes' in the journal header is not true or "
                          'false'),
])
def test_bad_header_lines_are_refused(line, words):
    with pytest.raises(JournalError, match=words):
        JournalHeader.parse(line, 'f.csv')


def test_appended_samples_read_back_exactly(tmp_path):
    samples = make_samples(7)
    path = tmp_path / 'a' / 'b' / 'samples.csv'          # parent directories are made
    data = written_journal(path, samples)
    lines = data.decode().splitlines()
    assert lines[0] == HEADER.line()
    assert lines[1] == ','.join(COLUMNS + COVARIANCE_COLUMNS)
    assert len(lines) == 2 + len(samples)
    contents = journal.read_journal(path)
    assert contents.header == HEADER and contents.notices == []
    assert_same_samples(contents.samples, samples)
    assert contents.intact_bytes == contents.size_bytes == len(data)
    path.write_bytes(b'\xef\xbb\xbf' + data)   # an editor's byte-order mark: still the journal
    contents = journal.read_journal(path)
    assert contents.header == HEADER and contents.notices == []
    assert_same_samples(contents.samples, samples)


def test_solve_reads_a_journal_as_a_samples_csv(tmp_path, capsys):
    path = tmp_path / 'samples.csv'
    written_journal(path, make_samples(8))
    assert cli.solve_main([str(path)]) == 0
    assert '"samples": 8' in capsys.readouterr().out


def test_solve_of_a_journal_with_a_tf_joint_hangs_the_mounting_where_the_tree_takes_it(
        tmp_path, capsys):
    # camera_link -> camera (the sensor frame) static: the joint is tool0 -> camera_link.
    path = tmp_path / 'samples.csv'
    chain = ('camera_link', (0.01, 0.02, 0.0, -0.5, 0.5, -0.5, 0.5))
    written_journal(path, make_samples(8), replace(HEADER, static_chain=chain))
    assert cli.solve_main([str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    command = out['static_transform_publisher']
    assert command.endswith('--frame-id tool0 --child-frame-id camera_link'), command
    values = [float(v) for v in re.findall(r'--(?:x|y|z|qx|qy|qz|qw) (\S+)', command)]
    joined = Pose.create(values[:3], quat.wxyz_from_xyzw(values[3:]))
    x, y, z, qx, qy, qz, qw = chain[1]
    back = joined @ Pose.create((x, y, z), (qw, qx, qy, qz))   # = the calibrated mounting
    assert_allclose(back.position, [out['translation'][k] for k in 'xyz'], atol=2e-10)
    assert out['urdf'].startswith('<!-- camera already hangs from camera_link in TF')
    # --child-frame camera_link, the chain's root, gave the camera's transform under its name.
    assert cli.solve_main([str(path), '--child-frame', '/camera_link']) == 0
    rooted = json.loads(capsys.readouterr().out)
    assert rooted['static_transform_publisher'] == command
    assert (rooted['parent_frame'], rooted['child_frame']) == ('tool0', 'camera')
    assert rooted['rotation'] == out['rotation']
    assert ('--child-frame camera_link is the top of the static chain above the sensor frame '
            "camera in the journal's TF tree: the result is the calibrated tool0 -> camera, and "
            'its static_transform_publisher line and URDF joint are tool0 -> camera_link (the '
            'transform to camera_link)') in rooted['warnings']
    # Edited by hand so that the sensor frame is its own parent: an error, not a traceback.
    text = path.read_text().replace('static_chain=camera_link,', 'static_chain=%2Fcamera,')
    path.write_text(text)
    assert cli.solve_main([str(path)]) == 2
    assert f'{path}, row 1: static_chain=' in capsys.readouterr().err


def test_every_append_is_fsynced(tmp_path, monkeypatch):
    opened, _ = started(tmp_path / 'samples.csv')
    calls = []
    real_fsync = os.fsync
    monkeypatch.setattr(journal.os, 'fsync', lambda fd: calls.append(fd) or real_fsync(fd))
    for sample in make_samples(3):
        opened.append(sample)
    assert len(calls) == 3
    opened.close()


def test_append_without_sync_is_in_the_file_and_sync_makes_it_durable(tmp_path, monkeypatch):
    path = tmp_path / 'samples.csv'
    opened, _ = started(path)
    samples = make_samples(3)
    calls = []
    real_fsync = os.fsync
    monkeypatch.setattr(journal.os, 'fsync', lambda fd: calls.append(fd) or real_fsync(fd))
    opened.append(samples[0], sync=False)
    assert calls == []
    assert_same_samples(journal.read_journal(path).samples, samples[:1])   # a crash keeps it
    opened.sync()
    opened.sync()                    # nothing new written: no second fsync
    assert len(calls) == 1
    opened.append(samples[1], sync=False)
    opened.close()                   # closing makes the last line durable too
    assert len(calls) == 2
    assert_same_samples(journal.read_journal(path).samples, samples[:2])


# --- crashes ----------------------------------------------------------------------------------

def test_a_torn_last_line_is_dropped_with_a_notice(tmp_path):
    samples = make_samples(5)
    path = tmp_path / 'samples.csv'
    data = written_journal(path, samples)
    path.write_bytes(data[:-40])        # the last row lost its end (a write cut short)
    contents = journal.read_journal(path)
    assert_same_samples(contents.samples, samples[:4])
    (notice,) = contents.notices
    assert 'without an end of line' in notice and str(path) in notice
    assert contents.intact_bytes < contents.size_bytes


def test_a_last_line_with_too_few_fields_is_dropped(tmp_path):
    samples = make_samples(4)
    path = tmp_path / 'samples.csv'
    data = written_journal(path, samples)
    last = data[:-1].rfind(b'\n') + 1
    path.write_bytes(data[:last] + b'1700000003.0,0.5,0.1\n')
    contents = journal.read_journal(path)
    assert_same_samples(contents.samples, samples[:3])
    (notice,) = contents.notices
    assert 'row 6' in notice and '3 of 15 fields' in notice


def test_a_comment_or_a_blank_line_at_the_end_is_no_interrupted_write(tmp_path):
    # A note added by hand at the end was called 'an interrupted write: dropped'.
    samples = make_samples(4)
    path = tmp_path / 'samples.csv'
    data = written_journal(path, samples)
    for end in (b'# moved the camera after this\n', b'  # indented\n', b'\n', b'  \n'):
        path.write_bytes(data + end)
        contents = journal.read_journal(path)
        assert_same_samples(contents.samples, samples)
        assert contents.notices == [] and contents.intact_bytes == len(data + end)


@settings(max_examples=60, deadline=None)
@given(cut=st.floats(min_value=0.0, max_value=1.0))
def test_a_crash_at_any_byte_loses_at_most_the_line_being_written(tmp_path_factory, cut):
    samples = make_samples(5, seed=3)
    path = tmp_path_factory.mktemp('crash') / 'samples.csv'
    data = written_journal(path, samples)
    header_bytes = data.index(b'\n', data.index(b'\n') + 1) + 1   # written atomically
    size = header_bytes + int(round(cut * (len(data) - header_bytes)))
    path.write_bytes(data[:size])
    contents = journal.read_journal(path)
    complete = data[header_bytes:size].count(b'\n')
    assert_same_samples(contents.samples, samples[:complete])
    assert len(contents.notices) == (0 if data[:size].endswith(b'\n') else 1)


def test_resume_cuts_the_torn_line_and_appends_cleanly(tmp_path):
    samples = make_samples(6)
    path = tmp_path / 'samples.csv'
    data = written_journal(path, samples[:5])
    path.write_bytes(data[:-25])
    opened, report = started(path, resume=True)
    assert_same_samples(report.samples, samples[:4])
    assert [level for level, _ in report.messages] == ['warning', 'info']
    assert 'resumed 4 samples' in report.messages[-1][1]
    opened.append(samples[5])
    opened.close()
    contents = journal.read_journal(path)
    assert contents.notices == []
    assert_same_samples(contents.samples, samples[:4] + [samples[5]])


def test_a_failed_write_is_retried_without_a_gap_or_a_torn_line(tmp_path, monkeypatch):
    samples = make_samples(4)
    opened, _ = started(tmp_path / 'samples.csv')
    opened.append(samples[0])
    real_write = os.write

    def disk_full(fd, data):   # half the line reaches the file, then the disk is full
        real_write(fd, data[:len(data) // 2])
        raise OSError(errno.ENOSPC, 'No space left on device')

    monkeypatch.setattr(journal.os, 'write', disk_full)
    with pytest.raises(OSError, match='No space'):
        opened.append(samples[1])
    with pytest.raises(OSError):
        opened.append(samples[2])
    assert opened.unwritten == 2 and opened.count == 3
    monkeypatch.setattr(journal.os, 'write', real_write)
    opened.append(samples[3])
    assert opened.unwritten == 0
    opened.close()
    contents = journal.read_journal(tmp_path / 'samples.csv')
    assert contents.notices == []
    assert_same_samples(contents.samples, samples)


# --- corrupt and foreign files ----------------------------------------------------------------

def test_a_bad_row_in_the_middle_is_corrupt(tmp_path):
    path = tmp_path / 'samples.csv'
    data = written_journal(path, make_samples(4))
    lines = data.decode().splitlines(keepends=True)
    lines[3] = lines[3].replace(',', ',abc', 1)
    path.write_text(''.join(lines))
    with pytest.raises(JournalError, match=r'row 4, field link_x: .*not a number'):
        journal.read_journal(path)


@pytest.mark.parametrize('content, words', [
    (b'format: quatcal_ros/rotation\nrotation: {x: 0, y: 0, z: 0, w: 1}\n',
     'not a quatcal_ros samples journal'),
    (b'', 'empty file'),
    (b'\x89PNG\r\n\x1a\n\x00\x00', 'not a text file'),
    (','.join(COLUMNS).encode() + b'\n', 'not a quatcal_ros samples journal'),
    (HEADER.line().encode() + b'\n', 'ends before its column row'),
])
def test_corrupt_or_foreign_files_are_moved_aside_and_reported(tmp_path, content, words):
    path = tmp_path / 'samples.csv'
    path.write_bytes(content)
    for resume in (True, False):
        opened, report = started(path, resume=resume)
        opened.close()
        (level, text), = report.messages
        assert level == 'error' and words in text and str(report.moved_to) in text
        assert report.moved_to.read_bytes() == content           # kept as it was
        assert report.moved_to.name.startswith('samples.csv.corrupt-')
        assert report.samples == []
        assert journal.read_journal(path).samples == []          # a new journal
        path.unlink()
        report.moved_to.rename(path)
    assert len(aside_files(tmp_path, 'corrupt')) == 0


def test_resume_false_moves_an_earlier_session_aside(tmp_path):
    path = tmp_path / 'samples.csv'
    data = written_journal(path, make_samples(3))
    opened, report = started(path, resume=False)
    opened.close()
    (level, text), = report.messages
    assert level == 'warning' and 'held 3 samples' in text and 'resume:=true' in text
    (aside,) = aside_files(tmp_path, 'previous')
    assert aside == report.moved_to and aside.read_bytes() == data
    assert str(aside) in text
    assert journal.read_journal(path).samples == []
    # A journal without samples is simply replaced: nothing to keep.
    opened, report = started(path, resume=False)
    opened.close()
    assert report.moved_to is None and len(aside_files(tmp_path, 'previous')) == 1


def test_resume_refuses_another_setup_or_other_frames(tmp_path):
    path = tmp_path / 'samples.csv'
    data = written_journal(path, make_samples(3))
    for other, words in ((JournalHeader('eye_to_hand', 'tool0', 'camera'), 'setup'),
                         (JournalHeader('eye_in_hand', 'flange', 'camera'), 'link_frame')):
        with pytest.raises(JournalRefused, match=f'resume:=true refused: .*{words}'):
            started(path, other, resume=True)
        assert path.read_bytes() == data                       # untouched
    assert aside_files(tmp_path, 'previous') == aside_files(tmp_path, 'corrupt') == []
    # The lock was released: the right parameters resume it.
    opened, report = started(path, resume=True)
    assert len(report.samples) == 3
    opened.close()


def test_resume_with_another_invert_sensor_goes_on_and_records_it(tmp_path):
    """The samples are the poses as received: the header says how they are solved now."""
    path = tmp_path / 'samples.csv'
    written_journal(path, make_samples(3), JournalHeader('eye_in_hand', 'tool0', 'camera',
                                                         False))
    now = JournalHeader('eye_in_hand', 'tool0', 'camera', True)
    opened, report = started(path, now, resume=True)
    opened.close()
    assert len(report.samples) == 3
    contents = journal.read_journal(path)
    assert contents.header == now and len(contents.samples) == 3


def test_the_sensor_time_offsets_round_trip_and_bad_ones_are_refused():
    header = replace(HEADER, invert_sensor=False, sensor_time_offsets=(0.0, -0.03))
    assert header.line().endswith(' invert_sensor=false sensor_time_offset_s=0.0,-0.03')
    assert JournalHeader.parse(header.line()) == header
    assert not header.differences(HEADER)   # not compared: start warns instead
    for value in ('', '0.0,x', 'nan', '1_0', '0.0,,0.1'):
        with pytest.raises(JournalError) as raised:
            JournalHeader.parse(HEADER.line() + f' sensor_time_offset_s={value}', 'f.csv')
        assert str(raised.value) == (
            f"f.csv, row 1: sensor_time_offset_s='{value}' in the journal header: expected "
            'seconds, finite numbers separated by commas')


def test_paired_with_lists_each_offset_the_kept_samples_were_paired_with():
    header = replace(HEADER, sensor_time_offsets=(0.0,))
    assert header.paired_with(0.0).sensor_time_offsets == (0.0,)
    assert header.paired_with(-0.03).sensor_time_offsets == (0.0, -0.03)
    assert header.paired_with(-0.03).paired_with(0.0).sensor_time_offsets == (0.0, -0.03)
    assert header.paired_with(-0.03, kept=False).sensor_time_offsets == (-0.03,)
    # An earlier version's journal does not say: unknown while its samples are kept.
    assert HEADER.paired_with(-0.03).sensor_time_offsets is None
    assert HEADER.paired_with(-0.03, kept=False).sensor_time_offsets == (-0.03,)


def test_resume_with_another_sensor_time_offset_warns(tmp_path):
    """Resumed samples keep their pairing, as after a change at runtime: said, not silent."""
    path = tmp_path / 'samples.csv'
    written = written_journal(path, make_samples(3), replace(HEADER, sensor_time_offsets=(0.0,)))
    opened, report = started(path, replace(HEADER, sensor_time_offsets=(-0.03,)), resume=True)
    opened.close()
    warnings = [text for level, text in report.messages if level == 'warning']
    assert warnings == [
        f'{path}: its 3 samples were paired with sensor_time_offset_s 0 (its first line); '
        '-0.03 applies to new poses only: the samples resumed keep their pairing. Call '
        '~/reset to take them again with -0.03, or resume with sensor_time_offset_s:=0.0']
    # Nothing rewritten: no sample was paired with -0.03 (the node adds it with the first).
    assert path.read_bytes() == written
    opened, report = started(path, replace(HEADER, sensor_time_offsets=(0.0,)), resume=True)
    opened.close()
    assert [level for level, _ in report.messages] == ['info']
    # The value to resume with exactly: a rounded one would warn again.
    written_journal(path, make_samples(3), replace(HEADER, sensor_time_offsets=(1 / 30,)))
    opened, report = started(path, replace(HEADER, sensor_time_offsets=(0.0,)), resume=True)
    opened.close()
    assert [text for level, text in report.messages if level == 'warning'][0].endswith(
        f'or resume with sensor_time_offset_s:={1 / 30!r}')
    # Samples of two offsets: each named, no single value to resume with.
    written_journal(path, make_samples(3), replace(HEADER, sensor_time_offsets=(0.0, -0.03)))
    opened, report = started(path, replace(HEADER, sensor_time_offsets=(0.0,)), resume=True)
    opened.close()
    assert [text for level, text in report.messages if level == 'warning'] == [
        f'{path}: its 3 samples were paired with sensor_time_offset_s 0 then -0.03 (its first '
        'line); 0 applies to new poses only: the samples resumed keep their pairing. Call '
        '~/reset to take them again with 0']
    # An earlier version's journal does not say which offset: nothing to compare.
    written_journal(path, make_samples(3), HEADER)
    opened, report = started(path, replace(HEADER, sensor_time_offsets=(-0.03,)), resume=True)
    opened.close()
    assert [level for level, _ in report.messages] == ['info']
    assert journal.read_journal(path).header.sensor_time_offsets is None


def test_restart_takes_the_header_given(tmp_path):
    path = tmp_path / 'samples.csv'
    opened, _ = started(path, replace(HEADER, sensor_time_offsets=(0.0, -0.03)))
    opened.append(make_samples(1)[0])
    opened.restart(NOW, replace(HEADER, sensor_time_offsets=(-0.03,)))
    opened.close()
    assert journal.read_journal(path).header.sensor_time_offsets == (-0.03,)


def test_resume_without_a_journal_starts_one(tmp_path):
    opened, report = started(tmp_path / 'samples.csv', resume=True)
    opened.close()
    (level, text), = report.messages
    assert level == 'warning' and 'nothing to resume' in text
    assert journal.read_journal(tmp_path / 'samples.csv').header == HEADER


def test_moving_aside_never_overwrites(tmp_path):
    path = tmp_path / 'samples.csv'
    path.write_text('one')
    taken = journal.aside_path(path, 'previous', NOW)
    taken.write_text('older')
    moved = journal.move_aside(path, 'previous', NOW)
    assert moved != taken and moved.name == taken.name + '-2'
    assert taken.read_text() == 'older' and moved.read_text() == 'one'
    assert not path.exists()


def test_the_lock_file_goes_with_the_journal_that_held_it(tmp_path):
    """No empty .NAME.lock is left beside a journal closed (replay --journal-out left one)."""
    path = tmp_path / 'samples.csv'
    opened, _ = started(path)
    assert journal.lock_path(path).exists()
    opened.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['samples.csv']
    # A refused start lets go of its lock, and of its file.
    written_journal(path, make_samples(3), JournalHeader('eye_to_hand', 'base', 'camera'))
    with pytest.raises(JournalRefused, match='resume:=true refused'):
        started(path, resume=True)
    assert not journal.lock_path(path).exists()
    # Another's lock file stays while they hold it.
    first, _ = started(path, resume=False)
    with pytest.raises(JournalRefused, match='in use'):
        started(path, resume=True)
    assert journal.lock_path(path).exists()
    first.close()


def test_a_lock_taken_on_a_file_its_holder_removed_is_taken_again(tmp_path, monkeypatch):
    """
    The race of removing lock files.

    B opens the lock file, A removes it and lets go, B locks the removed file: B must lock
    the file at the path, or a third would lock a new one.
    """
    path = tmp_path / 'samples.csv'
    holder = journal.lock(path)
    real_flock, opened = journal.fcntl.flock, []

    def flock_after_release(fd, operation):
        if not opened:   # B has the old file open: A lets go, removing it
            opened.append(fd)
            journal.release_lock(path, holder)
        return real_flock(fd, operation)
    monkeypatch.setattr(journal.fcntl, 'flock', flock_after_release)
    taken = journal.lock(path)
    monkeypatch.undo()
    assert journal.lock_path(path).exists()
    assert os.fstat(taken).st_ino == os.stat(journal.lock_path(path)).st_ino
    with pytest.raises(JournalRefused, match='in use'):
        journal.lock(path)
    journal.release_lock(path, taken)
    assert not journal.lock_path(path).exists()


def test_a_directory_or_a_journal_in_use_is_refused(tmp_path):
    (tmp_path / 'dir').mkdir()
    with pytest.raises(JournalRefused, match='directory'):
        started(tmp_path / 'dir')
    opened, _ = started(tmp_path / 'samples.csv')
    with pytest.raises(JournalRefused, match='in use by another running calibrator'):
        started(tmp_path / 'samples.csv', resume=True)
    (tmp_path / 'link.csv').symlink_to(tmp_path / 'samples.csv')   # one journal, two names
    with pytest.raises(JournalRefused, match='in use by another running calibrator'):
        started(tmp_path / 'link.csv', resume=True)
    opened.append(make_samples(1)[0])
    opened.close()
    # Started through the link, the journal is the file it names: moved aside, re-created
    # and locked as such, the link kept (it had been replaced by a file of its own).
    through, report = started(tmp_path / 'link.csv')
    assert report.moved_to is not None and report.moved_to.parent == tmp_path
    assert through.path == tmp_path / 'samples.csv' and (tmp_path / 'link.csv').is_symlink()
    with pytest.raises(JournalRefused, match='in use by another running calibrator'):
        started(tmp_path / 'samples.csv', resume=True)
    through.restart(now=NOW)
    assert (tmp_path / 'link.csv').is_symlink()
    through.close()
    started(tmp_path / 'samples.csv', resume=True)[0].close()
    with pytest.raises(FileExistsError):
        journal.Journal.create(tmp_path / 'samples.csv', HEADER)


# --- while running ----------------------------------------------------------------------------

def test_restart_moves_the_old_journal_aside(tmp_path):
    samples = make_samples(4)
    path = tmp_path / 'samples.csv'
    opened, _ = started(path)
    for sample in samples[:3]:
        opened.append(sample)
    old = path.read_bytes()
    moved = opened.restart(now=NOW)
    assert moved.read_bytes() == old and moved.name.startswith('samples.csv.previous-')
    assert opened.count == 0 and journal.read_journal(path).samples == []
    opened.append(samples[3])
    assert opened.restart(now=NOW) is not None
    assert opened.restart(now=NOW) is None          # nothing to keep: no new file aside
    assert len(aside_files(tmp_path, 'previous')) == 2
    opened.close()


def test_set_header_keeps_the_sample_lines(tmp_path):
    samples = make_samples(3)
    path = tmp_path / 'samples.csv'
    opened, _ = started(path)
    for sample in samples[:2]:
        opened.append(sample)
    before = path.read_bytes()
    other = JournalHeader('eye_to_hand', 'base_link', 'camera')
    opened.set_header(other)
    opened.append(samples[2])
    opened.close()
    after = path.read_bytes()
    assert after.split(b'\n', 1)[1].startswith(before.split(b'\n', 1)[1])
    contents = journal.read_journal(path)
    assert contents.header == other
    assert_same_samples(contents.samples, samples)


def test_journal_rows_are_the_samples_csv_rows(tmp_path):
    samples = make_samples(3)
    path = tmp_path / 'samples.csv'
    data = written_journal(path, samples).decode()
    assert data.split('\n', 1)[1] == format_samples(samples, covariance_columns=True)


def test_sensor_covariances_survive_the_journal(tmp_path):
    """Samples from PoseWithCovarianceStamped keep their covariances through a restart."""
    rng = np.random.default_rng(4)
    cell = simulation.random_cell(rng)
    covariances = simulation.pnp_like_covariance()[None] * np.arange(1.0, 6.0)[:, None, None]
    samples, _ = simulation.samples(rng, cell, 5, sensor_covariance=covariances,
                                    report_covariance=True)
    path = tmp_path / 'samples.csv'
    written_journal(path, samples[:2] + make_samples(1) + samples[2:])
    read = journal.read_journal(path).samples
    assert read[2].sensor.covariance is None
    for got, sample in zip(read[:2] + read[3:], samples):
        np.testing.assert_array_equal(got.sensor.covariance, sample.sensor.covariance)


def test_a_journal_of_an_earlier_version_gains_the_covariance_columns_on_resume(tmp_path):
    """Its 15-column row made the reader drop the covariances of every sample appended."""
    from quatcal_ros.core.pose import Pose
    samples = make_samples(3)
    path = tmp_path / 'samples.csv'
    path.write_text(HEADER.line() + '\n' + format_samples(samples[:2], covariance_columns=False))
    opened, report = started(path, resume=True)
    assert any('gained the covariance columns' in text for _, text in report.messages)
    covariance = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    last = samples[2]
    opened.append(replace(last, sensor=Pose(last.sensor.position, last.sensor.quaternion,
                                            covariance)))
    opened.close()
    read = journal.read_journal(path).samples
    assert [s.sensor.covariance is None for s in read] == [True, True, False]
    np.testing.assert_allclose(read[2].sensor.covariance, covariance)
    assert_same_samples(read[:2], samples[:2])
    # A column row in another order (read by name) is left as it is, the rows with it.
    moved = tmp_path / 'moved.csv'
    text = format_samples(samples[:2], covariance_columns=False)
    columns, rows = text.split('\n', 1)
    names = columns.split(',')
    names[1], names[2] = names[2], names[1]
    rows = '\n'.join(','.join(f[:1] + [f[2], f[1]] + f[3:]) for f in
                     (row.split(',') for row in rows.strip().split('\n'))) + '\n'
    moved.write_text(HEADER.line() + '\n' + ','.join(names) + '\n' + rows)
    before = moved.read_text()
    opened, _ = started(moved, resume=True)
    assert moved.read_text() == before
    opened.set_header(JournalHeader('eye_in_hand', 'flange', 'camera'))   # its second line too
    opened.close()
    assert moved.read_text().split('\n', 1)[1] == before.split('\n', 1)[1]
    assert_same_samples(journal.read_journal(moved).samples, samples[:2])
