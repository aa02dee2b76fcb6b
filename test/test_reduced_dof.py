"""
Robots that cannot turn the link freely: simulated SCARA and gantry cells with known answers.

The rotation must come back within its uncertainty (and that uncertainty be honest over many
cells), the undetermined translation be named in the right frame and take the user's prior,
and the rest of the translation be recovered within its uncertainty.
"""

from dataclasses import replace
import json

import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.core.solver import DegenerateMotionError
from quatcal_ros.files.samples_csv import format_samples
from quatcal_ros.sim import simulation
from quatcal_ros.stream.settings import ConfigError, known_translation
from quatcal_ros.tools.cli import solve_main

CELLS = 40


def errors(result, cell):
    """Return (rotation error deg, error of the determined translation mm)."""
    rotation = np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))
    d = np.array([u['direction'] for u in result.unobservable])
    error = result.translation - cell.mounting.position
    return rotation, 1e3 * np.linalg.norm(error - d.T @ (d @ error))


@pytest.mark.parametrize('kind, setup', [('scara', 'eye_in_hand'), ('scara', 'eye_to_hand'),
                                         ('gantry', 'eye_in_hand'), ('gantry', 'eye_to_hand')])
def test_the_rotation_is_recovered_within_an_honest_uncertainty(kind, setup):
    ratios, translation_sigmas = [], []
    for seed in range(CELLS):
        rng = np.random.default_rng(seed)
        cell = simulation.random_cell(rng, setup)
        samples = simulation.reduced_dof_samples(rng, cell, 25, kind, 0.1, 0.001)
        result = calibrate(samples, CalibrationOptions(setup=setup))
        translation_sigmas.append(result.translation_uncertainty_mm)
        rotation, translation = errors(result, cell)
        ratios.append((rotation / result.uncertainty_deg,
                       translation / max(result.translation_uncertainty_mm, 1e-12)))
        assert result.method == 'refined' and result.validation['verdict'] == 'pass'
        # The directions are in the result's parent frame, and say which.
        assert {u['frame'] for u in result.unobservable} == {
            'link' if setup == 'eye_in_hand' else 'base'}
        # A gantry cannot turn: its hint asks for positions only.
        assert ('turns by different angles' in result.hint) == (kind == 'scara'), result.hint
    rms = np.sqrt(np.mean(np.square(ratios), axis=0))
    # Over 40 cells an honest uncertainty gives an RMS ratio of 1 +- about 0.11 (1 sigma of a
    # chi with 40 draws); [0.7, 1.3] leaves room for the small-sample sandwich.
    assert 0.7 < rms[0] < 1.3, rms
    if kind == 'scara':
        assert 0.7 < rms[1] < 1.3, rms
    else:
        # A gantry determines no translation: nothing is left to be uncertain about.
        assert max(translation_sigmas) == 0 and rms[1] == 0


@pytest.mark.parametrize('kind', ['scara', 'gantry'])
def test_a_link_that_wobbles_by_microradians_gives_the_same_answer(kind):
    # Real link orientations are never exactly about one axis. The start's translations once
    # came from a least squares over all six, which put up to 10^6 m along the undetermined
    # direction to fit a 1e-10 rad wobble: the answer then moved by 0.1-3 sigma.
    rng = np.random.default_rng(12)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 12, kind, 0.1, 0.001)
    exact = calibrate(samples)
    for size in (1e-10, 1e-6):
        wobble = [replace(s, link=replace(s.link, quaternion=quat.normalize(
            s.link.quaternion + size * rng.standard_normal(4)))) for s in samples]
        result = calibrate(wobble)
        moved = np.degrees(quat.angle_between(result.quaternion, exact.quaternion))
        assert moved < 1e-3 * exact.uncertainty_deg, (size, moved)
        assert np.linalg.norm(result.translation - exact.translation) < 1e-6 + 10 * size
        assert result.uncertainty_deg == pytest.approx(exact.uncertainty_deg, rel=1e-3)


