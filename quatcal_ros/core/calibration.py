"""
Estimate the sensor mounting rotation A_z from still samples: robust, with quality figures.

Pipeline (one function, `calibrate`, used by the node, the bag replay and the CSV tool through
`Calibrator` / session.Session):
1. motions from the samples, all pairs or consecutive pairs (motions.py, eq. (35)-(36));
2. screening: motions too small to inform, and (robust mode) motions whose rotation angles
   theta_a and theta_b disagree (A_a and A_b must be similar matrices, Lemma 4 of Shiu and
   Ahmad; erratum 3 of the paper);
3. (robust) a consensus search whose minimal solver is the paper's two-motion method
   (solver.solve_two_motions), scored by the median sample residual (least median of squares,
   so no threshold has to be guessed);
4. (robust) rejection of bad samples: a bad detection spoils every motion it takes part in,
   so samples, not only motions, are tested, by their residual in the base frame;
5. least squares over the remaining motions (leastsq.py, stacked eq. (41));
6. quality: per-motion residuals, RMS residual, uncertainty and excitation (quality.py).

Quaternions are (w, x, y, z).  The answer is the rotation of T_link_sensor (eye-in-hand) or
T_base_sensor (eye-to-hand).
"""

from dataclasses import dataclass, field, replace

import numpy as np

from quatcal_ros.core import quality
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.leastsq import least_squares_rotation, MotionSystem
from quatcal_ros.core.motions import Motions, pair_indices, PAIRINGS, SampleRotations
from quatcal_ros.core.refine import refine, refine_from
from quatcal_ros.core.solver import DegenerateMotionError, solve_two_motions
from quatcal_ros.core.translation import SamplePositions, solve_translation
from quatcal_ros.core.units import SETUPS

# Quantile of the chi distribution with 3 degrees of freedom at 99.9 %: a sample whose residual
# angle exceeds 4.03 sigma is an outlier with 0.1 % false alarms.
CHI3_999 = 4.03
# Median of the chi distribution with 3 degrees of freedom (median angle / sigma).
CHI3_MEDIAN = 1.5382
# Smallest outlier threshold (radians): below it, differences are rounding, not bad data.
MIN_OUTLIER_THRESHOLD = 1e-6
# Median motion residual (degrees) above which the frame conventions are checked.
SUSPICIOUS_RESIDUAL_DEG = 0.5
# Motions used to estimate the scale of |theta_a - theta_b| (a median needs no more).
MISMATCH_SCALE_MOTIONS = 20000
# Minimum axis separation (degrees) of the two motions of a consensus hypothesis.
HYPOTHESIS_AXIS_SEPARATION_DEG = 20.0


class InsufficientDataError(DegenerateMotionError):
    """Too few samples or usable motions to determine the rotation."""


METHODS = ('refined', 'closed-form')


@dataclass(frozen=True)
class CalibrationOptions:
    """How to turn samples into an estimate (plain numbers; the node freezes its params here)."""

    setup: str = 'eye_in_hand'          # or 'eye_to_hand'
    pairs: str = 'all'                  # or 'consecutive'
    robust: bool = True
    invert_sensor: bool = False         # the sensor poses are the sensor in the object frame
    min_motion_deg: float = 5.0         # smaller motions carry too little information
    max_angle_mismatch_deg: float = 5.0  # upper bound of |theta_a - theta_b| of a good motion
    min_axis_spread_deg: float = 2.0    # motion axes closer to parallel than this: Case 1
    hypotheses: int = 32                # consensus-search trials (P(all bad) ~ 1e-15)
    seed: int = 0                       # fixed, so the same data always give the same answer
    method: str = 'refined'             # or 'closed-form' (Chou-Kamel + closed-form translation)

    def __post_init__(self):
        """Refuse a value outside its choices (ValueError naming field, value and choices)."""
        for name, choices in (('setup', SETUPS), ('pairs', PAIRINGS), ('method', METHODS)):
            value = getattr(self, name)
            if value not in choices:
                raise ValueError(f'{name} must be one of {", ".join(choices)}, not {value!r}')


# The joint refinement needs enough samples to estimate both noise levels (6 unknowns each
# for the mounting and the object, 6 residuals per sample).
MIN_REFINE_SAMPLES = 6


