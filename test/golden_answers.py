"""
The golden answers: recorded estimates the estimator is held to (test_golden.py).

A case is a set of samples and CalibrationOptions; its answer is what `summary` keeps of the
CalibrationResult (or of the error), or of a live calibrator's estimates at some sample
counts. `differences` compares two answers: decisions exactly (which samples were rejected
or called noisy, the method published, the validation verdict, the kinds of warning, the
noise model's distribution and shape), estimates within ANSWER_SIGMAS of their own
uncertainty, uncertainties and noise levels within RELATIVE_TOLERANCE.

Why these tolerances: the refinement stops when a step is below 0.01 of a sigma
(refine.STEP_TOLERANCE), so arithmetic that rounds differently on another machine (another
BLAS kernel, another summation order) can at most move the stopping point by about that;
a change of the estimator itself moves answers by more, or changes a decision.
"""

from dataclasses import asdict
import json
import math
from pathlib import Path

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions, Calibrator, \
    Thresholds
from quatcal_ros.files.samples_csv import format_samples, parse_samples

ANSWERS = Path(__file__).resolve().parent / 'golden' / 'answers.json'
ANSWER_SIGMAS = 0.02
# ... or within these (and uncertainties, noise levels within FLOOR_DEG of either unit) for
# noise-free data, whose sigmas are rounding (~1e-11 deg; ~1e-6 when the recorder perturbs).
FLOOR_DEG, FLOOR_MM = 1e-5, 1e-5
RELATIVE_TOLERANCE = 0.02


def solve(samples, options, live=None):
    """
    Return the summary of solving stored samples with stored options.

    live: sample counts (a list) at which to summarise the estimate of a live calibrator fed
    one sample at a time (its warm solves between full ones), {'live': {count: summary}}.
    """
    if live is not None:
        return {'live': _live(samples_of(samples), options_of(options), set(live))}
    try:
        return summary(calibrate(samples_of(samples), options_of(options)))
    except ValueError as error:   # DegenerateMotionError, InsufficientDataError
        return {'error': type(error).__name__, 'message': str(error).split(':')[0]}


def _live(samples, options, counts):
    calibrator = Calibrator(options)
    answers = {}
    for sample in samples:
        calibrator.add_sample(sample)
        calibrator.estimate()
        if len(calibrator.samples) in counts:
            result = calibrator.result
            answers[str(len(calibrator.samples))] = None if result is None else summary(result)
    return answers


def summary(result):
    """Return what the golden answers keep of a CalibrationResult."""
    return {
        'method': result.method,
        'quaternion': [float(v) for v in result.quaternion],
        'translation': [float(v) for v in result.translation],
        'uncertainty_deg': float(result.uncertainty_deg),
        'translation_uncertainty_mm': float(result.translation_uncertainty_mm),
        'closed_form': None if result.closed_form is None else {
            'quaternion': [float(v) for v in result.closed_form.quaternion],
            'translation': [float(v) for v in result.closed_form.translation],
            'uncertainty_deg': float(result.closed_form.uncertainty_deg),
            'translation_uncertainty_mm': float(result.closed_form.translation_uncertainty_mm)},
        'noise_deg': float(result.noise_deg),
        'translation_noise_mm': float(result.translation_noise_mm),
        'rejected': sorted([r['sample']] if 'sample' in r else r['motion']
                           for r in result.rejected),   # [sample] or [i, j] (a motion)
        'noisy': sorted(r['sample'] for r in result.noisy),
        'warnings': sorted(_warning_kind(w) for w in result.warnings),
        'validation': (result.validation or {}).get('verdict'),
        'noise_model': (None if result.noise_model is None else
                        {k: result.noise_model[k] for k in ('distribution', 'shape')}),
    }


def _warning_kind(text):
    """Return a warning's words before its first number: what it is about, not its figures."""
    words = []
    for word in text.split():
        if any(c.isdigit() for c in word):
            break
        words.append(word)
    return ' '.join(words[:8])


