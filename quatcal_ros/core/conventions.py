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
The warning names the fix. Two conventions are mirrors of each other: eye_in_hand with the
sensor poses inverted is eye_to_hand with the mounting and the object swapped (and the same
with the inversions exchanged), so the quick fits score them alike and the wrong one answers
with the object's pose. When the best and its mirror are that close, the Gaussian joint
refinement of each may decide: it weighs the residuals in the sensor frame, and when the noise
is the sensor's, the mirror's inverted poses carry its rotation noise into the positions by
the lever arm (on synthetic cells with sensor noise the mirror's noise was 1.45-4x the right
convention's). Real data need not show it (the MoveIt recording in data/: 1.004x), so below
MIRROR_DECISIVE the warning names both and says how to choose. Whenever the mirror fits too,
the warning names it beside the fix: the choice assumes the noise is the sensor's, and with
the robot's poses noisy instead the mirror fits better (on synthetic cells with only link-pose
noise, the quick fits preferred it by 1.5-3.5x).

A fit that no convention explains (a residual of tens of degrees) is not a rigid mounting, or
the data are dominated by bad detections: `rigid_fit_warnings` says so loudly.

Exchanged link and sensor poses fit exactly too (L X S = O gives S X' L = O' with X' = O^-1
and O' = X^-1), so no residual shows them: eye-in-hand, the answer is then the object's
pose, as long as the object is far from the robot base, and the object comes out as close
to the base as the sensor is to the link. `exchanged_warnings` says so when the mounting is
that long and the object that near (synthetic cells: mountings 0.06-0.13 m, objects 0.36-1.4
m; exchanged, the two lengths swapped places; the ETH arm recording: 0.014 m and 0.69 m).
With the sensor poses inverted, the exchange gives the inverse mounting, of the same length:
nothing to see.
"""

from dataclasses import dataclass
import math

import numpy as np

from quatcal_ros.core import quality
from quatcal_ros.core.leastsq import all_pairs_rotation
from quatcal_ros.core.motions import pair_angles, pair_indices, SampleRotations
from quatcal_ros.core.numerics import median
from quatcal_ros.core.refine import refine
from quatcal_ros.core.translation import SamplePositions, solve_translation
from quatcal_ros.core.units import DO_NOT_USE, SETUPS

# Samples (evenly spaced) the check examines: plenty for medians.
CHECK_SAMPLES = 400
# The configured convention is questioned only when its fit is poor in absolute terms...
SUSPICIOUS_RESIDUAL_DEG = 1.0
SUSPICIOUS_POSITION_MM = 5.0
# ... and another fits better by this factor (median rotation x median position residual).
BETTER_FACTOR = 6.0
# Floors of the medians (noise-free data, or no position information).
FLOOR_DEG, FLOOR_MM = 0.01, 0.01
# The best convention and its mirror score within this factor: the refinement is asked...
MIRROR_FACTOR = 2.0
# ... and decides when one's noise is this many times the other's; else both are named.
MIRROR_DECISIVE = 1.3
# A rotation residual (RMS, degrees) no rigid mounting with a working sensor leaves.
NOT_RIGID_DEG = 10.0
# An eye-in-hand mounting this long (metres), and this many times the object's distance from
# the robot base, looks like exchanged link and sensor poses (exchanged_warnings).
LONG_MOUNTING_M = 0.25
EXCHANGED_RATIO = 2.0

# The start of every warning that another frame convention fits far better.
PREFIX = 'frame convention:'
# Fewer samples than this (two independent motions) fit every convention alike. (The live
# calibrator solves in full up to 12 samples, so the warning never carries into a warm solve.)
CHECKED_FROM_SAMPLES = 4
NOT_CHECKED = f'{PREFIX} not checked yet:'


def warnings(samples, options, screen=None):
    """
    Return a warning naming the fix when another convention fits far better, else [].

    It ends by saying not to use the estimate as configured (units.DO_NOT_USE). The rest as
    `_better_convention`. With fewer than CHECKED_FROM_SAMPLES samples, a warning that no
    convention can be ruled out yet (3 samples with the sensor poses inverted gave a
    plausible answer metres off, with no word).
    """
    if len(samples) < CHECKED_FROM_SAMPLES:
        return [f'{NOT_CHECKED} {len(samples)} samples fit every setup and invert_sensor '
                f'alike; from {CHECKED_FROM_SAMPLES} samples on a wrong one is named']
    return [f'{text}; {DO_NOT_USE} as configured'
            for text in _better_convention(samples, options, screen)]


def unchecked(convention_warnings):
    """Return whether the warnings of `warnings` say the convention was not checked yet."""
    return any(text.startswith(NOT_CHECKED) for text in convention_warnings)


def _better_convention(samples, options, screen=None):
    """
    Return the warning of `warnings` without its last words, or [].

    screen: the configured convention's misfit from the main fit (`misfit`), when there is
    one: a good fit there ends the check at no cost. Otherwise the configured convention is
    compared with the others by the same quick fit (the main fit screens bad detections, the
    quick ones do not, so their misfits are not comparable).
    """
    if screen is not None and _good(screen):
        return []
    arrays = _arrays(samples)
    quick = _quick_fits(arrays, options)
    if quick is None:
        return []
    fits = {convention: misfit(*found.residuals) for convention, found in quick.items()}
    current = fits.pop((options.setup, options.invert_sensor))
    if _good(current):
        return []
    reordered = _quaternion_order(arrays, options, current)
    if reordered:   # (no convention fits such poses: its advice would mislead)
        return [reordered]
    others = fits
    best = min(others, key=lambda k: _score(others[k]))
    rotation, position = current
    if _score(current) < BETTER_FACTOR * _score(others[best]):
        return []
    said = (f'{PREFIX} the samples fit badly as configured (median residual '
            f'{rotation:.2f} deg, {position:.1f} mm) but well as')
    mirror = _mirror(*best)
    if mirror in others and _score(others[mirror]) < MIRROR_FACTOR * _score(others[best]):
        noise = {k: _refined_noise(quick[k]) for k in (best, mirror)}
        best, mirror = sorted((best, mirror), key=noise.get)
        if not noise[mirror] > MIRROR_DECISIVE * noise[best]:
            return [f'{said} {_name(*best)} ({_fit_text(others[best])}) and as '
                    f'{_name(*mirror)} ({_fit_text(others[mirror])}), mirror images of each '
                    'other (the same equations with the mounting and the observed object '
                    'swapped) that these data cannot tell apart: either '
                    f'{fix(options, *best)}, or {fix(options, *mirror)}; the right one '
                    "answers with where the sensor is mounted, the other with the object's "
                    'pose']
        worse = (f'{_fit_text(others[mirror])}; its refined noise '
                 f'{noise[mirror] / noise[best]:.1f}x as large')
    elif mirror in others and _good(others[mirror]):
        worse = _fit_text(others[mirror])
    else:
        return [f'{said} {_name(*best)} ({_fit_text(others[best])}): {fix(options, *best)}']
    # Which of the two is right follows from where the noise is: the sensor's, assumed here.
    return [f'{said} {_name(*best)} ({_fit_text(others[best])}): {fix(options, *best)}. '
            f'Its mirror image, {_name(*mirror)}, also fits ({worse}); if the noise is mostly '
            "in the robot's poses rather than the sensor's, the mirror may be the right one "
            f'instead: then {fix(options, *mirror)}']


# Quaternions read in the wrong component order: (internal w, x, y, z) rolled by this to
# undo it, and what was written where. Written (w, x, y, z) into columns read as (x, y, z, w)
# (a file's or message's order) they read as (z, w, x, y).
# The advice: every file and message holds x, y, z, w; only a program that builds the
# package's poses itself (w, x, y, z) can make the second mistake.
ORDERS = ((-1, '(w, x, y, z)', '(x, y, z, w)',
           'write each quaternion as x, y, z, w (the columns qx, qy, qz, qw of a file; x, y, '
           'z, w of a message), or check the conversion that made them'),
          (1, '(x, y, z, w)', '(w, x, y, z)',
           "a program that builds the package's poses itself gives their quaternions as "
           '(w, x, y, z)'))


def _quaternion_order(arrays, options, current):
    """
    Return a warning when the configured fit is good with some quaternions reordered, or ''.

    The link's, the sensor's or both, each order of ORDERS, under the configured convention:
    good (_good) and BETTER_FACTOR better than as given.
    """
    link_q, link_t, sensor_q, sensor_t = arrays
    found = []
    for shift, written, read, advice in ORDERS:
        rolled = (np.roll(link_q, shift, axis=1), np.roll(sensor_q, shift, axis=1))
        for which, (lq, sq) in (('link', (rolled[0], sensor_q)),
                                ('sensor', (link_q, rolled[1])), ('link and sensor', rolled)):
            fit = misfit(*_quick_fit((lq, link_t, sq, sensor_t), options.setup,
                                     options.invert_sensor).residuals)
            if _good(fit) and _score(current) >= BETTER_FACTOR * _score(fit):
                found.append((_score(fit), which, written, read, advice, fit))
    if not found:
        return ''
    _, which, written, read, advice, fit = min(found)
    return (f'the {which} quaternions look to be written in {written} order where {read} is '
            f'read: reordered, the samples fit well ({_fit_text(fit)}), as given badly '
            f'({_fit_text(current)}); {advice}. No setup or frame convention fits them as '
            'given')


def _fit_text(fit):
    return f'{fit[0]:.2f} deg, {fit[1]:.1f} mm'


def _good(fit):
    return fit[0] < SUSPICIOUS_RESIDUAL_DEG and fit[1] < SUSPICIOUS_POSITION_MM


def _score(fit):
    return max(fit[0], FLOOR_DEG) * max(fit[1], FLOOR_MM)


def _name(setup, invert):
    return setup + (' with the sensor poses inverted' if invert else '')


def fix(options, setup, invert):
    """
    Return what to change in `options` for setup and invert_sensor `invert`: its words.

    The setting, then the node's parameter and the offline tools' option (the core serves
    both).
    """
    words = []
    if setup != options.setup:
        words.append(f'set setup to {setup} (the node: setup:={setup}; the offline tools: '
                     f'--setup {setup})')
    if invert != options.invert_sensor:
        words.append('the sensor poses are inverted (the sensor in the object frame instead of '
                     'the object in the sensor frame): set invert_sensor to true (the node: '
                     'invert_sensor:=true; the offline tools: --invert-sensor)' if invert else
                     'the sensor poses are not inverted: set invert_sensor to false (the node: '
                     'invert_sensor:=false; the offline tools: drop --invert-sensor, or '
                     '--no-invert-sensor for a journal recorded with invert_sensor true)')
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


def _mirror(setup, invert):
    """Return the convention whose equations are these with mounting and object swapped."""
    return SETUPS[1 - SETUPS.index(setup)], not invert


def _refined_noise(quick):
    """Return the Gaussian joint refinement's rotation noise (deg) x translation noise (mm)."""
    rotations, positions = quick.rotations, quick.positions
    try:
        found = refine(rotations.link, positions.link, rotations.sensor, positions.sensor,
                       quick.q_z, quick.translation.translation, robust=False,
                       link_R=rotations.link_matrices)
    except np.linalg.LinAlgError:
        return math.inf
    return found.rotation_noise_deg * found.translation_noise_mm


@dataclass(frozen=True)
class _QuickFit:
    """The samples as a convention sees them, and its quick rotation and translation."""

    rotations: SampleRotations
    positions: SamplePositions
    q_z: np.ndarray
    translation: object           # solve_translation's answer

    @property
    def residuals(self):
        """Return the rotation and the position residuals, (N, 3) each, as `misfit` takes them."""
        return (quality.sample_residuals(self.rotations, self.q_z),
                self.translation.residuals)


def _quick_fit(arrays, setup, invert):
    """Return the _QuickFit of a convention."""
    link_q, link_t, sensor_q, sensor_t = arrays
    use = np.ones(len(link_q), dtype=bool)
    rotations = SampleRotations.from_arrays(link_q, sensor_q, setup, invert)
    positions = SamplePositions.from_arrays(link_t, sensor_t, rotations)
    # Every sample may anchor the signs: the quick fit does not screen bad detections.
    q_z = all_pairs_rotation(rotations, use, anchors=CHECK_SAMPLES)
    info = quality.Information.all_pairs(rotations.link_matrices, use)
    return _QuickFit(rotations, positions, q_z,
                     solve_translation(rotations, positions, q_z, info, use))


def _quick_fits(arrays, options):
    """
    Return each convention's _QuickFit, or None.

    {(setup, invert_sensor): _QuickFit}, for the four conventions, or two when the sensor
    poses cannot be inverted (`inversions`); their `misfit` scores them. arrays: `_arrays` of
    the samples. Each fit is the least squares of all
    pairs (leastsq.py) and the closed-form translation (translation.py), without the
    screening of bad detections. None when fewer than three motions are large enough to
    inform (the same for every convention: so are their angles).
    """
    link_q, link_t, sensor_q, sensor_t = arrays
    i, j = pair_indices(len(link_q))
    smallest = np.minimum(pair_angles(link_q)[i, j], pair_angles(sensor_q)[i, j])
    if np.count_nonzero(smallest >= np.radians(options.min_motion_deg)) < 3:
        return None
    return {(setup, invert): _quick_fit(arrays, setup, invert)
            for setup in SETUPS for invert in inversions(options)}


def inversions(options):
    """Return the invert_sensor values the sensor poses may have: both, or as configured."""
    return (False, True) if options.sensor_invertible else (options.invert_sensor,)


def exchanged_warnings(setup, translation, object_position):
    """Return a warning when an eye-in-hand answer looks like exchanged link and sensor poses."""
    if setup != 'eye_in_hand' or object_position is None:
        return []
    mounting, distance = float(np.linalg.norm(translation)), float(np.linalg.norm(object_position))
    if not (mounting > LONG_MOUNTING_M and mounting > EXCHANGED_RATIO * distance):
        return []
    return [f'the mounting comes out {mounting:.2f} m long while the observed object is only '
            f"{distance:.2f} m from the origin of the link poses' frame (the robot base): for "
            'a sensor on the link, the two look exchanged. Are the link and sensor poses '
            'swapped (the link_pose and sensor_pose topics, or the columns of a file), or the '
            'sensor poses inverted (invert_sensor)? '
            "Exchanged, they fit exactly as well, and the answer is the object's pose instead "
            'of the mounting (if the link poses are in a world frame whose origin is near the '
            'object, this may be right)']


def rigid_fit_warnings(residual_rms_deg, translation_noise_mm, robust=True):
    """
    Return a loud warning when the residuals are too large for any rigid mounting.

    robust: whether bad detections were screened (else the advice says to screen them).
    """
    if not residual_rms_deg > NOT_RIGID_DEG:
        return []
    screened = ('that most detections are good (the screening of bad ones needs a majority '
                'of good samples)' if robust else
                'that bad detections are screened (do not use --no-robust, or robust:=false '
                'on the node, on such data)')
    return [f'the samples do not fit a rigid mounting: residual {residual_rms_deg:.1f} deg RMS '
            f'(position scatter {translation_noise_mm:.0f} mm per axis). Check that the '
            'sensor is fixed where the setup says, that the link and sensor poses belong to '
            f'the same moments, and {screened}; {DO_NOT_USE}']