@dataclass(frozen=True)
class Estimate:
    """One estimate of the mounting: rotation (w, x, y, z), translation (m), uncertainties."""

    quaternion: np.ndarray
    translation: np.ndarray
    uncertainty_deg: float
    translation_uncertainty_mm: float

    def to_json_dict(self):
        """Return rotation {x, y, z, w}, translation {x, y, z} and the uncertainties."""
        x, y, z, w = quat.xyzw_from_wxyz(self.quaternion)
        return {'rotation': {'x': float(x), 'y': float(y), 'z': float(z), 'w': float(w)},
                'translation': dict(zip('xyz', (float(v) for v in self.translation))),
                'uncertainty_deg': _finite_or_none(self.uncertainty_deg),
                'translation_uncertainty_mm': _finite_or_none(self.translation_uncertainty_mm)}


@dataclass(frozen=True)
class CalibrationResult:
    """The estimate and everything needed to judge it."""

    quaternion: np.ndarray          # (w, x, y, z), w >= 0
    matrix: np.ndarray              # 3x3
    samples: int
    motions: int                    # motions formed from the samples
    inliers: int                    # motions used in the final least squares
    inlier_samples: int
    residual_rms_deg: float         # RMS of the per-motion residual angles (inliers)
    uncertainty_deg: float          # expected RMS error angle, sqrt(trace(cov))
    noise_deg: float                # estimated per-axis rotation noise of one sample
    excitation: float               # weakest / strongest information eigenvalue, 0..1
    weakest_axis: np.ndarray        # unit axis (parent frame) that is least determined
    hint: str
    setup: str
    pairs: str
    rejected: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    motion_residuals_deg: np.ndarray = None   # per inlier motion
    translation: np.ndarray = None  # (3,) metres, of the published estimate
    translation_uncertainty_mm: float = float('nan')
    translation_noise_mm: float = float('nan')   # per-axis noise of one sample's position
    method: str = 'closed-form'     # which estimate the top-level fields hold
    closed_form: Estimate = None    # Chou-Kamel rotation and closed-form translation
    refined: Estimate = None        # the joint refinement, when it ran

    def to_json_dict(self):
        """Return the JSON object of DESIGN.md contract 3 (plus extra keys, never renamed)."""
        x, y, z, w = quat.xyzw_from_wxyz(self.quaternion)
        return {
            'rotation': {'x': float(x), 'y': float(y), 'z': float(z), 'w': float(w)},
            'matrix': [[float(v) for v in row] for row in self.matrix],
            'samples': self.samples,
            'motions': self.motions,
            'inliers': self.inliers,
            'residual_rms_deg': _finite_or_none(self.residual_rms_deg),
            'uncertainty_deg': _finite_or_none(self.uncertainty_deg),
            'rejected': self.rejected,
            'warnings': self.warnings,
            'setup': self.setup,
            'pairs': self.pairs,
            'inlier_samples': self.inlier_samples,
            'noise_deg': _finite_or_none(self.noise_deg),
            'excitation': self.excitation,
            'weakest_axis': [float(v) for v in self.weakest_axis],
            'hint': self.hint,
            'translation': dict(zip('xyz', (float(v) for v in self.translation))),
            'translation_uncertainty_mm': _finite_or_none(self.translation_uncertainty_mm),
            'translation_noise_mm': _finite_or_none(self.translation_noise_mm),
            'method': self.method,
            'closed_form': self.closed_form.to_json_dict(),
            'refined': self.refined.to_json_dict() if self.refined else None,
        }


def _finite_or_none(value):
    return float(value) if np.isfinite(value) else None


def calibrate(samples, options=CalibrationOptions()):
    """
    Estimate A_z from still samples (list of pose.Sample); see the module docstring.

    Raises DegenerateMotionError (a ValueError) with the reason and the motion that would
    help when the samples cannot determine the rotation.
    """
    return _solve(samples, options).result


@dataclass(frozen=True)
class _Fit:
    """
    The closed-form fit of the samples: what an estimate is made of, and an update extends.

    All per-sample arrays cover every sample; sample_ok marks those the fit uses.
    """

    rotations: SampleRotations
    positions: SamplePositions
    sample_ok: np.ndarray        # bool per sample
    inliers: Motions             # the motions of the final least squares
    system: MotionSystem         # their normal matrix
    info: quality.Information    # their H, G, C
    q_z: np.ndarray              # the closed-form (Chou-Kamel least-squares) rotation
    motion_count: int            # motions formed from the samples
    rejected: list
    warnings: list               # the frame-convention warnings of the last full solve
    mismatch_limit: float        # radians, |theta_a - theta_b| screen
    outlier_threshold: float     # radians, sample residual test


