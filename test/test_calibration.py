"""
Least squares, robustness and quality figures on synthetic cells with known answers.

Most tests here check the paper's method and its least-squares extension, so they ask for
method='closed-form' (CLOSED); the joint refinement is tested at the end with translation noise.
"""

import re
import warnings

import numpy as np
import pytest

from quatcal_ros.core import conventions, quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions, Calibrator
from quatcal_ros.core.leastsq import MotionSystem
from quatcal_ros.core.motions import Motions, pair_indices, SampleRotations
from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.core.solver import DegenerateMotionError
from quatcal_ros.sim import simulation


CLOSED = CalibrationOptions(method='closed-form')


def error_deg(result, cell):
    return np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))


def synthetic(seed, n, setup='eye_in_hand', **noise):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng, setup)
    samples, outliers = simulation.samples(rng, cell, n, **noise)
    return cell, samples, outliers


@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
@pytest.mark.parametrize('pairs', ['all', 'consecutive'])
def test_noise_free_cells_are_recovered_to_rounding(setup, pairs):
    for seed in range(20):
        cell, samples, _ = synthetic(seed, 8, setup)
        options = CalibrationOptions(setup=setup, pairs=pairs, method='closed-form')
        result = calibrate(samples, options)
        # float64 rounding through ~10 products and an eigen-solve: 1e-9 deg is ~1e-11 rad.
        assert error_deg(result, cell) < 1e-9
        assert result.inlier_samples == 8
        assert all('too small' in r['reason'] for r in result.rejected)


def test_noise_level_sets_the_error_and_the_uncertainty_is_honest():
    """RMS true error / RMS reported uncertainty within [0.7, 1.3] over 200 noisy cells."""
    errors, uncertainties = [], []
    for seed in range(200):
        noise = [0.1, 0.5, 1.0][seed % 3]
        cell, samples, _ = synthetic(1000 + seed, 10 + seed % 20, rotation_noise_deg=noise)
        result = calibrate(samples, CLOSED)
        errors.append(error_deg(result, cell))
        uncertainties.append(result.uncertainty_deg)
        # The noise estimate recovers the simulated per-axis noise (3N - 6 dof, N >= 10).
        assert 0.4 * noise < result.noise_deg < 1.8 * noise
    ratio = np.sqrt(np.mean(np.square(errors))) / np.sqrt(np.mean(np.square(uncertainties)))
    assert 0.7 <= ratio <= 1.3


def test_uncertainty_is_honest_for_consecutive_pairs_too():
    errors, uncertainties = [], []
    for seed in range(200):
        cell, samples, _ = synthetic(3000 + seed, 12, rotation_noise_deg=0.5)
        result = calibrate(samples, CalibrationOptions(pairs='consecutive', method='closed-form'))
        errors.append(error_deg(result, cell))
        uncertainties.append(result.uncertainty_deg)
    ratio = np.sqrt(np.mean(np.square(errors))) / np.sqrt(np.mean(np.square(uncertainties)))
    assert 0.7 <= ratio <= 1.3


def test_all_pairs_beat_consecutive_pairs():
    all_errors, consecutive_errors = [], []
    for seed in range(60):
        cell, samples, _ = synthetic(5000 + seed, 15, rotation_noise_deg=0.5)
        all_errors.append(error_deg(calibrate(samples, CLOSED), cell))
        consecutive_errors.append(error_deg(calibrate(samples, CalibrationOptions(
            pairs='consecutive', method='closed-form')), cell))
    assert np.median(all_errors) < np.median(consecutive_errors)


def test_flipped_marker_samples_are_rejected_as_samples():
    for seed in range(30):
        cell, samples, outliers = synthetic(7000 + seed, 30, rotation_noise_deg=0.5,
                                            outlier_fraction=0.1)
        result = calibrate(samples, CLOSED)
        rejected = sorted(r['sample'] for r in result.rejected if 'sample' in r)
        assert set(outliers) <= set(rejected)
        # chi-3 test at 99.9 %: a false alarm now and then, never a crowd of them.
        assert len(rejected) <= len(outliers) + 2
        clean = calibrate([s for i, s in enumerate(samples) if i not in outliers], CLOSED)
        assert error_deg(result, cell) < 3.0 * max(clean.uncertainty_deg, 0.05)
        assert all('marker flip' in r['reason'] for r in result.rejected if 'sample' in r)


