"""
Frame-convention and rigid-mounting checks over the whole fit, rotations and translations.

A wrong convention (the other setup, the sensor poses inverted) still lets rotations fit
moderately well when the robot turns little, since rotation angles cannot tell
(angle(L_i^T L_j) == angle(L_i L_j^T)), but the object positions the samples predict then
scatter by the lever arms (tens of centimetres) instead of by the sensor noise. So the
configured convention's misfit (median rotation and position residuals; from the main fit when
there is one) is questioned when it is poor: then each of the four conventions (setup x sensor
inversion) gets the same quick closed-form fit of rotation and translation, and the configured
one is compared with the best by the median rotation residual times the median position
residual.
The warning names the fix.

A fit that no convention explains (a residual of tens of degrees) is not a rigid mounting, or
the data are dominated by bad detections: `rigid_fit_warnings` says so loudly.
"""

import math

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.numerics import inverse, median
from quatcal_ros.core.units import SETUPS

# Samples (evenly spaced) the check examines: plenty for medians.
CHECK_SAMPLES = 400
# The configured convention is questioned only when its fit is poor in absolute terms...
SUSPICIOUS_RESIDUAL_DEG = 1.0
SUSPICIOUS_POSITION_MM = 5.0
# ... and another fits better by this factor (median rotation x median position residual).
BETTER_FACTOR = 6.0
# Floors of the medians (noise-free data, or no position information).
FLOOR_DEG, FLOOR_MM = 0.01, 0.01
# A rotation residual (RMS, degrees) no rigid mounting with a working sensor leaves.
NOT_RIGID_DEG = 10.0


def warnings(samples, options, screen=None):
    """
    Return a warning naming the fix when another convention fits far better, else [].

    screen: the configured convention's misfit from the main fit (`misfit`), when there is
    one: a good fit there ends the check at no cost. Otherwise the configured convention is
    compared with the others by the same quick fit (the main fit screens bad detections, the
    quick ones do not, so their misfits are not comparable).
    """
    if screen is not None and _good(screen):
        return []
    fits = _quick_misfits(_arrays(samples), options)
    if fits is None:
        return []
    current = fits.pop((options.setup, options.invert_sensor))
    if _good(current):
        return []
    others = fits
    best = min(others, key=lambda k: _score(others[k]))
    rotation, position = current
    if _score(current) < BETTER_FACTOR * _score(others[best]):
        return []
    return [f'frame convention: the samples fit badly as configured (median residual '
            f'{rotation:.2f} deg, {position:.1f} mm) but well as {_name(*best)} '
            f'({others[best][0]:.2f} deg, {others[best][1]:.1f} mm): '
            f'{_fix(options, *best)}']


def _good(fit):
    return fit[0] < SUSPICIOUS_RESIDUAL_DEG and fit[1] < SUSPICIOUS_POSITION_MM


def _score(fit):
    return max(fit[0], FLOOR_DEG) * max(fit[1], FLOOR_MM)


def _name(setup, invert):
    return setup + (' with the sensor poses inverted' if invert else '')


def _fix(options, setup, invert):
    words = []
    if setup != options.setup:
        words.append(f'use --setup {setup}')
    if invert != options.invert_sensor:
        words.append('the sensor poses are inverted (the sensor in the object frame instead of '
                     'the object in the sensor frame): use --invert-sensor' if invert else
                     'the sensor poses are not inverted: drop --invert-sensor')
    return '; '.join(words)


def misfit(rotation_residuals, position_residuals):
    """Return the median rotation (deg) and position (mm) residuals of the samples (N, 3)."""
    return (math.degrees(median(np.linalg.norm(rotation_residuals, axis=1))),
            1e3 * median(np.linalg.norm(position_residuals, axis=1)))


def _arrays(samples):
    """Return the link and sensor quaternions and positions of (at most CHECK_SAMPLES) samples."""
    if len(samples) > CHECK_SAMPLES:
        samples = [samples[k] for k in np.linspace(0, len(samples) - 1, CHECK_SAMPLES,
                                                   dtype=int)]
    return tuple(np.array([getattr(getattr(s, pose), field) for s in samples], dtype=float)
                 for pose in ('link', 'sensor') for field in ('quaternion', 'position'))