@dataclass(frozen=True)
class _Solution:
    """An estimate: its fit, its CalibrationResult and the refinement it publishes (or None)."""

    fit: _Fit
    result: CalibrationResult
    refinement: object           # refine.Refinement or None: the start of warm-started steps


def _solve(samples, options):
    """Run the full pipeline of the module docstring on `samples`; return its _Solution."""
    n = len(samples)
    if n < 3:
        raise InsufficientDataError(
            f'{n} sample(s): at least 3 are needed (two motions about different axes); '
            'move the robot to new poses, rotating the link by 20-40 degrees each time')
    rotations = SampleRotations.from_samples(samples, options.setup, options.invert_sensor)
    motions = Motions.between(rotations, *pair_indices(n, options.pairs))
    usable, limit = _screen(motions, options)
    sample_ok = np.ones(n, dtype=bool)
    try:
        if options.robust:
            q_z = _consensus(rotations, motions.subset(usable), options)
            for _ in range(2):
                sample_ok = _good_samples(rotations, q_z)
                fit = motions.subset(usable & sample_ok[motions.i] & sample_ok[motions.j])
                _require_motions(fit, options)
                q_z = least_squares_rotation(fit.q_a, fit.q_b, reference=q_z)
        else:
            fit = motions.subset(usable)
            _require_motions(fit, options)
            q_z = least_squares_rotation(fit.q_a, fit.q_b)
        system = MotionSystem()
        system.add(fit.q_a, fit.q_b, reference=q_z if options.robust or _near_half_turns(fit)
                   else None)
        q_z = system.solve()[0]
        info = _check_excitation(rotations, fit, options)
    except DegenerateMotionError as error:
        raise type(error)(' '.join([str(error)] + convention_warnings(samples, options))) \
            from None
    warnings = convention_warnings(samples, options) if _suspicious(fit, q_z) else []
    rejected = (_rejected_motions(motions, usable, sample_ok, limit, options)
                + _rejected_samples(rotations, q_z, sample_ok, motions))
    threshold = (_outlier_threshold(np.linalg.norm(
        quality.sample_residuals(rotations, q_z, sample_ok)[sample_ok], axis=1))
        if options.robust else np.inf)
    return _estimate(_Fit(rotations, SamplePositions.from_samples(samples, rotations),
                          sample_ok, fit, system, info, q_z, len(motions), rejected, warnings,
                          limit, threshold), options)


def _suspicious(fit, q_z):
    """
    Whether the residuals are too large for the noise the angle mismatches show.

    Under the right convention the median residual is ~2.3 times the median |theta_a -
    theta_b| (3-D versus 1-D projections of the same noise); a wrong convention leaves the
    angles equal but the residuals at tens of degrees.
    """
    residual = np.median(fit.residual_angles(q_z))
    mismatch = np.median(np.abs(fit.angle_a - fit.angle_b))
    return residual > np.radians(SUSPICIOUS_RESIDUAL_DEG) and residual > 6.0 * mismatch


def _near_half_turns(motions):
    """Whether any motion is within ~6 deg of a half turn, where erratum 3's sign rule fails."""
    return bool(np.any(np.minimum(np.abs(motions.q_a[:, 0]), np.abs(motions.q_b[:, 0])) < 0.05))


def _screen(motions, options):
    """Motions usable for the estimate (bool mask) and the |theta_a - theta_b| limit."""
    angle_a, angle_b = motions.angle_a, motions.angle_b
    large = _usable(angle_a, angle_b, options.min_motion_deg, np.inf)
    limit = np.inf
    if options.robust and np.any(large[:MISMATCH_SCALE_MOTIONS]):
        # |theta_a - theta_b| of a good motion is Gaussian: 5 robust sigmas, within bounds.
        mismatch = np.abs(angle_a - angle_b)[:MISMATCH_SCALE_MOTIONS]
        sigma = np.median(mismatch[large[:MISMATCH_SCALE_MOTIONS]]) / 0.6745
        limit = np.clip(5.0 * sigma, np.radians(0.1), np.radians(options.max_angle_mismatch_deg))
    return _usable(angle_a, angle_b, options.min_motion_deg, limit), limit


