"""
Validation: how well the mounting predicts each sample it was not fitted to.

For every good sample, the fit of all the other samples (refine.Refinement.leave_one_out)
predicts the sensor's view of the object; the prediction error is split into an angle (deg)
and a distance (mm). Their RMS over the samples is what a user should expect on a new pose,
noise included, and the verdict compares it with the user's thresholds. The worst samples are
named so they can be inspected (or dropped).
"""

from dataclasses import dataclass, replace

import numpy as np

WORST = 3


@dataclass(frozen=True)
class Thresholds:
    """Pass limits of the leave-one-out prediction errors (RMS over the good samples)."""

    max_rotation_deg: float = 1.0
    max_translation_mm: float = 10.0

    def to_json_dict(self):
        """Return the thresholds as JSON."""
        return {'max_rotation_deg': self.max_rotation_deg,
                'max_translation_mm': self.max_translation_mm}


def validate(leave_one_out, samples, thresholds=Thresholds(), fit='poses'):
    """
    Return the JSON object of the validation (DESIGN.md contract 6).

    leave_one_out: (K, 6) predicted residuals (rotation vector in radians, position in
    metres, sensor frame) of the good samples whose indices are `samples` (K,); fit: the
    estimate's, 'poses' or 'pixels' (the fit on camera images' corners).
    """
    squares = (leave_one_out * leave_one_out).reshape(-1, 2, 3).sum(axis=2)   # (K, 2)
    rotation, translation = np.sqrt(squares).T * np.array([[np.degrees(1.0)], [1e3]])
    rms_rotation, rms_translation = (np.sqrt(squares.mean(axis=0))
                                     * [np.degrees(1.0), 1e3]).tolist()
    # Worst by the larger of the two errors, each in units of its RMS.
    badness = np.maximum(rotation / max(rms_rotation, 1e-300),
                         translation / max(rms_translation, 1e-300))
    worst = np.argsort(-badness, kind='stable')[:WORST]
    entries = [{'sample': s, 'rotation_deg': r, 'translation_mm': t} for s, r, t in zip(
        np.asarray(samples).tolist(), rotation.tolist(), translation.tolist())]
    failures = []
    if rms_rotation > thresholds.max_rotation_deg:
        failures.append(f'rotation {rms_rotation:.3f} deg > {thresholds.max_rotation_deg:g} deg')
    if rms_translation > thresholds.max_translation_mm:
        failures.append(f'translation {rms_translation:.2f} mm > '
                        f'{thresholds.max_translation_mm:g} mm')
    verdict = 'fail' if failures else 'pass'
    reason = ('leave-one-out prediction errors (RMS over the good samples) within the '
              'thresholds' if not failures else
              'leave-one-out prediction errors (RMS) above the thresholds: ' + ', '.join(failures))
    return {
        'method': 'leave-one-out',
        'fit': fit,
        'verdict': verdict,
        'reason': reason,
        'rms_rotation_deg': rms_rotation,
        'rms_translation_mm': rms_translation,
        'thresholds': thresholds.to_json_dict(),
        'worst': [dict(entries[k]) for k in worst.tolist()],
        'samples': entries,
    }


def not_enough_samples(count, needed, thresholds=Thresholds(), fit='poses'):
    """Return the validation object when too few good samples exist to validate."""
    return {'method': 'leave-one-out', 'fit': fit, 'verdict': 'unknown',
            'reason': f'{count} good samples: the leave-one-out validation needs {needed}',
            'rms_rotation_deg': None, 'rms_translation_mm': None,
            'thresholds': thresholds.to_json_dict(), 'worst': [], 'samples': []}


def published(result, warnings=(), causes=()):
    """
    Return CalibrationResult `result` as it is printed and saved, with `warnings` added.

    After its own warnings, a failed validation's comes first of them (said in the warnings,
    not only in "validation"). causes: the input's problems that explain the estimate's
    warnings (TF frames given swapped), before them all. The tools' JSON and files and the
    node's ~/save all use it.
    """
    failed = failure_warning(result.validation)
    if failed:
        warnings = [f"{failed} (each sample's prediction error is listed with the validation, "
                    'the worst first)',
                    *warnings]
    if not (warnings or causes):
        return result
    return replace(result, warnings=[*causes, *result.warnings, *warnings])


def failure_warning(validation):
    """Return 'validation failed: <reason>' for a failed validation object (or None), else ''."""
    if not validation or validation.get('verdict') != 'fail':
        return ''
    return f'validation failed: {validation["reason"]}'