def _quick_misfits(arrays, options):
    """
    Return each convention's median residuals of a quick fit, or None.

    {(setup, invert_sensor): (median rotation residual in degrees, position in mm)}, for the
    four conventions; arrays: `_arrays` of the samples. Each fit is the least squares of all
    pairs (leastsq.py) and the closed-form translation (translation.py), without the
    screening of bad detections; all four at once, as they share most of their arithmetic
    (the samples' signs, the link rotations up to a transpose). None when fewer than three
    motions are large enough to inform (the same for every convention: so are their angles).
    """
    link_q, link_t, sensor_q, sensor_t = arrays
    n = len(link_q)
    # Motions large enough to inform: every pair's rotation angles, 2 acos |q_i . q_j|.
    cosine = np.cos(np.radians(options.min_motion_deg) / 2.0)
    link_dots, sensor_dots = link_q @ link_q.T, sensor_q @ sensor_q.T
    small = (np.abs(link_dots) >= cosine) | (np.abs(sensor_dots) >= cosine)
    if (small.size - small.sum()) // 2 < 3:
        return None
    conventions = [(setup, invert) for setup in SETUPS for invert in (False, True)]
    conjugate = np.array([1.0, -1.0, -1.0, -1.0])
    # Each convention's link and sensor poses (motions.py, translation.py): (4, N, ...).
    links = np.array([link_q * conjugate if setup == 'eye_to_hand' else link_q
                      for setup, _ in conventions])
    sensors = np.array([sensor_q * conjugate if invert else sensor_q for _, invert in conventions])
    link_R = quat.matrix_from_quaternion(links)                   # (4, N, 3, 3)
    # t(inv(T)) = -R^T t, R^T the rotation of the conjugated quaternion
    inverted_sensor = -(quat.matrix_from_quaternion(sensor_q * conjugate)
                        @ sensor_t[..., None])[..., 0]
    link_positions = np.array([link_t if setup == 'eye_in_hand' else
                               -(link_R[k] @ link_t[..., None])[..., 0]
                               for k, (setup, _) in enumerate(conventions)])
    sensor_positions = np.array([inverted_sensor if invert else sensor_t
                                 for _, invert in conventions])
    # The all-pairs least squares of every convention (leastsq.all_pairs_rotation).
    A = quat.plus_matrix(links) @ quat.minus_matrix(sensors)      # (4, N, 4, 4)
    signs = np.broadcast_to(np.where((link_dots * sensor_dots)[
        int(np.argmax(np.abs(link_dots * sensor_dots).min(axis=1)))] < 0.0, -1.0, 1.0),
        (4, n))
    for _ in range(3):
        S = (signs[:, None, :] @ A.reshape(4, n, 16))[:, 0].reshape(4, 4, 4)
        p = np.linalg.svd(S)[2][:, 0]                              # (4, 4)
        Z = (A @ p[:, None, :, None])[..., 0]                      # (4, N, 4)
        new_signs = np.where(np.einsum('cni,ci->cn', Z, (S @ p[..., None])[..., 0]) < 0.0,
                             -1.0, 1.0)
        if np.array_equal(new_signs, signs):
            break
        signs = new_signs
    # Object orientations about their means: the rotation residuals (quality.py).
    mean = quat.average(Z)                                        # (4, 4)
    rotation = quat.rotation_vector(quat.multiply(Z, quat.conjugate(mean)[:, None, :]))
    # The closed-form translation (translation.py) of all pairs (quality.Information).
    total = link_R.sum(axis=1)                                    # (4, 3, 3)
    C = n * np.swapaxes(link_R, 2, 3) - np.swapaxes(total, 1, 2)[:, None]
    H = n * n * np.eye(3) - np.swapaxes(total, 1, 2) @ total
    offsets = link_positions + (link_R @ (quat.matrix_from_quaternion(p)[:, None]
                                          @ sensor_positions[..., None]))[..., 0]
    rows = np.swapaxes(C, 1, 2).reshape(4, 3, -1)               # sum_n C_n x_n
    t_z = -(inverse(H) @ (rows @ offsets.reshape(4, -1, 1)))[..., 0]    # (4, 3)
    predictions = offsets + (link_R @ t_z[:, None, :, None])[..., 0]
    position = predictions - predictions.mean(axis=1, keepdims=True)
    rotation_deg = np.degrees(median(np.linalg.norm(rotation, axis=2), axis=1))
    position_mm = 1e3 * median(np.linalg.norm(position, axis=2), axis=1)
    return {convention: (float(r), float(t)) for convention, r, t in zip(
        conventions, rotation_deg, position_mm)}


def rigid_fit_warnings(residual_rms_deg, translation_noise_mm):
    """Return a loud warning when the residuals are too large for any rigid mounting."""
    if not residual_rms_deg > NOT_RIGID_DEG:
        return []
    return [f'the samples do not fit a rigid mounting: residual {residual_rms_deg:.1f} deg RMS '
            f'(position scatter {translation_noise_mm:.0f} mm per axis). Check that the '
            'sensor is fixed where the setup says, that the link and sensor poses belong to '
            'the same moments, and that bad detections are screened (do not use --no-robust '
            'on such data); do not use this estimate']
