"""
The calibration report: one self-contained HTML page (`solve --report`, `replay --report`).

The page holds the answer and its uncertainty, the validation verdict, each sample's
leave-one-out prediction error (rejected and down-weighted samples marked), the estimate as
samples were added (each prefix solved again with the same options), where the motions' rotation
axes point (where the data are thin), the time offset when one was measured, and the mount in
two views. The figures are inline SVG (figures.py); the page loads nothing, runs no script,
and is written atomically.
"""

from html import escape

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate
from quatcal_ros.core.motions import SampleRotations
from quatcal_ros.files.persistence import atomic_write_text
from quatcal_ros.report import figures

# Prefixes solved again for the convergence figure, at most.
CONVERGENCE_POINTS = 15
STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 60em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 1.8em; }
table { border-collapse: collapse; } td, th { padding: 0.2em 0.8em; text-align: left; }
tr:nth-child(even) { background: #f3f5f8; }
.pass { color: #1e7d32; font-weight: bold; } .fail { color: #c62828; font-weight: bold; }
.warn { color: #8a5300; } code { background: #f3f5f8; padding: 0 0.2em; }
figure { margin: 0.5em 0; } svg { max-width: 100%; height: auto; }
"""


def write_report(path, result, samples, options, frames, title='', time_offset=None):
    """Write the report page of `result` (its `samples`, CalibrationOptions) to `path`."""
    atomic_write_text(path, report_html(result, samples, options, frames, title,
                                        time_offset))


def report_html(result, samples, options, frames, title='', time_offset=None):
    """
    Return the report page as text.

    frames: (parent, child) of the mounting; time_offset: the replay's "time_offset" JSON
    object, or None.
    """
    parent, child = frames
    sections = [f'<h1>Hand-eye calibration{": " + escape(title) if title else ""}</h1>',
                _answer(result, parent, child), _validation(result)]
    if time_offset:
        sections.append(_time_offset(time_offset))
    sections += [
        '<h2>Each sample, predicted from the others</h2>',
        '<p>The object pose of each sample predicted by the estimate of all the other samples '
        '(leave-one-out), against the one observed; the dashed lines are the thresholds. A '
        'rejected sample is not predicted: its column is shaded.</p>',
        _figure(_sample_figure(result, len(samples))), _set_aside(result),
        '<h2>The estimate as samples were added</h2>',
        '<p>Each prefix of the samples solved again with the same options: its distance from '
        'the final answer, and the uncertainty it reported.'
        + (' On camera images the prefixes are solved on the board poses, and measured from '
           'the pose-based answer of all samples (which the fit on the pixels then refines).'
           if result.reprojection else '') + '</p>',
        _figure(_convergence_figure(result, samples, options)),
        '<h2>Coverage of rotation axes</h2>',
        f'<p>The rotation axis of each motion between consecutive samples, in the '
        f'{_frame(options)} frame (the frame of the least determined axis). '
        f'Sparse regions are directions the data do not excite; the least determined axis is '
        f'{_vector(result.weakest_axis)}. {escape(result.hint)}</p>',
        _figure(_coverage_figure(result, samples, options)),
        '<h2>The mount</h2>',
        f'<p>{escape(child)} in {escape(parent)}: axes x red, y green, z blue.</p>',
        _figure(figures.mount_views(result.matrix, result.translation, parent, child))]
    return ('<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<title>Hand-eye calibration report</title><style>{STYLE}</style></head>'
            '<body>\n' + '\n'.join(sections) + '\n</body></html>\n')


def _figure(svg):
    return f'<figure>{svg}</figure>'


def _vector(values, digits=3):
    return '(' + ', '.join(f'{float(v):.{digits}f}' for v in values) + ')'


def _answer(result, parent, child):
    x, y, z, w = quat.xyzw_from_wxyz(result.quaternion)
    rows = [('mounting', f'{escape(parent)} &rarr; {escape(child)} ({result.setup})'),
            ('rotation (x, y, z, w)', _vector((x, y, z, w), 6)),
            ('translation (m)', _vector(result.translation, 4)),
            ('rotation uncertainty', f'{result.uncertainty_deg:.3g} deg (expected RMS error)'),
            ('translation uncertainty', f'{result.translation_uncertainty_mm:.3g} mm'),
            ('method', escape(result.method)),
            ('samples', f'{result.samples} ({result.samples - result.inlier_samples} rejected, '
                        f'{len(result.noisy)} down-weighted)'),
            ('motions', f'{result.inliers} of {result.motions} used, residual '
                        f'{result.residual_rms_deg:.3g} deg RMS'
                        + (' (of the pose-based estimate)' if result.reprojection else ''))]
    rows += _on_pixels(result)
    table = ''.join(f'<tr><th>{name}</th><td>{value}</td></tr>' for name, value in rows)
    warnings = ''.join(f'<li class="warn">{escape(text)}</li>' for text in result.warnings)
    return (f'<table>{table}</table>'
            + (f'<h2>Warnings</h2><ul>{warnings}</ul>' if warnings else ''))


def _on_pixels(result):
    """Return the answer table's rows of the fit on the pixels (camera images), if it is one."""
    fit = result.reprojection
    if not fit:
        return []
    deg, mm = fit['view_error_deg'], fit['view_error_mm']
    fitted = any(deg) or any(mm)
    evidence = fit.get('view_error_evidence')
    test = ('' if evidence is None else
            f' (likelihood-ratio evidence {evidence:.1f}, fitted from '
            f'{fit["view_error_threshold"]:g})')
    shared = (f'{_vector(deg, 3)} deg and {_vector(mm, 2)} mm (x, y, z in the camera frame, '
              "standard deviations): what all corners of a view share, from the robot's pose "
              f'or the camera model, fitted{test}'
              if fitted else f'none: the corners show no error a view shares{test}')
    within = (f', {fit["within_view_rms_px"]:#.3g} px once each view' + "'s shared error is "
              'taken out' if fitted else '')
    worst = {'sample': fit['worst_view_sample']}
    if 'worst_view_image' in fit:
        worst['image'] = fit['worst_view_image']
    rows = [('fit on the pixels', f'pixel noise {fit["pixel_noise_px"]:#.3g} px; reprojection '
                                  f'RMS {fit["reprojection_rms_px"]:#.3g} px{within}; the '
                                  f'worst view: sample {escape(_sample(worst))}, '
                                  f'{fit["worst_view_rms_px"]:#.3g} px RMS'),
            ("each view's shared error", shared)]
    scale, focal_evidence = fit.get('focal_scale', 1.0), fit.get('focal_evidence')
    if scale != 1.0:
        rows.append(('focal length', f"camera_info's times {scale:.4f} "
                                     f'(+-{fit["focal_scale_sd"]:.2g}), fitted (likelihood-ratio '
                                     f'evidence {focal_evidence:.1f}, from '
                                     f'{fit["focal_threshold"]:g})'))
    elif focal_evidence is not None:
        rows.append(('focal length', f"camera_info's: the corners show no error in it "
                                     f'(likelihood-ratio evidence {focal_evidence:.1f}, fitted '
                                     f'from {fit["focal_threshold"]:g})'))
    pose_based = result.refined or result.closed_form
    if pose_based is not None:
        apart_deg = np.degrees(quat.angle_between(pose_based.quaternion, result.quaternion))
        apart_mm = 1e3 * np.linalg.norm(np.asarray(pose_based.translation) - result.translation)
        checked = fit.get('pose_based_validation') or {}
        said = ('' if checked.get('rms_rotation_deg') is None else
                f'; its validation {escape(checked["verdict"])} '
                f'({checked["rms_rotation_deg"]:.3g} deg, '
                f'{checked["rms_translation_mm"]:.3g} mm)')
        if scale != 1.0:   # (its poses are PnP's with the focal lengths the fit scaled)
            said += "; its board poses use camera_info's focal lengths"
        rows.append(('pose-based estimate', f'{apart_deg:.3g} deg and {apart_mm:.3g} mm from '
                                            f'this one; uncertainty '
                                            f'{pose_based.uncertainty_deg:.3g} deg, '
                                            f'{pose_based.translation_uncertainty_mm:.3g} mm'
                                            + said))
    return rows


def _validation(result):
    validation = result.validation or {}
    verdict = validation.get('verdict', 'unknown')
    thresholds = validation.get('thresholds', {})
    worst = ', '.join(f'{_sample(w)} ({w["rotation_deg"]:.3g} deg, '
                      f'{w["translation_mm"]:.3g} mm'
                      + (f', {w["reprojection_rms_px"]:.3g} px' if 'reprojection_rms_px' in w
                         else '') + ')' for w in validation.get('worst', []))
    numbers = ''
    if validation.get('rms_rotation_deg') is not None:
        numbers = (f' RMS prediction error {validation["rms_rotation_deg"]:.3g} deg and '
                   f'{validation["rms_translation_mm"]:.3g} mm against thresholds '
                   f'{thresholds.get("max_rotation_deg", float("nan")):g} deg and '
                   f'{thresholds.get("max_translation_mm", float("nan")):g} mm.')
    if validation.get('rms_reprojection_px') is not None:
        numbers += (" Each view's corners lie "
                    f'{validation["rms_reprojection_px"]:.3g} px (RMS over the views) from '
                    'the pixels the fit without that view predicts.')
    css = verdict if verdict in ('pass', 'fail') else 'warn'
    whose = (' (of the pose-based estimate)'
             if result.reprojection and validation.get('fit') != 'pixels' else '')
    return (f'<h2>Validation{whose}: <span class="{css}">{escape(verdict)}</span></h2>'
            f'<p>{escape(validation.get("reason", ""))}.{numbers}'
            + (f' Worst samples: {escape(worst)}.' if worst else '') + '</p>')


def offset_sentence(offset):
    """Say what the time-offset search found, of the replay JSON's `time_offset`."""
    runs = offset.get('runs', 1)
    where = (f' (searched on the longest of the {runs} runs: the stamps start over)'
             if runs > 1 else '')
    given = offset.get('searched_around_s')
    around = (f', searched around the given {given:+.3f} s, where the RMS residual is '
              f'{_degrees(offset.get("residual_at_given_deg"))}' if given else '')
    said = (f'sensor stamps shifted by {1e3 * offset["sensor_offset_s"]:+.1f} ms (speed '
            f'correlation {offset["correlation"]:.2f}{around}); RMS residual of the search '
            f"(the same sensor frames, the link at each shifted stamp: not the capture's "
            f'residual_rms_deg) {_degrees(offset["residual_without_deg"])} without any '
            f'offset, {_degrees(offset["residual_with_deg"])} with it{where}')
    if offset.get('speeds_aligned', True):
        return said
    centre = given or 0.0
    return (f'{said}. The angular speeds of the two streams align nowhere within '
            f'{1e3 * offset["searched_within_s"]:g} ms of {centre:+.3f} s (best correlation '
            f'{offset["correlation"]:.2f}, at {offset["weak_peak_s"]:+.3f} s): the offset was '
            f'searched by the residual alone, near {centre:+.3f} s. It may lie beyond (give '
            'the one you expect with --sensor-time-offset, and the search looks around it), '
            'or the two streams do not show the same motion')


def _degrees(value):
    """Return a residual of the time_offset JSON in words ('none': nothing to solve there)."""
    return 'none (too few samples there)' if value is None else f'{value:.3f} deg'


def _time_offset(offset):
    sentence = offset_sentence(offset)
    return f'<h2>Time offset</h2><p>{escape(sentence[0].upper() + sentence[1:])}.</p>'


def _sample(entry):
    """Return a sample's number, with its image where it has one (solve DIR): '3 (4.png)'."""
    return f'{entry["sample"]} ({entry["image"]})' if 'image' in entry else str(entry['sample'])


def _set_aside(result):
    """Return the rejected and the down-weighted samples with their reasons, as a list."""
    items = [f'sample {_sample(entry)} rejected: {entry["reason"]}'
             for entry in result.rejected if 'sample' in entry]
    items += [f'sample {_sample(entry)} down-weighted (weight {entry["weight"]:.2g}): '
              f'{entry["reason"]}' for entry in result.noisy]
    return ('<ul>' + ''.join(f'<li>{escape(item)}</li>' for item in items) + '</ul>'
            if items else '')


def _sample_figure(result, count):
    rotation, translation = np.full(count, np.nan), np.full(count, np.nan)
    validation = result.validation or {}
    for item in validation.get('samples', []):
        rotation[item['sample']] = item['rotation_deg']
        translation[item['sample']] = item['translation_mm']
    thresholds = validation.get('thresholds', {})
    return figures.sample_residuals(rotation, translation, result.sample_states(count),
                                    (thresholds.get('max_rotation_deg', np.nan),
                                     thresholds.get('max_translation_mm', np.nan)))


def convergence(result, samples, options, points=CONVERGENCE_POINTS):
    """
    Return (counts, deg, sigma deg, mm, sigma mm) of prefix estimates against `result`.

    Against the pose-based answer of all samples when `result` is the fit on the pixels (the
    prefixes are pose-based: the pixel fit's own would mix two estimators).
    """
    n = len(samples)
    if result.reprojection:   # (the pose-based answer the session published beside it)
        result = result.refined or result.closed_form
    counts = sorted({int(round(k)) for k in np.linspace(min(4, n), n, points)})
    rows = []
    for k in counts:
        try:
            prefix = result if k == n else calibrate(samples[:k], options)
        except ValueError:   # too few motions, or degenerate ones, yet
            continue
        rows.append((k, np.degrees(quat.angle_between(prefix.quaternion, result.quaternion)),
                     prefix.uncertainty_deg,
                     1e3 * np.linalg.norm(np.asarray(prefix.translation) - result.translation),
                     prefix.translation_uncertainty_mm))
    return tuple(np.array(column, float) for column in zip(*rows)) if rows else None


def _convergence_figure(result, samples, options):
    found = convergence(result, samples, options)
    if found is None:
        return '<p>(no prefix could be solved)</p>'
    return figures.convergence(*found)


def motion_axes(samples, result, options):
    """Return (axes (M, 3), angles deg) of consecutive used samples' motions (_frame's frame)."""
    rotations = SampleRotations.from_samples(samples, options.setup, options.invert_sensor)
    ok = (np.ones(len(samples), bool) if result.sample_ok is None
          else np.asarray(result.sample_ok, bool))
    link = rotations.link[ok]
    relative = quat.multiply(quat.conjugate(link[:-1]), link[1:])
    vectors = quat.rotation_vector(relative)
    angles = np.linalg.norm(vectors, axis=1)
    moved = angles > 1e-9
    return vectors[moved] / angles[moved, None], np.degrees(angles[moved])


def _coverage_figure(result, samples, options):
    axes, angles = motion_axes(samples, result, options)
    if not len(axes):
        return '<p>(no motion)</p>'
    return figures.axis_coverage(axes, angles, result.weakest_axis, _frame(options))


def _frame(options):
    """Return the motions' frame: the link's (eye-in-hand), the robot base's (eye-to-hand)."""
    return 'link' if options.setup == 'eye_in_hand' else 'base'