def differences(expected, actual):
    """Return what differs between two summaries beyond the tolerances, as strings ([]: none)."""
    if 'live' in expected or 'live' in actual:
        return _live_differences(expected.get('live', {}), actual.get('live', {}))
    if 'error' in expected or 'error' in actual:
        return [] if expected == actual else [f'expected {expected}, got {actual}']
    decisions = ('method', 'rejected', 'noisy', 'warnings', 'validation', 'noise_model')
    found = [f'{key}: expected {expected[key]}, got {actual[key]}' for key in decisions
             if expected[key] != actual[key]]
    found += _estimate_differences('published', expected, actual)
    if (expected['closed_form'] is None) != (actual['closed_form'] is None):
        found.append(f'closed form: expected {expected["closed_form"]}, '
                     f'got {actual["closed_form"]}')
    elif expected['closed_form'] is not None:
        found += _estimate_differences('closed form', expected['closed_form'],
                                       actual['closed_form'])
    for key in ('noise_deg', 'translation_noise_mm'):
        if not _relatively_close(expected[key], actual[key]):
            found.append(f'{key}: expected {_figure(expected[key])}, got {_figure(actual[key])}')
    return found


def _live_differences(expected, actual):
    found = []
    for count in sorted(set(expected) | set(actual), key=int):
        want, got = expected.get(count), actual.get(count)
        if want is None or got is None:
            if want != got:
                found.append(f'after {count} samples: expected {want}, got {got}')
            continue
        found += [f'after {count} samples: {d}' for d in differences(want, got)]
    return found


def _estimate_differences(label, want, got):
    found = []
    sigma_deg = want['uncertainty_deg']
    moved_deg = math.degrees(quat.angle_between(np.array(want['quaternion']),
                                                np.array(got['quaternion'])))
    if not moved_deg <= _tolerance(sigma_deg, FLOOR_DEG):   # (a NaN answer moved too)
        found.append(f'{label} rotation moved {moved_deg:.3g} deg (sigma {sigma_deg:.3g} deg)')
    sigma_mm = want['translation_uncertainty_mm']
    moved_mm = 1e3 * float(np.linalg.norm(np.subtract(want['translation'], got['translation'])))
    if not moved_mm <= _tolerance(sigma_mm, FLOOR_MM):
        found.append(f'{label} translation moved {moved_mm:.3g} mm (sigma {sigma_mm:.3g} mm)')
    for key in ('uncertainty_deg', 'translation_uncertainty_mm'):
        if not _relatively_close(want[key], got[key]):
            found.append(f'{label} {key}: expected {_figure(want[key])}, '
                         f'got {_figure(got[key])}')
    return found


def _figure(value):
    return 'None' if value is None else f'{value:.6g}'


def _tolerance(sigma, floor):
    return max(ANSWER_SIGMAS * sigma, floor) if _finite(sigma) else floor


def _finite(value):
    return value is not None and math.isfinite(value)


def _relatively_close(want, got):
    if not (_finite(want) and _finite(got)):   # both NaN, both infinite or both None
        return repr(want) == repr(got)
    return abs(want - got) <= RELATIVE_TOLERANCE * max(abs(want), abs(got)) + FLOOR_DEG


def stored_samples(samples):
    """Return samples as stored: samples CSV text (full precision, covariances included)."""
    return format_samples(samples)


def stored_options(options):
    """Return CalibrationOptions as stored."""
    fields = asdict(options)
    fields['validation'] = asdict(options.validation)
    return fields


def samples_of(stored):
    """Return stored samples (samples CSV text) as pose.Sample."""
    return parse_samples(stored, 'stored samples')


def options_of(stored):
    """Return stored options as CalibrationOptions."""
    fields = dict(stored)
    fields['validation'] = Thresholds(**fields['validation'])
    if fields.get('known_translation') is not None:
        fields['known_translation'] = tuple(fields['known_translation'])
    return CalibrationOptions(**fields)


def load():
    """Return the recorded cases [(name, stored samples, stored options, live, answer)]."""
    recorded = json.loads(ANSWERS.read_text())
    return [(case['name'], recorded['samples'][case['samples']], case['options'],
             case.get('live'), case['answer']) for case in recorded['cases']]