def _usable(angle_a, angle_b, min_motion_deg, limit):
    """
    Return which motions are large enough (min_motion_deg) with angles within `limit`.

    angle_a, angle_b: the motions' rotation angles of link and sensor (radians); the smaller
    must reach min_motion_deg, and they may differ by at most `limit` (radians).
    """
    return ((np.minimum(angle_a, angle_b) >= np.radians(min_motion_deg))
            & (np.abs(angle_a - angle_b) <= limit))


def _rejected_motions(motions, usable, sample_ok, limit, options):
    """
    Give reasons for the screened-out motions between good samples.

    A rejected sample's own entry covers its motions.
    """
    rejected = []
    unexplained = motions.subset(~usable & sample_ok[motions.i] & sample_ok[motions.j])
    angles_a, angles_b = np.degrees(unexplained.angle_a), np.degrees(unexplained.angle_b)
    for i, j, a, b in zip(unexplained.i, unexplained.j, angles_a, angles_b):
        if min(a, b) < options.min_motion_deg:
            reason = (f'too small to inform: the link rotates {a:.2f} deg '
                      f'(minimum {options.min_motion_deg:g} deg)')
        else:
            reason = (f'rotation angles disagree: link {a:.2f} deg, sensor {b:.2f} deg '
                      f'(limit {np.degrees(limit):.2f} deg)')
        rejected.append({'motion': [int(i), int(j)], 'reason': reason})
    return rejected


def _consensus(rotations, candidates, options):
    """Least-median-of-squares consensus over two-motion hypotheses of the paper's method."""
    if len(candidates) < 2:
        raise InsufficientDataError(
            f'only {len(candidates)} usable motion(s): at least two motions about different '
            'axes are needed; rotate the link by 20-40 degrees about a new axis and stop')
    hypotheses = [least_squares_rotation(candidates.q_a, candidates.q_b)]
    rng = np.random.default_rng(options.seed)
    axes = candidates.axis_a
    min_cos = np.cos(np.radians(HYPOTHESIS_AXIS_SEPARATION_DEG))
    for _ in range(4 * options.hypotheses):
        if len(hypotheses) > options.hypotheses:
            break
        k1, k2 = rng.choice(len(candidates), size=2, replace=False)
        if abs(axes[k1] @ axes[k2]) > min_cos:
            continue
        A_a = quat.matrix_from_quaternion(candidates.q_a[[k1, k2]])
        A_b = quat.matrix_from_quaternion(candidates.q_b[[k1, k2]])
        try:
            solution = solve_two_motions(
                A_a[0], A_b[0], A_a[1], A_b[1], min_rotation=0.0, angle_tolerance=np.pi,
                min_axis_separation=0.0)
        except DegenerateMotionError:
            continue
        hypotheses.append(solution.quaternion)
    scores = [np.median(np.linalg.norm(quality.sample_residuals(rotations, q), axis=1))
              for q in hypotheses]
    return hypotheses[int(np.argmin(scores))]


def _outlier_threshold(angles):
    """
    Residual angle (radians) above which a sample is an outlier (robust chi-3 test).

    The residual angles of good samples follow sigma times a chi distribution with 3 degrees of
    freedom, shrunk by sqrt((3N - 6) / 3N) because six parameters were fitted to them.
    """
    n = len(angles)
    shrink = np.sqrt(max(3 * n - 6, 1) / (3 * n))
    sigma = np.median(angles) / (CHI3_MEDIAN * shrink)
    return max(CHI3_999 * sigma, MIN_OUTLIER_THRESHOLD)


def _good_samples(rotations, q_z):
    """Mark the samples whose object orientation agrees with the consensus (bool mask)."""
    ok = np.ones(len(rotations), dtype=bool)
    for _ in range(3):
        angles = np.linalg.norm(quality.sample_residuals(rotations, q_z, ok), axis=1)
        ok = angles <= _outlier_threshold(angles[ok])
    return ok


def _rejected_samples(rotations, q_z, sample_ok, motions):
    """Reasons for each rejected sample."""
    if np.all(sample_ok):
        return []
    angles = np.degrees(np.linalg.norm(
        quality.sample_residuals(rotations, q_z, sample_ok), axis=1))
    threshold = np.degrees(_outlier_threshold(np.radians(angles[sample_ok])))
    return [_sample_rejection(i, angles[i], threshold,
                              int(np.sum((motions.i == i) | (motions.j == i))))
            for i in np.flatnonzero(~sample_ok)]


