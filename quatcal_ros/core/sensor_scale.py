"""
A scale error in the sensor's positions, which no rotation shows.

A marker or board of the wrong size scales every position its detector reports; a camera whose
focal length is off scales the depth, along its optical axis (z), alone. The rotations are
unchanged, the leave-one-out validation can pass (a board 5 % too large gave 9.8 mm RMS on
the ETH arm recording against a 10 mm threshold), and the translation of the mounting takes
the error. The object's positions show it: with the sensor's positions scaled by d per axis of
the sensor frame (D = diag(d), 1 when right), sample i puts the object at
    o = t(link_i) + R(link_i) (t_z + R_z D t(sensor_i)),
which is linear in (t_z, d, o) given the rotation R_z. `fit` solves it by least squares over
the good samples (links and sensors inverted as for the estimate, translation.py), in the
sensor frame and weighted by the fitted noise of the sensor's positions (the refinement's:
a camera's depth is the noisiest), with the uncertainty of d from the larger of the model's
and the sandwich's variance (unweighted, 2 of the 2,850 right cells below came out named).
`warning` says when d is off 1 by more than MIN_ERROR and by SIGMAS uncertainties on some
axis, and names a unit for a factor beyond 10; positions all in millimetres, link's and
sensor's alike, keep d = 1: `all_in_millimetres` judges their sizes instead.

Measured (scale per axis +- its uncertainty): the ETH arm recording gives (1.0029, 1.0046,
0.9930) +- (0.0025, 0.0032, 0.0026) and the MoveIt recording (0.9972, 1.0086, 0.9982) +-
(0.0019, 0.0036, 0.0030), within 2.7 uncertainties of 1; with their sensor positions scaled by
1.02 both are named (2.2 % too large), and with the depth alone scaled by 1.03 too (z 0.967
and 0.969, 13 and 11 uncertainties). Of 2,850 synthetic cells of 8-12 samples of
the right scale in five noise modes (isotropic, PnP-like, t tails, robot noise, flips) none
was named, the largest deviation 4.1 uncertainties; of 9,000 of 20-30 samples (refitted) one,
at 5.8 (robot noise), the next largest 5.3 (test_honesty.py). A depth 3 % too long was named
on 86 of 200 cells of 20 samples, 128 of 30 and 189 of 60; 10 % on all from 20.
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.core.units import DO_NOT_USE

# A scale error is said when some axis is off 1 by more than this fraction...
MIN_ERROR = 0.01
# ... and by more than this many of its uncertainties (the largest of the right scale, above).
SIGMAS = 5.5
# Fewer samples leave the 9 unknowns too few equations (3N - 9) to judge them: the sd is then
# so uncertain that 5 of them came by chance (1 of 20 cells of 6 samples with robot noise).
MIN_SAMPLES = 8
# A factor between a pair of these is positions in that unit where metres were due (the
# sensor's over the link's, or its inverse): the unit that a factor beyond 10 names.
UNITS = ((500.0, 2000.0, 'millimetres'), (70.0, 150.0, 'centimetres'), (30.0, 50.0, 'inches'))
# Link positions farther than this from the base (median, metres) are in millimetres, not a
# robot cell: no robot reaches 100 m. With sensor positions beyond the second figure they are
# all in millimetres (a board 10 mm from the camera is too close to see, while no detector or
# tracker sees 10 m away at every pose). The scale fit, which compares the two, cannot see
# them scaled alike; a board closer than 100 mm was missed when both had to pass 100 m.
ALL_IN_MILLIMETRES_M = 100.0
ALL_IN_MILLIMETRES_SENSOR_M = 10.0
# From this many samples the fit is weighted again by its own residuals (fit).
REFIT_SAMPLES = 20
# Sensor positions this much too large or small along an axis (a board size mistyped, such as
# 0.3 for 0.03 m; a focal length 30 % off, along the depth) move the mounting's translation by
# 30-100 mm or more at a camera's 0.3-1 m from its target, far beyond any use: the warning
# then says not to use the estimate.
SIZE_UNUSABLE = 0.10
# A factor beyond this (or below its inverse) on every axis is positions in another unit; a
# factor of 10 is a size mistyped (0.3 for 0.03 m), named as such.
UNITS_FACTOR = 15.0
AXES = 'xyz'


@dataclass(frozen=True)
class SensorScale:
    """The scale per axis of the sensor frame that fits the positions best, and its sd."""

    scale: np.ndarray        # (3,)
    uncertainty: np.ndarray  # (3,) standard deviations

    def to_json_dict(self):
        """Return {scale: [x, y, z], uncertainty: [x, y, z]}."""
        return {'scale': [float(v) for v in self.scale],
                'uncertainty': [float(v) for v in self.uncertainty]}


def fit(link_R, link_t, sensor_t, R_z, noise=None):
    """
    Return the SensorScale of the samples, or None with fewer than MIN_SAMPLES.

    link_R (N, 3, 3), link_t (N, 3): the links (inverted for eye-to-hand); sensor_t (N, 3):
    the sensors' positions (inverted with invert_sensor); R_z: the mounting's rotation;
    noise: the sensor positions' noise covariance (3, 3, sensor frame; the refinement's), or
    None (isotropic). Each sample's equation is taken in the sensor frame, where that noise
    lives: D t(sensor_i) = M_i^T (o - t(link_i)) - R_z^T t_z, M_i = R(link_i) R_z, weighted
    by the noise's inverse. From REFIT_SAMPLES on, fitted again weighted by the covariance
    of its own residuals: the refinement, which has no scale, takes a depth scaled by 1.1 as
    depth noise, and the first fit then saw it in 40 of 200 cells of 20 samples (200 of
    200 refitted).
    """
    n = len(link_t)
    if n < MIN_SAMPLES:
        return None
    M_T = np.swapaxes(link_R @ R_z, 1, 2)
    # Rows per sample (3, 9) over (d, o, t_z), and the right-hand side M_i^T t(link_i).
    A = np.empty((n, 3, 9))
    A[:, :, :3] = sensor_t[:, :, None] * np.eye(3)
    A[:, :, 3:6] = -M_T
    A[:, :, 6:] = R_z.T
    b = -(M_T @ link_t[..., None])[..., 0]
    found = _weighted(A, b, noise)
    if found is None or n < REFIT_SAMPLES:
        return None if found is None else found[0]
    residuals = np.einsum('nia,a->ni', A, found[1]) - b   # in the sensor frame
    refitted = _weighted(A, b, residuals.T @ residuals / (n - 3))
    return found[0] if refitted is None else refitted[0]


def _weighted(A, b, noise):
    """
    Return (SensorScale, all 9 unknowns) of the equations A (N, 3, 9), b (N, 3), or None.

    Weighted by the inverse of `noise` (3, 3), or unweighted (None); the uncertainty is the
    larger of the model's and the sandwich's.
    """
    n = len(b)
    if noise is not None:
        try:
            whiten = np.linalg.inv(np.linalg.cholesky(noise))
        except np.linalg.LinAlgError:
            return None
        A, b = whiten @ A, b @ whiten.T
    rows = A.reshape(-1, 9)
    try:
        normal_inv = np.linalg.inv(rows.T @ rows)
    except np.linalg.LinAlgError:
        return None
    theta = normal_inv @ (rows.T @ b.reshape(-1))
    residuals = (rows @ theta - b.reshape(-1)).reshape(n, 3)
    dof = 3 * n - 9
    model = normal_inv * (np.einsum('ij,ij->', residuals, residuals) / dof)
    scores = np.einsum('nia,ni->na', A, residuals)
    sandwich = normal_inv @ (scores.T @ scores) @ normal_inv * (3 * n / dof)
    variance = np.maximum(np.diag(model), np.diag(sandwich))[:3]
    return SensorScale(theta[:3], np.sqrt(variance)), theta


def warning(found):
    """Return the warning a SensorScale calls for, or None."""
    if found is None:
        return None
    off = _off(found)
    if not np.any(off):
        return None
    axes = ', '.join(f'{axis} {scale:.4f} +- {sd:.4f}' for axis, scale, sd
                     in zip(AXES, found.scale, found.uncertainty))
    factor = float(np.median(found.scale))
    if off.all() and factor > 0.0 and not 1.0 / UNITS_FACTOR < factor < UNITS_FACTOR:
        size = max(factor, 1.0 / factor)
        unit = next((name for low, high, name in UNITS if low < size < high), None)
        look = (f'look to be in {unit}' if unit else
                f'are in another unit than the {"sensor" if factor > 1 else "link"} positions')
        return (f"the sensor's positions fit the mounting best scaled by ({axes}) along the "
                f"sensor's axes: a factor of {factor:.4g}, which is no size error but units: "
                f'the {"link" if factor > 1 else "sensor"} positions {look}; every position '
                'must be in metres (the pose messages, robot_poses.csv, a samples file). '
                f'Neither the rotation nor the translation holds: {DO_NOT_USE}')
    if off.all() and np.ptp(found.scale) <= 3.0 * found.uncertainty.max():
        where, cause = '', "is the marker's or the board's size given right, in metres?"
    elif off[2] and not off[:2].any():
        where, cause = (" along its z axis (a camera's depth) alone",
                        "is the camera's focal length (its intrinsic calibration) right?")
    else:
        where, cause = '', "check the marker or board size and the camera's calibration."
    wrong = 1.0 / found.scale[off] - 1.0   # how far the positions are off, per axis
    if np.all(wrong > 0) or np.all(wrong < 0):
        size = float(np.mean(wrong))
        look = f'{abs(size) * 100:.1f} % too {"large" if size > 0 else "small"}'
    else:
        look = 'off by ' + ', '.join(f'{100 * w:+.1f} % along {axis}' for axis, w
                                     in zip(np.array(list(AXES))[off], wrong))
    said = (f"the sensor's positions fit the mounting best scaled by ({axes}; +- one "
            f"standard deviation) along the sensor's axes, not by 1: they look {look}{where}: "
            f"{cause} The mounting's translation takes the error, and so does the rotation "
            'of an estimate on camera pixels (a rigid mounting no longer fits them); the '
            'rotation from the poses does not')
    if grossly_off(found):
        said += (f'. Off by over {100 * SIZE_UNUSABLE:.0f} %, the translation is wrong by '
                 f'tens of millimetres or more: {DO_NOT_USE}')
    return said


def grossly_off(found):
    """
    Return whether the sensor positions are too large or small by SIZE_UNUSABLE on some axis.

    Said (off 1 by SIGMAS of its uncertainty) and positive: mirrored positions have no size.
    Then the mounting comes out as long as the error makes it, and warnings that judge its
    length (an exchange of the link and sensor poses) see only that.
    """
    if found is None or not np.all(found.scale > 0.0):
        return False
    wrong = 1.0 / found.scale - 1.0   # how far the positions are off, per axis
    return bool(np.any(_off(found) & (np.abs(wrong) > SIZE_UNUSABLE)))


def _off(found):
    """Return the mask of the axes whose factor is off 1 enough to be said (MIN_ERROR, SIGMAS)."""
    error = np.abs(found.scale - 1.0)
    return (error > MIN_ERROR) & (error > SIGMAS * found.uncertainty)


def all_in_millimetres(link_positions, sensor_positions):
    """Return the warning for link and sensor positions alike in millimetres, or None."""
    link, sensor = (float(np.median(np.linalg.norm(positions, axis=1)))
                    for positions in (link_positions, sensor_positions))
    if not (link > ALL_IN_MILLIMETRES_M and sensor > ALL_IN_MILLIMETRES_SENSOR_M):
        return None
    return (f'the sensor sees its target a median {sensor:.4g} m away and the link stands '
            f'{link:.4g} m from its base: the positions look to be in millimetres, all of them. '
            'The rotation holds, but the translation and its uncertainty are in that unit '
            'too; give every position in metres (the pose messages, robot_poses.csv, a '
            f'samples file): {DO_NOT_USE} as it is')