@pytest.mark.parametrize('pairs', ['all', 'consecutive'])
def test_a_rejected_sample_counts_the_motions_it_takes_part_in(pairs):
    cell, samples, _ = synthetic(7003, 12, rotation_noise_deg=0.3)
    half_turn = quat.from_axis_angle([1.0, 0, 0], np.pi)   # a marker flip
    for k in (0, 6):   # the first sample has one neighbour, the others two
        bad = list(samples)
        sensor = samples[k].sensor
        flipped = Pose.create(sensor.position, quat.multiply(sensor.quaternion, half_turn))
        bad[k] = Sample(samples[k].stamp_ns, samples[k].link, flipped)
        result = calibrate(bad, CalibrationOptions(pairs=pairs))
        (entry,) = [r for r in result.rejected if 'sample' in r]
        assert entry['sample'] == k
        # every entry has contract 3's motion [i, j]: here one the sample takes part in
        assert entry['motion'] == ([0, 1] if k == 0 else [k - 1, k])
        spoiled = {'all': 'its 11 motions are not used',
                   'consecutive': 'its motion is not used' if k == 0 else
                   'its 2 motions are not used'}[pairs]
        assert entry['reason'].endswith(spoiled), entry['reason']


def test_a_motion_too_small_names_both_angles():
    cell, samples, _ = synthetic(7004, 10, rotation_noise_deg=0.1)
    # the sensor pose did not update between samples 4 and 5: only the link turned
    stale = [Sample(s.stamp_ns, s.link, samples[4].sensor) if k == 5 else s
             for k, s in enumerate(samples)]
    result = calibrate(stale, CalibrationOptions(pairs='consecutive', robust=False))
    (entry,) = [r for r in result.rejected if r.get('motion') == [4, 5]]
    assert re.fullmatch(r'too small to inform: the link rotates [0-9.]+ deg, the sensor '
                        r'0\.00 deg \(minimum 5 deg\)', entry['reason']), entry['reason']


def test_flips_among_few_samples_are_rejected_though_they_pull_the_mean():
    # Two 60-80 deg flips among ten samples pull the plain mean of the object orientations
    # 13 deg: about it every good sample lies 13 deg off, and a noise fitted to that explained
    # the flips (18 of these 60 cells kept one: 37 deg RMS residual, "not a rigid mounting").
    options = CalibrationOptions(setup='eye_to_hand')
    covariance = simulation.pnp_like_covariance()
    for seed in range(20000, 20060):
        rng = np.random.default_rng(seed)
        cell = simulation.random_cell(rng, 'eye_to_hand')
        samples, outliers = simulation.samples(rng, cell, 10, outlier_fraction=0.15,
                                               sensor_covariance=covariance)
        result = calibrate(samples, options)
        assert sorted(r['sample'] for r in result.rejected if 'sample' in r) == outliers
        assert not result.warnings and result.validation['verdict'] == 'pass'


@pytest.mark.parametrize('fraction', [0.0, 0.1, 0.3, 0.4])
def test_the_consensus_search_is_skipped_only_where_it_would_change_nothing(
        fraction, monkeypatch):
    # Clean samples (motion angles that agree, no bad detection about the least squares of
    # them all) skip the consensus search and its second round: the same answer either way.
    from quatcal_ros.core import calibration
    screen, consensus = calibration._screen, calibration._consensus
    searches = []

    def search_always(motions, options):
        usable, limit, _ = screen(motions, options)
        return usable, limit, False

    def counted(*args):
        searches.append(1)
        return consensus(*args)
    monkeypatch.setattr(calibration, '_consensus', counted)
    for n in (6, 10, 25):
        for seed in range(4):
            _, samples, outliers = synthetic(7100 + seed, n, rotation_noise_deg=0.5,
                                             translation_noise_m=0.001,
                                             outlier_fraction=fraction)
            searches.clear()
            skipped = calibrate(samples)
            searched_too = bool(searches)
            with monkeypatch.context() as patch:
                patch.setattr(calibration, '_screen', search_always)
                searched = calibrate(samples)
            assert skipped.to_json_dict() == searched.to_json_dict()
            # Searched whenever a sample is rejected; never for clean samples.
            assert searched_too == bool(outliers) or (outliers and not skipped.rejected)