@pytest.mark.parametrize('kind', ['scara', 'gantry'])
def test_three_samples_give_no_estimate_without_an_uncertainty(kind):
    # Each of three samples is essential to the fit: leaving one out, as the uncertainty does,
    # solved a singular system, and the reported uncertainty was rounding (0.9 deg to 2e6 deg
    # over 8 cells). Now an error says so, and a fourth sample gives an estimate.
    rng = np.random.default_rng(0)
    samples = simulation.reduced_dof_samples(rng, simulation.random_cell(rng), 8, kind, 0.1,
                                             0.001)
    with pytest.raises(ValueError, match='The translations can fix it, but with 3 samples the '
                                         'fit needs every one of them'):
        calibrate(samples[:3])
    result = calibrate(samples[:4])
    assert result.unobservable and 0.0 < result.uncertainty_deg < 10.0


def test_the_undetermined_direction_is_named_in_the_parent_frame():
    rng = np.random.default_rng(5)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 20, 'scara', 0.1, 0.001)
    result = calibrate(samples)
    (item,) = result.unobservable
    # The SCARA turns about base z; home's z axis seen in the link frame is the link's axis.
    expected = quat.matrix_from_quaternion(cell.home.quaternion).T @ [0.0, 0.0, 1.0]
    assert item['what'] == 'translation' and 'one axis' in item['reason']
    assert abs(np.dot(item['direction'], expected)) > 1 - 1e-9
    assert abs(np.dot(result.translation, item['direction'])) < 1e-12   # zero: no prior
    gantry = calibrate(simulation.reduced_dof_samples(rng, cell, 20, 'gantry', 0.1, 0.001))
    directions = np.array([u['direction'] for u in gantry.unobservable])
    np.testing.assert_allclose(directions @ directions.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(gantry.translation, 0.0, atol=1e-12)
    assert 'never turns' in gantry.warnings[0]


def test_the_known_translation_fills_only_the_undetermined_part():
    rng = np.random.default_rng(6)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 20, 'scara', 0.1, 0.001)
    without = calibrate(samples)
    known = tuple(cell.mounting.position + [0.3, -0.2, 0.0])   # right along z only
    given = calibrate(samples, CalibrationOptions(known_translation=known))
    d = np.array(given.unobservable[0]['direction'])
    assert np.dot(given.translation, d) == pytest.approx(np.dot(known, d), abs=1e-12)
    np.testing.assert_allclose(given.translation - np.dot(given.translation, d) * d,
                               without.translation - np.dot(without.translation, d) * d,
                               atol=1e-12)
    assert 'from known_translation' in given.warnings[0]
    assert not any('known_translation is not used' in w for w in given.warnings)
    assert np.linalg.norm(given.translation - cell.mounting.position) * 1e3 < \
        4 * given.translation_uncertainty_mm
    # A robot that turns its link freely determines all of it: the value given is unused,
    # which was not said.
    free, _ = simulation.samples(rng, cell, 20, 0.1, 0.001)
    used = calibrate(free, CalibrationOptions(known_translation=known))
    assert any(w.startswith('known_translation is not used: the motions determine the whole '
                            'translation') for w in used.warnings), used.warnings
    np.testing.assert_array_equal(used.translation, calibrate(free).translation)


