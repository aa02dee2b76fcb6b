"""Tests of quatcal_ros.files.persistence: atomic writes and the result YAML."""

import os
from types import SimpleNamespace

import numpy as np
from numpy.testing import assert_allclose
import pytest
from quatcal_ros.core import calibration
from quatcal_ros.core import quaternion as quat
from quatcal_ros.files import persistence
from quatcal_ros.sim import simulation
import yaml


def _leftovers(directory, name):
    return [p for p in os.listdir(directory) if p != name]


def test_atomic_write_creates_directories_and_leaves_no_temporary(tmp_path):
    target = tmp_path / 'a' / 'b' / 'result.yaml'
    written = persistence.atomic_write_text(target, 'first\n')
    assert written == target
    assert target.read_text() == 'first\n'
    persistence.atomic_write_text(target, 'second\n')
    assert target.read_text() == 'second\n'
    assert _leftovers(target.parent, 'result.yaml') == []
    assert (target.stat().st_mode & 0o777) == 0o644


def test_atomic_write_expands_user(tmp_path, monkeypatch):
    monkeypatch.setenv('HOME', str(tmp_path))
    written = persistence.atomic_write_bytes('~/x/out.bin', b'\x00\x01')
    assert written == tmp_path / 'x' / 'out.bin'
    assert written.read_bytes() == b'\x00\x01'


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / 'result.yaml'
    target.write_text('old\n')

    def broken_replace(src, dst):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(persistence.os, 'replace', broken_replace)
    with pytest.raises(OSError, match='No space'):
        persistence.atomic_write_text(target, 'new\n')
    assert target.read_text() == 'old\n'
    assert _leftovers(tmp_path, 'result.yaml') == []


def test_write_is_synced_then_renamed_then_directory_synced(tmp_path, monkeypatch):
    calls = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(persistence.os, 'fsync',
                        lambda fd: calls.append('fsync') or real_fsync(fd))
    monkeypatch.setattr(persistence.os, 'replace',
                        lambda a, b: calls.append('replace') or real_replace(a, b))
    persistence.atomic_write_text(tmp_path / 'f.txt', 'x')
    assert calls == ['fsync', 'replace', 'fsync']


def test_a_link_is_followed_and_a_files_permissions_kept(tmp_path):
    # The link itself was replaced by a regular file (the real file never updated), and a
    # 0600 file became 0644.
    real = tmp_path / 'real' / 'result.yaml'
    real.parent.mkdir()
    real.write_text('old\n')
    real.chmod(0o600)
    link = tmp_path / 'result.yaml'
    link.symlink_to(real)
    assert persistence.atomic_write_text(link, 'new\n') == real
    assert link.is_symlink() and real.read_text() == 'new\n'
    assert (real.stat().st_mode & 0o777) == 0o600
    dangling = tmp_path / 'later.yaml'
    dangling.symlink_to(tmp_path / 'real' / 'later.yaml')
    persistence.atomic_write_text(dangling, 'x')
    assert dangling.is_symlink() and (tmp_path / 'real' / 'later.yaml').read_text() == 'x'