@pytest.mark.parametrize('n', [3, 12, 70])
def test_pairs_screened_from_their_angles_alone_equal_the_screened_motions(n):
    # calibration._pair_screen takes every pair's rotation angles from two N x N products of
    # the quaternions instead of forming the motions: the same usable count and verdict.
    from quatcal_ros.core import calibration
    for fraction in (0.0, 0.2):
        _, samples, _ = synthetic(7300 + n, n, rotation_noise_deg=0.5,
                                  outlier_fraction=fraction)
        rotations = SampleRotations.from_samples(samples)
        options = CalibrationOptions()
        screen = calibration._pair_screen(rotations, options)
        motions = Motions.between(rotations, *calibration._candidate_pairs(n, options))
        usable, _, consistent = calibration._screen(motions, options)
        assert len(screen) == usable.sum() and screen.consistent == consistent
        assert consistent == (fraction == 0.0) or n == 3


def test_without_robustness_outliers_spoil_the_estimate():
    cell, samples, outliers = synthetic(8000, 30, rotation_noise_deg=0.5, outlier_fraction=0.1)
    assert outliers
    plain = calibrate(samples, CalibrationOptions(robust=False, method='closed-form'))
    robust = calibrate(samples, CLOSED)
    assert error_deg(plain, cell) > 5.0 * error_deg(robust, cell)


def test_a_refinement_that_diverges_in_translation_is_not_published(monkeypatch):
    # --no-robust on 6 samples with a flipped marker: the refinement once landed at 4e7 m
    # (a repeatability sweep found it) and was published, flagged only as not rigid. Such a
    # divergence, made here on purpose, leaves the closed form published.
    from dataclasses import replace

    from quatcal_ros.core import calibration
    real_refine = calibration.refine

    def diverging(*args, **kwargs):
        refined = real_refine(*args, **kwargs)
        return replace(refined, translation=refined.translation + 4e7)
    monkeypatch.setattr(calibration, 'refine', diverging)
    rng = np.random.default_rng(11376)
    samples = simulation.samples(rng, simulation.random_cell(rng), 6, rotation_noise_deg=0.3,
                                 translation_noise_m=0.002, outlier_fraction=0.1)[0]
    result = calibrate(samples, CalibrationOptions(robust=False))
    assert result.method == 'closed-form'
    assert np.linalg.norm(result.translation) < 10.0
    assert any('did not converge to a plausible answer' in w for w in result.warnings)
    assert any('do not fit a rigid mounting' in w for w in result.warnings)


@pytest.mark.parametrize('field, value, choices', [
    ('method', 'refine', 'refined, closed-form'),
    ('setup', 'eye-in-hand', 'eye_in_hand, eye_to_hand'),
    ('pairs', 'consecutives', 'all, consecutive')])
def test_options_refuse_unknown_choices_and_name_them(field, value, choices):
    with pytest.raises(ValueError) as error:
        CalibrationOptions(**{field: value})
    assert str(error.value) == f'{field} must be one of {choices}, not {value!r}'


def test_same_data_give_the_same_answer():
    _, samples, _ = synthetic(9000, 25, rotation_noise_deg=1.0, outlier_fraction=0.1)
    first = calibrate(samples).to_json_dict()
    assert all(calibrate(samples).to_json_dict() == first for _ in range(3))


def test_motions_about_one_axis_are_solved_from_the_translations_and_the_rest_named():
    rng = np.random.default_rng(1)
    cell = simulation.random_cell(rng)
    axis = np.array([0.0, 0.0, 1.0])
    samples = []
    for k, angle in enumerate([0, 20, 45, 70, 100]):
        turn = quat.from_axis_angle(axis, np.radians(angle))
        link = cell.home @ Pose.create([0.01 * k, 0, 0], turn)
        samples.append(Sample(k, link, cell.sensor_pose(link)))
    result = calibrate(samples)   # noise-free: the rotation exactly, Case 1 or not
    assert np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion)) < 1e-6
    (unobservable,) = result.unobservable
    np.testing.assert_allclose(np.abs(unobservable['direction']), axis, atol=1e-9)
    assert 'one axis only' in result.warnings[0] and 'set to zero' in result.warnings[0]
    # Parallel axes and no translation at all: nothing fixes the rotation about the axis.
    turned = [Sample(k, cell.home @ Pose.create([0, 0, 0], quat.from_axis_angle(
        axis, np.radians(a))), None) for k, a in enumerate([0, 20, 45, 70])]
    turned = [Sample(s.stamp_ns, s.link, cell.sensor_pose(s.link)) for s in turned]
    with pytest.raises(DegenerateMotionError, match=r'Case 1.*link z.*perpendicular'):
        calibrate(turned)


