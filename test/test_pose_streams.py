"""Pose-stream files (files/pose_streams.py) and their conversion to a bag (poses_to_bag)."""

import numpy as np
import pytest
from quatcal_ros.files.pose_streams import parse_pose_stream
from quatcal_ros.files.text_input import BadInputError


@pytest.mark.parametrize('header', ['"t","x","y","z","qx","qy","qz","qw"',
                                    'time (s),x,y,z,qx,qy,qz,qw', '%time,x,y,z,qx,qy,qz,qw',
                                    'nanoseconds x y z qx qy qz qw'])
def test_a_header_row_of_names_is_skipped_as_other_programs_write_them(header):
    # (quoted as R writes them, with units, a name that begins as 'nan' does)
    stamps, _, _ = parse_pose_stream(header + '\n1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,1\n', 'f.csv')
    assert len(stamps) == 2


def test_rows_of_commas_or_spaces_with_comments_and_a_header_are_read():
    text = ('# timestamp tx ty tz qx qy qz qw (a TUM trajectory)\n'
            '1.5 0.1 0.2 0.3 0 0 0 1\n'
            '\n'
            '1.75\t0.1 0.2 0.3   0 0 0.7071 0.7071\n')
    stamps, positions, quaternions = parse_pose_stream(text, 'tum.txt')
    assert stamps == [1_500_000_000, 1_750_000_000]
    np.testing.assert_array_equal(positions, [[0.1, 0.2, 0.3]] * 2)
    np.testing.assert_allclose(quaternions, [[1, 0, 0, 0], [np.sqrt(0.5), 0, 0, np.sqrt(0.5)]])
    # A row of names first, commas, the nanoseconds of a stamp kept exactly
    stamps, _, _ = parse_pose_stream('t,x,y,z,qx,qy,qz,qw\n1700000000.123456789, 0, 0, 0, 0, 0, '
                                     '0, 1\n', 'eth.csv')
    assert stamps == [1_700_000_000_123_456_789]


@pytest.mark.parametrize('text, expected', [
    ('', 'f.csv: no poses: expected rows of t x y z qx qy qz qw'),
    ('# only a comment\n', 'f.csv: no poses'),
    ('1,0,0,0,0,0,1\n', 'f.csv, row 1: 7 fields, expected 8: t x y z qx qy qz qw (seconds, '
                        'metres, a quaternion x y z w)'),
    ('inf,nan,nan,nan,nan,nan,nan,nan\n1,0,0,0,0,0,0,1\n',
     'row 1, field t: inf is not a finite number'),   # (no header)
    # A first row of numbers in another separator is no header: it was skipped as one.
    ('1;0;0;0;0;0;0;1\n2,0,0,0,0,0,0,1\n', 'f.csv, row 1: 1 fields, expected 8'),
    ('\u0661 0 0 0 0 0 0 1\n', "f.csv, row 1, field t: '\u0661' is not a number"),
    ('1,0,,0,0,0,0,1\n', "f.csv, row 1, field y: '' is not a number"),
    ('1,0,0,0,0,0,0,1\n2,0,0,nan,0,0,0,1\n', 'f.csv, row 2, field z: nan is not a finite number'),
    ('1,0,0,0,0,0,0,2\n', 'f.csv, row 1, fields qx..qw: the quaternion has norm 2, not 1 '
                          '(tolerance 0.01); quaternions are x, y, z, w'),
    ('1,0,0,5000,0,0,0,1\n', 'f.csv, row 1, fields x..z: [0.0, 0.0, 5000.0] m is not a position'),
    ('-1,0,0,0,0,0,0,1\n', 'f.csv, row 1, field t: -1 s is not a stamp (seconds, from 0)'),
    ('2,0,0,0,0,0,0,1\n1,0,0,0,0,0,0,1\n', "f.csv, row 2, field t: 1 s is not after row 1's 2 "
                                           's: the rows must be in time order, one pose a stamp'),
    ('1,0,0,0,0,0,0,1\n1.0,0,0,0,0,0,0,1\n', "row 2, field t: 1.0 s is not after row 1's 1 s"),
])
def test_a_bad_row_is_named_with_its_field(text, expected):
    with pytest.raises(BadInputError) as raised:
        parse_pose_stream(text, 'f.csv')
    assert expected in str(raised.value), raised.value


def test_poses_to_bag_names_what_is_wrong(tmp_path, capsys, monkeypatch):
    from quatcal_ros.tools.poses_to_bag import main
    good, bad = tmp_path / 'link.txt', tmp_path / 'camera.txt'
    good.write_text('1 0 0 0 0 0 0 1\n2 0 0 0.1 0 0 0 1\n')
    bad.write_text('1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n')
    assert main([str(good), str(bad), str(tmp_path / 'bag')]) == 2
    assert capsys.readouterr().err == (
        f'poses_to_bag: error: {bad}, row 2: 7 fields, expected 8: t x y z qx qy qz qw '
        '(seconds, metres, a quaternion x y z w)\n')
    assert sorted(tmp_path.iterdir()) == sorted([good, bad])   # no bag, no partial one
    assert main([str(good), str(good), str(tmp_path / 'bag'), '--sensor-topic',
                 '/link_pose']) == 2
    assert '--link-topic and --sensor-topic are both /link_pose' in capsys.readouterr().err
    assert main([str(good), str(tmp_path / 'none.txt'), str(tmp_path / 'bag')]) == 2
    assert 'none.txt' in capsys.readouterr().err
    # Written, with mcap too, in a folder made for it; its storage file named after it
    # (it kept the hidden name of the partial folder, which a copy of '*' lost).
    assert main([str(good), str(good), str(tmp_path / 'new' / 'bag'), '--storage', 'mcap',
                 '--link-topic', 'robot/pose']) == 0
    assert sorted(p.name for p in (tmp_path / 'new' / 'bag').iterdir()) == [
        'bag.mcap', 'metadata.yaml']
    assert [p.name for p in (tmp_path / 'new').iterdir()] == ['bag']   # no partial left
    # The topic written absolute, as rosbag2's are.
    assert capsys.readouterr().out.startswith(f'{tmp_path / "new" / "bag"}: 2 link poses on '
                                              '/robot/pose, 2 sensor poses on /sensor_pose')
    # A write that fails leaves no partial folder behind.
    from quatcal_ros.ros import bag

    def full_disk(path, *args):
        (path / 'half.db3').parent.mkdir(parents=True)
        (path / 'half.db3').write_text('x')
        raise OSError(28, 'No space left on device')
    monkeypatch.setattr(bag, 'write_bag', full_disk)
    capsys.readouterr()
    assert main([str(good), str(good), str(tmp_path / 'full' / 'bag')]) == 2
    assert capsys.readouterr().err == (f'poses_to_bag: error: {tmp_path / "full" / "bag"}: '
                                       'cannot write: [Errno 28] No space left on device\n')
    assert list((tmp_path / 'full').iterdir()) == []