def _sample_rejection(index, angle_deg, threshold_deg, spoiled):
    """Return the `rejected` entry of a bad sample."""
    return {'sample': int(index), 'reason': (
        f'its object orientation disagrees with the other samples by {angle_deg:.2f} deg '
        f'(threshold {threshold_deg:.2f} deg): a bad detection such as a marker flip; its '
        f'{spoiled} motions are not used')}


def _require_motions(fit, options):
    if len(fit) < 2:
        raise InsufficientDataError(
            f'only {len(fit)} usable motion(s) after screening: at least two motions about '
            'different axes are needed; rotate the link by 20-40 degrees about a new axis')


def _check_excitation(rotations, fit, options):
    """Information of the fitted motions; Case 1 (all axes parallel) is refused."""
    info = quality.Information.of(rotations.link_matrices, fit.i, fit.j)
    ratio, axis = info.excitation()
    if ratio < np.sin(np.radians(options.min_axis_spread_deg)) ** 2:
        frame = _parent_frame(options)
        raise DegenerateMotionError(
            f'Case 1: all {len(fit)} usable motions rotate about (nearly) the same axis, '
            f'{quality.nearest_axis_name(axis, frame)} ([{", ".join(f"{c:.2f}" for c in axis)}]'
            '), so the rotation about it is undetermined; '
            + quality.next_motion_hint(0.0, axis, frame))
    return info


def _parent_frame(options):
    return 'link' if options.setup == 'eye_in_hand' else 'base'


def _estimate(fit, options, previous=None):
    """
    Return the _Solution of `fit`: the published estimate with its quality figures.

    The closed form is the Chou-Kamel rotation fit.q_z with the closed-form translation. The
    joint refinement starts from it, or, given the previous refine.Refinement (an incremental
    update), takes one warm-started step from that; it is published when it lands near the
    closed form (_plausible), else the closed form is, with a warning.
    """
    rotations, positions, ok = fit.rotations, fit.positions, fit.sample_ok
    sigma = quality.noise_sigma(quality.sample_residuals(rotations, fit.q_z, ok)[ok])
    covariance = fit.info.covariance(sigma)
    translation = solve_translation(rotations, positions, fit.q_z, fit.info, ok, covariance)
    closed = Estimate(fit.q_z, translation.translation, quality.uncertainty_deg(covariance),
                      translation.uncertainty_mm)
    warnings = list(fit.warnings)
    refinement = None
    if options.method == 'refined' and np.sum(ok) >= MIN_REFINE_SAMPLES:
        arrays = (rotations.link[ok], positions.link[ok], rotations.sensor[ok],
                  positions.sensor[ok])
        refinement = (refine(*arrays, fit.q_z, translation.translation) if previous is None
                      else refine_from(previous, *arrays, rotations.link_matrices[ok]))
        if not _plausible(refinement, fit.q_z, closed.uncertainty_deg):
            refinement = None
            warnings.append('the joint refinement did not converge to a plausible answer: '
                            'the closed-form estimate is published instead')
    if refinement is None:
        refined, noise = None, (np.degrees(sigma), 1e3 * translation.noise_m)
    else:
        refined = Estimate(refinement.quaternion, refinement.translation,
                           refinement.uncertainty_deg, refinement.translation_uncertainty_mm)
        noise = (refinement.rotation_noise_deg, refinement.translation_noise_mm)
    return _Solution(fit, _report(fit, options, closed, refined, noise, warnings), refinement)


def _report(fit, options, closed, refined, noise, warnings):
    """Return the CalibrationResult: the published estimate with its quality figures."""
    published = refined or closed
    ratio, axis = fit.info.excitation()
    motion_residuals = np.degrees(quality.motion_residual_angles(
        fit.rotations, published.quaternion, fit.inliers.i, fit.inliers.j))
    return CalibrationResult(
        quaternion=published.quaternion, matrix=quat.matrix_from_quaternion(published.quaternion),
        samples=len(fit.rotations), motions=fit.motion_count, inliers=len(fit.inliers),
        inlier_samples=int(np.sum(fit.sample_ok)),
        residual_rms_deg=float(np.sqrt(np.mean(motion_residuals ** 2))),
        uncertainty_deg=published.uncertainty_deg,
        noise_deg=float(noise[0]), excitation=ratio, weakest_axis=axis,
        hint=quality.next_motion_hint(ratio, axis, _parent_frame(options)),
        setup=options.setup, pairs=options.pairs, rejected=fit.rejected, warnings=warnings,
        motion_residuals_deg=motion_residuals, translation=published.translation,
        translation_uncertainty_mm=published.translation_uncertainty_mm,
        translation_noise_mm=float(noise[1]), method='refined' if refined else 'closed-form',
        closed_form=closed, refined=refined)