def test_eye_to_hand_names_the_base_axis_and_asks_to_turn_the_link():
    # The motions' axes are in the base frame there, whether the link turns about a base axis
    # or about one of its own (link x lies along base z here); the base itself never turns.
    camera = Pose.create([1.0, 0.2, 0.8], quat.from_axis_angle([1.0, 0, 0], np.radians(150)))
    marker = Pose.create([0.0, 0.05, 0.1], quat.from_axis_angle([0, 1.0, 0], np.radians(30)))
    start = Pose.create([0.5, 0.1, 0.4], quat.from_axis_angle([0, 1.0, 0], np.radians(90)))

    def turn(axis, angle):
        return Pose.create([0, 0, 0], quat.from_axis_angle(axis, np.radians(angle)))

    for turned in (lambda a: turn([0, 0, 1.0], a) @ start,    # about base z
                   lambda a: start @ turn([1.0, 0, 0], a)):   # about link x
        links = [turned(angle) for angle in (0, 20, 45, 70)]
        samples = [Sample(k, link, camera.inverse() @ link @ marker)
                   for k, link in enumerate(links)]
        with pytest.raises(DegenerateMotionError,   # 4 samples: 6 motions, all pairs
                           match=r'Case 1: all 6 usable motions .*base z.*rotate the link '
                                 r'about axes perpendicular to '
                                 r'it, e.g. tilt about base x or base y'):
            calibrate(samples, CalibrationOptions(setup='eye_to_hand'))


def test_too_few_samples_and_no_motion_are_refused():
    cell, samples, _ = synthetic(2, 5)
    with pytest.raises(DegenerateMotionError, match='at least 3'):
        calibrate(samples[:2])
    still = [Sample(k, samples[0].link, samples[0].sensor) for k in range(5)]
    with pytest.raises(DegenerateMotionError, match='usable motion'):
        calibrate(still)


def test_calibrator_estimates_from_the_first_two_non_parallel_motions():
    cell, samples, _ = synthetic(4, 6, rotation_noise_deg=0.1)
    calibrator = Calibrator()
    calibrator.add_sample(samples[0])
    calibrator.estimate()
    assert calibrator.result is None
    calibrator.add_sample(samples[1])
    calibrator.estimate()
    assert calibrator.result is None and 'at least 3' in calibrator.last_error
    calibrator.add_sample(samples[2])
    assert calibrator.estimate() == [] and calibrator.result.samples == 3
    # Three samples fit every setup and invert_sensor alike: said (a wrong one gave a plausible
    # answer metres off, with no word); from the fourth on, in the warm solves too, checked.
    assert calibrator.result.warnings == [
        'frame convention: not checked yet: 3 samples fit every setup and invert_sensor alike; '
        'from 4 samples on a wrong one is named']
    for sample in samples[3:]:
        calibrator.add_sample(sample)
        calibrator.estimate()
        assert calibrator.result.warnings == [], calibrator.result.warnings
    assert error_deg(calibrator.result, cell) < 3 * calibrator.result.uncertainty_deg + 0.01
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    assert conventions.unchecked(calibrate(inverted[:3]).warnings)
    named = calibrate(inverted[:4]).warnings
    assert named[0].startswith('frame convention: the samples fit badly as configured') and \
        'invert_sensor' in named[0], named
    calibrator.reset()
    assert calibrator.result is None and calibrator.samples == []


@pytest.mark.parametrize('options', [CalibrationOptions(robust=False),
                                     CalibrationOptions(pairs='consecutive', robust=False)])