@pytest.mark.parametrize('turn_deg', [1.0, 2.0])
def test_a_link_that_turns_a_little_is_held_at_the_known_translation(turn_deg):
    # A link turning a degree or two (under min_motion_deg: solved as a gantry) leaves the
    # translation only nearly undetermined; held at zero instead of the prior it misfits by
    # |t_X| times the turn: eye_to_hand (t_X about 1 m) gave a rotation error of 0.9-1.6 deg
    # RMS and 3.8-7.5 mm of fitted noise with the true translation given, 0.21 deg and
    # 0.97 mm now.
    errors_deg, noise_mm = [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        cell = simulation.random_cell(rng, 'eye_to_hand')
        samples = simulation.reduced_dof_samples(rng, cell, 20, 'scara', 0.1, 0.001,
                                                 turn_deg=turn_deg)
        result = calibrate(samples, CalibrationOptions(
            setup='eye_to_hand', known_translation=tuple(cell.mounting.position)))
        errors_deg.append(np.degrees(quat.angle_between(result.quaternion,
                                                        cell.mounting.quaternion)))
        noise_mm.append(result.translation_noise_mm)
    assert np.sqrt(np.mean(np.square(errors_deg))) < 0.3
    assert np.median(noise_mm) < 1.1


def test_an_arm_is_no_gantry_when_min_motion_deg_exceeds_its_turns():
    # min_motion_deg says which motions count; set above an arm's largest turn (43 deg) it
    # made the arm a gantry: 'the link never turns', translation zero, exit 0.
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 20, rotation_noise_deg=0.2,
                                    translation_noise_m=0.001)
    with pytest.raises(DegenerateMotionError, match=r'at least min_motion_deg \(90 deg\)'):
        calibrate(samples, CalibrationOptions(min_motion_deg=90.0))


def test_known_translation_setting_is_three_numbers():
    assert known_translation('') is None
    assert known_translation('0.1, -0.2 0.3') == (0.1, -0.2, 0.3)
    for bad in ('0.1 0.2', 'a b c', '1 2 nan'):
        with pytest.raises(ConfigError, match='known_translation'):
            known_translation(bad)


def test_solve_prints_the_unobservable_directions(tmp_path, capsys):
    rng = np.random.default_rng(8)
    cell = simulation.random_cell(rng)
    path = tmp_path / 'scara.csv'
    path.write_text(format_samples(simulation.reduced_dof_samples(rng, cell, 20, 'scara',
                                                                  0.1, 0.001)))
    assert solve_main([str(path), '--known-translation', '0 0 0.07']) == 0
    result = json.loads(capsys.readouterr().out)
    (item,) = result['unobservable']
    assert item['what'] == 'translation' and len(item['direction']) == 3
    assert result['translation']['z'] == pytest.approx(0.07, abs=1e-9)  # link z is the axis
    assert result['next_pose'] is None
    assert solve_main([str(path), '--known-translation', '0 0']) == 2
    assert 'known_translation' in capsys.readouterr().err


@pytest.mark.parametrize('options', [CalibrationOptions(invert_sensor=True),
                                     CalibrationOptions(setup='eye_to_hand')])
def test_a_wrong_convention_is_named_not_published_quietly(options):
    rng = np.random.default_rng(1)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 20, 'scara', 0.1, 0.001)
    assert not any('far better' in w for w in calibrate(samples).warnings)
    result = calibrate(samples, options)
    assert result.validation['verdict'] == 'fail'
    (warning,) = [w for w in result.warnings if 'far better' in w]
    assert 'far better with setup eye_in_hand and invert_sensor false' in warning
    # The fix names what to change, and only that.
    fix = ('drop --invert-sensor' if options.invert_sensor else '--setup eye_in_hand')
    assert fix in warning and ('--setup' in warning) == (options.setup != 'eye_in_hand')


def test_the_mirror_convention_fits_as_well_and_answers_with_the_object():
    # eye_in_hand and eye_to_hand with inverted sensor poses are the same equations with the
    # mounting and the object swapped (README, frames and conventions): no data can tell them.
    rng = np.random.default_rng(1)
    cell = simulation.random_cell(rng)
    samples = simulation.reduced_dof_samples(rng, cell, 20, 'scara', 0.1, 0.001)
    right = calibrate(samples)
    mirror = calibrate(samples, CalibrationOptions(setup='eye_to_hand', invert_sensor=True))
    # The same fit up to how the noise maps through the inverted poses (1.5x here): no warning
    # can fire on it, so the README says which answer to suspect.
    ratio = mirror.translation_noise_mm / right.translation_noise_mm
    assert 1 / 3 < ratio < 3 and mirror.validation['verdict'] == 'pass'
    object_in_base = cell.target.quaternion
    assert np.degrees(quat.angle_between(mirror.quaternion, object_in_base)) < 1.0