def _plausible(refinement, q_closed, closed_uncertainty_deg):
    """
    Whether the refinement converged near the closed form (within 10 of its sigmas + 1 deg).

    The closed form's uncertainty counts as at least 0.01 deg, and as that when unknown (NaN).
    """
    if not (refinement.converged and np.all(np.isfinite(refinement.quaternion))):
        return False
    sigma_deg = closed_uncertainty_deg if closed_uncertainty_deg > 0.01 else 0.01
    moved = np.degrees(quat.angle_between(refinement.quaternion, q_closed))
    return bool(moved < 10.0 * sigma_deg + 1.0)


# --- frame-convention check -------------------------------------------------------------

CONVENTION_PAIRS = 2000   # pairs examined: plenty for a median, bounded cost


def convention_warnings(samples, options):
    """
    Warnings when the data fit far better with the sensor poses inverted.

    Under the right convention one rotation solves every motion; with the sensor poses
    inverted (the sensor in the object frame, as data/ethz_robot_arm_real stores
    them) or the link poses inverted (eye-to-hand data solved as eye-in-hand) the residuals
    grow to tens of degrees.  Rotation angles cannot tell (angle(L_i^T L_j) == angle(L_i L_j^T)),
    and rotations alone cannot tell an inverted sensor from the other setup either: eye-in-hand
    data fit (eye_to_hand, sensor inverted) exactly, with the object's orientation as answer.
    So the check compares the median residual of the configured convention with that of the
    inverted sensor and names both possible fixes.
    """
    current = _median_residual_deg(samples, options.setup, options.invert_sensor, options)
    other = _median_residual_deg(samples, options.setup, not options.invert_sensor, options)
    if (current is None or other is None or current < SUSPICIOUS_RESIDUAL_DEG
            or current < 3.0 * other):
        return []
    other_setup = 'eye_to_hand' if options.setup == 'eye_in_hand' else 'eye_in_hand'
    invert = ('the sensor poses are inverted (the sensor in the object frame instead of the '
              'object in the sensor frame): use --invert-sensor' if not options.invert_sensor
              else 'the sensor poses are not inverted: drop --invert-sensor')
    return [f'frame convention: the motions fit badly as configured (median residual '
            f'{current:.2f} deg) but well with the sensor poses inverted ({other:.2f} deg): '
            f'either {invert}, or the setup is {other_setup}: use --setup {other_setup}']


def _median_residual_deg(samples, setup, invert_sensor, options):
    """Median motion residual (degrees) of a plain least-squares fit under one convention."""
    rotations = SampleRotations.from_samples(samples, setup, invert_sensor)
    i, j = pair_indices(len(samples), 'all')
    if len(i) > CONVENTION_PAIRS:
        pick = np.random.default_rng(options.seed).choice(len(i), CONVENTION_PAIRS, False)
        i, j = i[pick], j[pick]
    motions = Motions.between(rotations, i, j)
    motions = motions.subset(np.minimum(motions.angle_a, motions.angle_b)
                             >= np.radians(options.min_motion_deg))
    if len(motions) < 3:
        return None
    q_z = least_squares_rotation(motions.q_a, motions.q_b)
    return float(np.degrees(np.median(motions.residual_angles(q_z))))


# Full solves come at least every 1/FULL_SOLVE_SHARE of the samples (Calibrator).
FULL_SOLVE_SHARE = 5