def test_the_live_pattern_without_robustness_estimates_between_full_solves_too(options):
    # Between full solves the calibrator warm-starts from its last estimate: --no-robust
    # recomputes the least squares there (no bad-detection round to skip).
    cell, samples, _ = synthetic(14, 24, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(options)
    for k, sample in enumerate(samples):
        calibrator.add_sample(sample)
        messages = calibrator.estimate()
        assert messages == [] or k < 2, messages
    result = calibrator.result
    assert result.samples == 24
    assert error_deg(result, cell) < 3 * result.uncertainty_deg + 0.01
    full = calibrate(samples, options)
    assert np.degrees(quat.angle_between(result.quaternion, full.quaternion)) < \
        0.5 * full.uncertainty_deg


def test_the_consensus_mean_is_not_pulled_by_a_half_turn_of_the_first_sample():
    # A marker flipped by half a turn gives an object orientation orthogonal to the others
    # (as quaternions): the hypotheses' scoring must not start its mean there.
    from quatcal_ros.core import calibration
    for n in (6, 10, 20):
        cell, samples, _ = synthetic(7400 + n, n, rotation_noise_deg=0.2)
        first = samples[0]
        turn = quat.from_axis_angle([0.0, 0.0, 1.0], np.pi)
        samples[0] = Sample(first.stamp_ns, first.link,
                            Pose(first.sensor.position, quat.multiply(turn,
                                                                      first.sensor.quaternion)))
        rotations = SampleRotations.from_samples(samples)
        Z = rotations.object_orientations(cell.mounting.quaternion)[None]
        spread = calibration._spread(Z)[0]
        assert np.median(spread) < 1e-4 and spread[0] > 0.9


def test_inverted_sensor_convention_is_detected_and_named():
    cell, samples, _ = synthetic(5, 15, rotation_noise_deg=0.2)
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    result = calibrate(inverted, CalibrationOptions(robust=False))
    assert any('--invert-sensor' in w for w in result.warnings)
    fixed = calibrate(inverted, CalibrationOptions(invert_sensor=True))
    assert not fixed.warnings
    assert error_deg(fixed, cell) < 3 * fixed.uncertainty_deg + 0.01


@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
@pytest.mark.parametrize('which', ['link', 'sensor'])
def test_quaternions_in_the_wrong_component_order_are_named(setup, which):
    # (w, x, y, z) written where (x, y, z, w) is read: the warning advised another setup, and
    # following it left a 114 deg error.
    cell, samples, _ = synthetic(4, 15, setup, rotation_noise_deg=0.2)

    def misread(pose):   # the columns qx, qy, qz, qw holding w, x, y, z
        return Pose(pose.position, np.roll(pose.quaternion, 1))
    given = [Sample(s.stamp_ns, misread(s.link) if which == 'link' else s.link,
                    misread(s.sensor) if which == 'sensor' else s.sensor) for s in samples]
    result = calibrate(given, CalibrationOptions(setup=setup))
    assert result.warnings[0].startswith(
        f'the {which} quaternions look to be written in (w, x, y, z) order where (x, y, z, w) '
        'is read: reordered, the samples fit well ('), result.warnings
    assert not any('--setup' in w or '--invert-sensor' in w for w in result.warnings)
    assert 'write each quaternion as x, y, z, w (the columns qx, qy, qz, qw' in result.warnings[0]
    assert not any('quaternions look' in w for w in calibrate(
        samples, CalibrationOptions(setup=setup)).warnings)


@pytest.mark.parametrize('mistake', ['inverted', 'other setup'])
def test_the_fix_named_is_not_the_mirror_convention(mistake):
    # eye_in_hand with inverted sensor poses is eye_to_hand with mounting and object swapped:
    # with small rotations the quick fits scored the two alike, and 17 and 20 of 150 cells
    # named the mirror, whose answer is the object's pose (of these 40: 3 and 4 did).
    # The refinement of each decides.
    right_fixes = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        setup = 'eye_to_hand' if mistake == 'other setup' else 'eye_in_hand'
        cell = simulation.random_cell(rng, setup)
        samples = simulation.samples(rng, cell, 15, rotation_noise_deg=0.2,
                                     translation_noise_m=0.001, rotation_spread_deg=5.0)[0]
        if mistake == 'inverted':
            samples = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
        said = ' '.join(calibrate(samples).warnings)
        if 'frame convention' not in said:
            continue
        named = said.split('. Its mirror image')[0]   # the fix it names first
        if mistake == 'inverted':
            assert '--invert-sensor' in named and '--setup' not in named, seed
        else:
            assert '--setup eye_to_hand' in named and '--invert-sensor' not in named, seed
        right_fixes += 1
    assert right_fixes >= 38


def test_exchanged_link_and_sensor_poses_are_named_though_they_fit():
    # L X S = O exchanged is S X' L = O': the same residuals, and the answer the object's
    # pose (O^-1). On these cells the mountings are 0.05-0.15 m long, and exchanged 0.25-1.63 m:
    # all named but one, whose object is 0.25 m from the base (below LONG_MOUNTING_M).
    named = 0
    for seed in range(20):
        _, samples, _ = synthetic(seed, 12, rotation_noise_deg=0.2, translation_noise_m=0.001)
        right = calibrate(samples)
        assert not any('look exchanged' in w for w in right.warnings), seed
        exchanged = calibrate([Sample(s.stamp_ns, s.sensor, s.link) for s in samples])
        assert exchanged.residual_rms_deg == pytest.approx(right.residual_rms_deg, rel=1e-3)
        said = [w for w in exchanged.warnings if 'look exchanged' in w]
        length = np.linalg.norm(exchanged.translation)
        assert bool(said) == (length > 0.25), (seed, length)
        if said:
            named += 1
            assert said[0].startswith(f'the mounting comes out {length:.2f} m long while the '
                                      'observed object is only'), said
            assert 'Are the link and sensor poses swapped' in said[0]
    assert named == 19


def test_a_convention_warning_stands_through_the_warm_solves():
    # The live calibrator's estimates between full solves re-fit no convention: the warning
    # of the last full solve stood only in it, and came and went on /diagnostics.
    cell, samples, _ = synthetic(5, 16, rotation_noise_deg=0.2)
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    calibrator = Calibrator(CalibrationOptions(robust=False))
    calibrator.add_samples(inverted[:13])
    calibrator.estimate()   # a full solve
    (said,) = [w for w in calibrator.result.warnings if w.startswith('frame convention')]
    for sample in inverted[13:]:   # warm solves (14 and 15 of every 10th)
        calibrator.add_sample(sample)
        calibrator.estimate()
        assert said in calibrator.result.warnings


def test_with_the_noise_in_the_robot_poses_the_right_fix_is_still_named():
    # The refinement tells a convention from its mirror by the sensor noise each leaves, which
    # assumes the noise is the sensor's. With the robot's poses noisy instead, it prefers the
    # mirror (12 of 12 cells here): the warning then names the right fix beside it.
    for seed in range(100, 106):
        cell, samples, _ = synthetic(seed, 15, link_rotation_noise_deg=0.05,
                                     link_translation_noise_m=0.0002)
        result = calibrate(samples, CalibrationOptions(invert_sensor=True))
        (said,) = [w for w in result.warnings if w.startswith('frame convention')]
        assert 'drop --invert-sensor' in said, said
        # The mirror's fit is said in one form (it alternated between a noise ratio alone
        # and the fit alone as samples came), the ratio beside it when it was refined.
        assert re.search(r'Its mirror image, [a-z_ ]+, also fits \(\d\.\d\d deg, '
                         r'\d+\.\d mm(; its refined noise \d\.\dx as large)?\)', said), said
        # The mirror's fix is said as a clause, not in parentheses around parentheses.
        assert 'may be the right one instead: then ' in said, said


def test_inverted_sensor_poses_with_bad_detections_are_still_named():
    # The main fit screens bad detections, the quick fits of the other conventions do not:
    # the configured convention is compared with them by the same quick fit.
    rng = np.random.default_rng(10)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 10, rotation_noise_deg=0.2,
                                 translation_noise_m=0.001, outlier_fraction=0.15)[0]
    inverted = [Sample(s.stamp_ns, s.link, s.sensor.inverse()) for s in samples]
    assert any('--invert-sensor' in w for w in calibrate(inverted).warnings)