def test_created_directories_are_synced_too(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(persistence, '_fsync_directory', synced.append)
    persistence.atomic_write_text(tmp_path / 'a' / 'b' / 'f.txt', 'x')
    assert synced == [tmp_path / 'a' / 'b', tmp_path / 'a', tmp_path]


def test_unwritable_directory_raises_oserror(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    with pytest.raises(OSError):
        persistence.atomic_write_text(blocker / 'result.yaml', 'x')


@pytest.fixture(scope='module')
def real_result():
    rng = np.random.default_rng(11)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 8, rotation_noise_deg=0.05)
    return cell, calibration.calibrate(samples)


def test_result_yaml_round_trip(tmp_path, real_result):
    cell, result = real_result
    path = persistence.write_result_yaml(tmp_path / 'calib.yaml', result, 'tool0', 'camera')
    with open(path) as stream:
        document = yaml.safe_load(stream)
    assert document['parent_frame'] == 'tool0'
    assert document['child_frame'] == 'camera'
    assert document['setup'] == 'eye_in_hand'
    rotation = document['rotation']
    assert list(rotation) == ['x', 'y', 'z', 'w']
    q_xyzw = np.array([rotation[k] for k in 'xyzw'])
    assert_allclose(q_xyzw, quat.xyzw_from_wxyz(result.quaternion), atol=1e-12)
    assert np.degrees(quat.angle_between(quat.wxyz_from_xyzw(q_xyzw),
                                         cell.mounting.quaternion)) < 0.5
    assert_allclose(document['matrix'], result.matrix, atol=1e-12)
    quality = document['quality']
    assert quality['samples'] == 8 and isinstance(quality['samples'], int)
    assert quality['motions'] == result.motions
    assert quality['inliers'] == result.inliers
    assert quality['residual_rms_deg'] == pytest.approx(result.residual_rms_deg)
    assert quality['uncertainty_deg'] == pytest.approx(result.uncertainty_deg)
    assert document['hint'] == result.hint
    back = persistence.read_result_yaml(path)
    assert_allclose(back['quaternion_xyzw'], q_xyzw)
    # The URDF joint and the xacro macro as literal blocks: pasted as they read.
    from quatcal_ros.files import exports
    text = path.read_text()
    joint = exports.urdf_joint(result, 'tool0', 'camera')
    assert document['urdf'] == joint
    assert 'urdf: |\n' + ''.join(f'  {line}\n' for line in joint.splitlines()) in text
    assert 'xacro: |\n  <?xml' in text


def test_a_new_file_follows_the_umask_and_a_link_loop_is_an_os_error(tmp_path):
    """Files were always 0644 under umask 077; a link loop raised RuntimeError."""
    before = os.umask(0o077)
    try:
        persistence.atomic_write_text(tmp_path / 'private.yaml', 'x')
    finally:
        os.umask(before)
    assert (tmp_path / 'private.yaml').stat().st_mode & 0o777 == 0o600
    os.symlink(tmp_path / 'b', tmp_path / 'a')
    os.symlink(tmp_path / 'a', tmp_path / 'b')
    with pytest.raises(OSError, match='a loop of symbolic links; nothing was written'):
        persistence.atomic_write_text(tmp_path / 'a', 'x')


def test_a_write_below_a_file_or_a_dangling_link_is_an_os_error(tmp_path):
    (tmp_path / 'file').write_text('')
    os.symlink(tmp_path / 'gone', tmp_path / 'dangling')
    for parent in ('file', 'dangling'):
        with pytest.raises(OSError, match='a parent is a file, not a directory'):
            persistence.atomic_write_text(tmp_path / parent / 'x.yaml', 'x')


def test_result_yaml_writes_frames_beyond_ascii_as_themselves(tmp_path):
    """A frame named in the user's language reads as it is named, and reads back."""
    result = SimpleNamespace(
        quaternion=np.array([0.0, 0.0, 0.0, 1.0]), matrix=np.eye(3), samples=3, motions=3,
        inliers=3, residual_rms_deg=0.1, uncertainty_deg=0.2, hint='', warnings=[])
    text = persistence.format_result_yaml(result, 'poignet_é', 'caméra_前', 'eye_in_hand')
    assert 'caméra_前' in text and '\\u' not in text
    path = tmp_path / 'result.yaml'
    persistence.atomic_write_text(path, text)
    back = persistence.read_result_yaml(path)
    assert (back['parent_frame'], back['child_frame']) == ('poignet_é', 'caméra_前')


def test_result_yaml_plain_result_with_nan_and_extra(tmp_path):
    result = SimpleNamespace(
        quaternion=np.array([0.0, 0.0, 0.0, 1.0]), matrix=np.diag([-1.0, -1.0, 1.0]),
        samples=np.int64(3), motions=3, inliers=2, residual_rms_deg=float('nan'),
        uncertainty_deg=np.float64(0.25), hint='rotate about x', warnings=['careful'])
    text = persistence.format_result_yaml(result, 'base_link', 'camera', 'eye_to_hand',
                                          extra={'source': 'run.bag'})
    assert text.startswith('#')
    document = yaml.safe_load(text)
    assert document['rotation'] == {'x': 0.0, 'y': 0.0, 'z': 1.0, 'w': 0.0}
    assert document['quality']['residual_rms_deg'] is None
    assert document['quality']['uncertainty_deg'] == 0.25
    assert document['setup'] == 'eye_to_hand'
    assert document['warnings'] == ['careful']
    assert document['source'] == 'run.bag'


def test_read_result_yaml_refuses_other_files(tmp_path):
    path = tmp_path / 'other.yaml'
    path.write_text('a: 1\n')
    with pytest.raises(ValueError, match='other.yaml'):
        persistence.read_result_yaml(path)


def test_the_result_file_is_the_whole_mounting(tmp_path):
    rng = np.random.default_rng(11)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.1,
                                    translation_noise_m=0.001)
    result = calibration.calibrate(samples)
    path = persistence.write_result_yaml(tmp_path / 'r.yaml', result, 'tool0', 'camera')
    document = persistence.read_result_yaml(path)
    assert (document['format'], document['format_version']) == ('quatcal_ros/mounting', 2)
    assert document['method'] == 'refined'
    assert_allclose(document['translation_xyz'], result.translation, atol=1e-15)
    assert document['quality']['translation_uncertainty_mm'] == \
        result.translation_uncertainty_mm
    for name in ('closed_form', 'refined'):
        estimate = document['estimates'][name]
        assert estimate['uncertainty_deg'] > 0 and estimate['translation_uncertainty_mm'] > 0
        assert set(estimate['translation']) == set('xyz')
    # The validation verdict without the per-sample list (that is in the JSON), and the joint.
    validation = document['validation']
    assert validation['verdict'] == result.validation['verdict'] == 'pass'
    assert validation['thresholds'] == result.validation['thresholds']
    assert len(validation['worst']) == 3 and 'samples' not in validation
    assert '<parent link="tool0"/>' in document['urdf']
    assert '<child link="camera"/>' in document['urdf']
    assert 'xacro:macro' in document['xacro']


def test_version_1_files_still_read_and_unknown_versions_are_named(tmp_path):
    old = tmp_path / 'old.yaml'
    old.write_text('format: quatcal_ros/rotation\nformat_version: 1\nparent_frame: tool0\n'
                   'rotation: {x: 0.0, y: 0.0, z: 0.0, w: 1.0}\n')
    document = persistence.read_result_yaml(old)
    assert_allclose(document['quaternion_xyzw'], [0, 0, 0, 1])
    assert document['translation_xyz'] is None
    future = tmp_path / 'future.yaml'
    future.write_text('format: quatcal_ros/mounting\nformat_version: 9\n'
                      'rotation: {x: 0.0, y: 0.0, z: 0.0, w: 1.0}\n')
    with pytest.raises(ValueError, match='version 9 is not one this version reads'):
        persistence.read_result_yaml(future)