class Calibrator:
    """
    Samples in, an estimate of all of them out on request: what session.Session drives.

    add_sample and add_samples only store; estimate() brings the estimate up to date. One new
    sample is tested against the current estimate, its motions (one per earlier good sample)
    screened and added to the least-squares system and the information, and the refinement
    takes one warm-started step: no consensus search, no refit. The full robust pipeline of
    `calibrate` runs instead while the samples are few (up to `small`), on every
    `full_solve_step`-th sample (every `full_solve_every`-th up to 5 times that many samples,
    then spaced to a fifth of the samples, so an early misjudgement cannot persist and a long
    session stays fast), when there is no
    estimate to extend, and when several samples came since the last estimate (a file, a
    resumed session, a replay that asks once at the end: its answer is then that of
    `calibrate` on all the samples).
    """

    def __init__(self, options=CalibrationOptions(), full_solve_every=10, small=12):
        self.options = options
        self.full_solve_every = full_solve_every
        self.small = small
        self.reset()

    def reset(self):
        """Forget all samples and the estimate."""
        self.samples = []
        self.last_error = 'no samples yet'
        self._solution = None
        self._estimated = 0   # samples the last estimate() covered

    @property
    def due(self):
        """Return whether samples came since the last estimate()."""
        return len(self.samples) > self._estimated

    @property
    def result(self):
        """Return the CalibrationResult of the last estimate(), or None (no estimate)."""
        return self._solution.result if self._solution else None

    def add_sample(self, sample):
        """Add one still sample; estimate() takes it into account."""
        self.samples.append(sample)

    def add_samples(self, samples):
        """Add many samples (a file, a resumed session); estimate() solves them all at once."""
        self.samples.extend(samples)

    def estimate(self):
        """Bring the estimate up to date with every sample (class docstring); return messages."""
        n = len(self.samples)
        new, self._estimated = n - self._estimated, n
        if not new:
            return []
        if (new == 1 and self._solution is not None and n > self.small
                and n % self.full_solve_step(n)):
            return self._add_incrementally(self.samples[-1])
        try:
            self._solution = _solve(self.samples, self.options)
        except DegenerateMotionError as error:
            self._solution = None
            self.last_error = str(error)
            return [f'no estimate yet: {error}']
        return []

    def full_solve_step(self, n):
        """
        Return the spacing of full solves at n samples.

        It is full_solve_every, doubled while the full solves would come more often than
        every 1/FULL_SOLVE_SHARE of the samples.  Early misjudgements are corrected often
        while they matter, and a large session does not pay an O(N^2) solve every few
        samples (at 200 samples: every 40th).
        """
        step = self.full_solve_every
        while step * FULL_SOLVE_SHARE < n:
            step *= 2
        return step

    def _add_incrementally(self, sample):
        old = self._solution.fit
        rotations = old.rotations.appended(sample)
        positions = old.positions.appended(sample, rotations)
        k = len(rotations) - 1
        q_z = self._solution.result.quaternion   # the published estimate
        newest = quat.multiply(quat.multiply(rotations.link[k], q_z), rotations.sensor[k])
        mean = quat.average(old.rotations.object_orientations(q_z)[old.sample_ok])
        angle = quat.angle_between(newest, mean)   # Z_k against the mean Z
        rejected = list(old.rejected)
        messages = []
        if angle > old.outlier_threshold:
            sample_ok = np.append(old.sample_ok, False)
            spoiled = int(np.sum(old.sample_ok)) if self.options.pairs == 'all' else 1
            rejected.append(_sample_rejection(k, np.degrees(angle),
                                              np.degrees(old.outlier_threshold), spoiled))
            messages.append(f'sample {k} rejected: {rejected[-1]["reason"]}')
            inliers, system, q_closed = old.inliers, old.system, old.q_z   # as before
            info = old.info.extended(rotations.link_matrices, [], [])
        else:
            sample_ok = np.append(old.sample_ok, True)
            new = self._new_motions(rotations, old, q_z)
            system = old.system.copy()
            system.add(new.q_a, new.q_b, reference=q_z)
            q_closed = system.solve()[0]
            inliers = Motions.concatenate(old.inliers, new)
            info = old.info.extended(rotations.link_matrices, new.i, new.j)
        fit = replace(old, rotations=rotations, positions=positions, sample_ok=sample_ok,
                      inliers=inliers, system=system, info=info, q_z=q_closed,
                      motion_count=old.motion_count + (k if self.options.pairs == 'all' else 1),
                      rejected=rejected)
        self._solution = _estimate(fit, self.options, self._solution.refinement)
        return messages

    def _new_motions(self, rotations, old, q_z):
        """Return the screened motions from the good samples of `old` to the newest sample."""
        k = len(rotations) - 1
        partners = np.flatnonzero(old.sample_ok)
        if self.options.pairs == 'consecutive':
            partners = partners[-1:]
        new = Motions.between(rotations, partners, np.full(len(partners), k))
        return new.subset(_usable(new.angle_a, new.angle_b, self.options.min_motion_deg,
                                  old.mismatch_limit))