def test_wrong_setup_is_detected_and_named():
    cell, samples, _ = synthetic(6, 15, 'eye_to_hand', rotation_noise_deg=0.2)
    try:
        said = ' '.join(calibrate(samples).warnings)
    except DegenerateMotionError as error:
        said = str(error)
    # Rotations alone cannot tell the other setup from inverted sensor poses; the
    # translations can, so the right fix is the one named (its mirror image only beside it).
    named = said.split('. Its mirror image')[0]
    assert '--setup eye_to_hand' in named and '--invert-sensor' not in named
    right = calibrate(samples, CalibrationOptions(setup='eye_to_hand'))
    assert not right.warnings
    assert error_deg(right, cell) < 3 * right.uncertainty_deg + 0.01


def test_hint_names_the_least_excited_axis():
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    samples = []
    # Rotations about link x and, slightly, link y: the rotation about link z is least known.
    for k, (ax, ay) in enumerate([(0, 0), (30, 0), (-30, 0), (0, 4), (20, -4), (-10, 3)]):
        rot = quat.multiply(quat.from_axis_angle([1, 0, 0], np.radians(ax)),
                            quat.from_axis_angle([0, 1, 0], np.radians(ay)))
        link = cell.home @ Pose.create([0.01 * k, 0.0, 0.0], rot)
        samples.append(Sample(k, link, cell.sensor_pose(link)))
    result = calibrate(samples, CalibrationOptions(min_motion_deg=2.0))
    assert 'link z' in result.hint and result.excitation < 0.2


def test_contract_3_json_keys():
    _, samples, _ = synthetic(7, 10, rotation_noise_deg=0.3)
    out = calibrate(samples).to_json_dict()
    for key in ('rotation', 'matrix', 'samples', 'motions', 'inliers', 'residual_rms_deg',
                'uncertainty_deg', 'rejected', 'warnings'):
        assert key in out
    assert set(out['rotation']) == {'x', 'y', 'z', 'w'}
    assert out['samples'] == 10 and out['motions'] == 45


def test_incremental_least_squares_equals_batch():
    _, samples, _ = synthetic(8, 30, rotation_noise_deg=0.5)
    rotations = SampleRotations.from_samples(samples)
    motions = Motions.between(rotations, *pair_indices(30))
    batch = MotionSystem()
    batch.add(motions.q_a, motions.q_b)
    incremental = MotionSystem()
    for k in range(len(motions)):
        incremental.add(motions.q_a[k], motions.q_b[k])
    np.testing.assert_allclose(incremental.normal_matrix, batch.normal_matrix, atol=1e-9)
    assert quat.angle_between(incremental.solve()[0], batch.solve()[0]) < 1e-12


def test_incremental_updates_agree_with_the_full_solve_and_reject_flips():
    cell, samples, outliers = synthetic(10, 39, rotation_noise_deg=0.5, outlier_fraction=0.1)
    calibrator = Calibrator(full_solve_every=10, small=12)
    for k, sample in enumerate(samples):
        calibrator.add_sample(sample)
        calibrator.estimate()
        if k < 14 or calibrator.result is None:
            continue
        full = calibrate(samples[:k + 1])
        # Same data, same model: the two differ by the samples each path rejected, far less
        # than the uncertainty.
        assert quat.angle_between(calibrator.result.quaternion, full.quaternion) < np.radians(
            0.3 * full.uncertainty_deg)
    late = [i for i in outliers if i > 12 and (i + 1) % 10]
    assert late, 'the draw must put an outlier on the incremental path'
    rejected = {r['sample'] for r in calibrator.result.rejected if 'sample' in r}
    assert set(late) <= rejected


def test_refinement_is_honest_and_beats_the_closed_form_with_translations():
    """Rotation and translation: RMS true error / RMS reported within [0.7, 1.3]."""
    rows = {'rot': [], 'rot_unc': [], 'trans': [], 'trans_unc': [], 'closed': []}
    for seed in range(200):
        noise = [0.1, 0.5, 1.0][seed % 3]
        cell, samples, _ = synthetic(11000 + seed, 10 + seed % 20, rotation_noise_deg=noise,
                                     translation_noise_m=0.001)
        result = calibrate(samples)
        assert result.method == 'refined' and result.refined is not None
        rows['rot'].append(error_deg(result, cell))
        rows['rot_unc'].append(result.uncertainty_deg)
        rows['trans'].append(1e3 * np.linalg.norm(result.translation - cell.mounting.position))
        rows['trans_unc'].append(result.translation_uncertainty_mm)
        rows['closed'].append(np.degrees(quat.angle_between(result.closed_form.quaternion,
                                                            cell.mounting.quaternion)))
    rms = {key: np.sqrt(np.mean(np.square(values))) for key, values in rows.items()}
    assert 0.7 <= rms['rot'] / rms['rot_unc'] <= 1.3
    assert 0.7 <= rms['trans'] / rms['trans_unc'] <= 1.3
    assert np.median(rows['rot']) < 0.7 * np.median(rows['closed'])


def test_closed_form_translation_is_honest():
    errors, uncertainties = [], []
    for seed in range(200):
        cell, samples, _ = synthetic(12000 + seed, 10 + seed % 20, rotation_noise_deg=0.5,
                                     translation_noise_m=0.001)
        result = calibrate(samples, CLOSED)
        errors.append(1e3 * np.linalg.norm(result.translation - cell.mounting.position))
        uncertainties.append(result.translation_uncertainty_mm)
    ratio = np.sqrt(np.mean(np.square(errors))) / np.sqrt(np.mean(np.square(uncertainties)))
    assert 0.7 <= ratio <= 1.3


@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
def test_noise_free_translation_is_exact(setup):
    for seed in range(10):
        cell, samples, _ = synthetic(seed, 8, setup)
        for method in ('closed-form', 'refined'):
            result = calibrate(samples, CalibrationOptions(setup=setup, method=method))
            # Rounding only: positions of ~1 m through a few products and solves.
            np.testing.assert_allclose(result.translation, cell.mounting.position, atol=1e-9)
            assert error_deg(result, cell) < 1e-7


@pytest.mark.parametrize('options, words', [
    ({'min_motion_deg': float('nan')}, 'min_motion_deg must lie in'),
    ({'min_motion_deg': 0.0}, 'min_motion_deg must lie in'),
    ({'max_angle_mismatch_deg': -1.0}, 'max_angle_mismatch_deg must lie in'),
    ({'hypotheses': 0}, 'hypotheses must be a whole number'),
    ({'known_translation': (0.0, 0.0)}, 'three numbers'),
    ({'known_translation': (float('nan'), 0.0, 0.0)}, 'three numbers'),
    ({'known_translation': (1e9, 0.0, 0.0)}, 'not a position in a robot cell'),
])
def test_options_out_of_range_are_refused_by_name(options, words):
    """The Python entry point: NaN had raised an IndexError, (0, 0) a matmul shape error."""
    with pytest.raises(ValueError, match=words):
        CalibrationOptions(**options)


def test_a_robust_fit_no_rigid_mounting_leaves_is_not_told_to_screen_detections():
    # Two samples in three with random sensor orientations: the screening of bad detections
    # ran and could not help; the warning told the user not to turn off what was on.
    rng = np.random.default_rng(0)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 12, rotation_noise_deg=0.3,
                                 translation_noise_m=0.001)[0]
    spoiled = [Sample(s.stamp_ns, s.link, Pose(s.sensor.position,
                                               quat.normalize(rng.normal(size=4))))
               if k % 3 else s for k, s in enumerate(samples)]
    (said,) = [w for w in calibrate(spoiled).warnings
               if w.startswith('the samples do not fit a rigid mounting')]
    assert 'that most detections are good' in said and '--no-robust' not in said, said


def test_a_sample_that_knows_nothing_leaves_the_reported_noise_as_it_was():
    # The noise of a typical sample was the mean of the samples' covariances: one sample
    # given a variance of 1 m^2 among millimetres made it 22 deg and 285 mm. Of the mean
    # information, it stays where the others put it; the estimate is nearly theirs.
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 12, rotation_noise_deg=0.2,
                                 translation_noise_m=0.001)[0]
    given = np.diag([1e-6] * 3 + [1e-5] * 3)   # ROS order: position first
    unsure = calibrate([Sample(s.stamp_ns, s.link, Pose(
        s.sensor.position, s.sensor.quaternion, np.eye(6) if k == 7 else given))
        for k, s in enumerate(samples)])
    without = calibrate([Sample(s.stamp_ns, s.link,
                                Pose(s.sensor.position, s.sensor.quaternion, given))
                         for k, s in enumerate(samples) if k != 7])
    assert unsure.noise_model['sample_covariances'] == 'input'
    # (the rotation stage before the refinement weighs every sample alike)
    assert quat.angle_between(without.quaternion, unsure.quaternion) < 0.2 * np.radians(
        without.uncertainty_deg)
    assert 0.9 < unsure.noise_deg / without.noise_deg < 1.1
    assert 0.9 < unsure.translation_noise_mm / without.translation_noise_mm < 1.1
    assert 0.1 < without.noise_deg < 0.4 and 0.5 < without.translation_noise_mm < 2.0


@pytest.mark.parametrize('scale', [1e-8, 1e6])
def test_covariances_given_in_any_unit_weigh_and_report_alike(scale):
    # Only the covariances' ratios weigh the samples; the refinement fits their common scale
    # (its noise floors, 1e-6 in the units of the covariances, stay far below the noise).
    rng = np.random.default_rng(5)
    cell = simulation.random_cell(rng)
    covariances = simulation.pnp_like_covariance()[None] * np.linspace(1.0, 4.0, 12)[:, None, None]
    samples = simulation.samples(rng, cell, 12, sensor_covariance=covariances,
                                 report_covariance=True)[0]
    plain = calibrate(samples)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        scaled = calibrate([Sample(s.stamp_ns, s.link, Pose(
            s.sensor.position, s.sensor.quaternion, s.sensor.covariance * scale))
            for s in samples])
    assert quat.angle_between(plain.quaternion, scaled.quaternion) < 1e-9
    for name in ('noise_deg', 'translation_noise_mm', 'uncertainty_deg',
                 'translation_uncertainty_mm'):
        assert getattr(scaled, name) == pytest.approx(getattr(plain, name), rel=1e-6), name
