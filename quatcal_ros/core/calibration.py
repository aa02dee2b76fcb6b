"""
Estimate the sensor mounting A_z from still samples: robust, with quality figures.

Pipeline (one function, `calibrate`, used by the node, the bag replay and the CSV tool through
`Calibrator` / session.Session). Every step is O(N) in the samples:
1. the pairs of samples screened as motions (eq. (35)-(36)) for size and for rotation angles
   theta_a, theta_b that disagree (Lemma 4 of Shiu and Ahmad; erratum 3), from the angles
   alone, and the least squares of eq. (41) over all pairs without forming a motion
   (leastsq.all_pairs_rotation);
2. (robust) bad detections: a bad detection spoils every motion it takes part in, so samples
   are judged, by their object orientation in the base frame, against a heavy-tailed noise
   model fitted to all of them (heavy_tails.bad_detections). When a motion's angles or a
   sample disagree, a consensus search over two-motion hypotheses (what the paper's method
   solves, here by the least squares of eq. (41), for all at once) on a bounded set of
   candidate motions, scored by the median sample residual (least median of squares),
   restarts the judgement from a start no bad detection can pull; on clean samples it could
   only end where the least squares of all began, and is skipped;
3. the least squares of eq. (41) over all pairs of the good samples, or over consecutive
   pairs; the closed-form translation (translation.py);
4. the joint refinement of rotation and translation over the absolute poses (refine.py):
   anisotropic, heavy-tailed sensor noise estimated from the data, a sandwich covariance;
5. quality: residuals, uncertainty, excitation, leave-one-out validation (validation.py), and
   the frame-convention check over the whole fit (conventions.py).

Quaternions are (w, x, y, z). The answer is the rotation of T_link_sensor (eye-in-hand) or
T_base_sensor (eye-to-hand).
"""

from dataclasses import dataclass, field, replace
import math

import numpy as np

from quatcal_ros.core import conventions
from quatcal_ros.core import half_turns
from quatcal_ros.core import heavy_tails
from quatcal_ros.core import quality
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core import reduced_dof
from quatcal_ros.core import sensor_scale
from quatcal_ros.core.leastsq import all_pairs_rotation, b_matrices, least_squares_rotation, \
    MotionSystem, null_vectors
from quatcal_ros.core.motions import motion_count, Motions, pair_angles, pair_indices, \
    PAIRINGS, SampleRotations
from quatcal_ros.core.numerics import finite_or_none, median, random_integers
from quatcal_ros.core.pose import covariance_form_problem, inverse_perturbation, \
    residual_order
from quatcal_ros.core.refine import MAX_ITERATIONS, refine, uncertainties, with_jackknife_of
from quatcal_ros.core.solver import DegenerateMotionError
from quatcal_ros.core.translation import SamplePositions, solve_translation
from quatcal_ros.core.units import DO_NOT_USE, position_problem, SETUPS
from quatcal_ros.core.validation import not_enough_samples, Thresholds, validate

# Candidate motions of the consensus search: every pair up to this many, else the consecutive
# pairs and random others (a median needs no more).
CANDIDATE_MOTIONS = 2000
# Minimum axis separation (degrees) of the two motions of a consensus hypothesis.
HYPOTHESIS_AXIS_SEPARATION_DEG = 20.0
COS_HYPOTHESIS_SEPARATION = math.cos(math.radians(HYPOTHESIS_AXIS_SEPARATION_DEG))
# A refinement sample whose noise weight falls below this is reported as noisy.
NOISY_WEIGHT = 0.5
# Gauss-Newton steps of a warm-started refinement (between full solves).
WARM_ITERATIONS = 3
# Object residuals about the plain mean this many times wider (median angle) than about their
# median: bad detections pulled the mean, and the residuals are taken near the median instead.
RECENTRE_RATIO = 2.0


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
    # False for board poses from camera images (always the board in the camera frame): the
    # convention check then never asks for inverted sensor poses.
    sensor_invertible: bool = True
    min_motion_deg: float = 5.0         # smaller motions carry too little information
    max_angle_mismatch_deg: float = 5.0  # upper bound of |theta_a - theta_b| of a good motion
    min_axis_spread_deg: float = 2.0    # motion axes closer to parallel than this: Case 1
    hypotheses: int = 32                # consensus-search trials (P(all bad) ~ 1e-15)
    seed: int = 0                       # fixed, so the same data always give the same answer
    method: str = 'refined'             # or 'closed-form' (Chou-Kamel + closed-form translation)
    validation: Thresholds = field(default_factory=Thresholds)
    # The translation (m, x y z) along the directions reduced-DOF motions leave undetermined
    # (reduced_dof.py); None: zero, said loudly.
    known_translation: tuple = None

    def __post_init__(self):
        """
        Refuse a value outside its choices or range (ValueError naming field and value).

        The command lines and the node check their settings first; this guards the Python
        entry point (min_motion_deg NaN had raised an IndexError deep in the estimate).
        """
        for name, choices in (('setup', SETUPS), ('pairs', PAIRINGS), ('method', METHODS)):
            value = getattr(self, name)
            if value not in choices:
                raise ValueError(f'{name} must be one of {", ".join(choices)}, not {value!r}')
        for name, low, high in (('min_motion_deg', 0.0, 180.0),
                                ('max_angle_mismatch_deg', 0.0, 180.0),
                                ('min_axis_spread_deg', 0.0, 90.0)):
            value = getattr(self, name)
            if not low < value <= high:   # NaN too
                raise ValueError(f'{name} must lie in ({low:g}, {high:g}] degrees, not {value!r}')
        if not (isinstance(self.hypotheses, int) and self.hypotheses >= 1):
            raise ValueError(f'hypotheses must be a whole number >= 1, not {self.hypotheses!r}')
        if self.known_translation is not None:
            values = np.asarray(self.known_translation, dtype=float)
            problem = ('three numbers (x, y, z) in metres' if values.shape != (3,)
                       or not np.all(np.isfinite(values))
                       else position_problem(tuple(values.tolist())))
            if problem:
                raise ValueError(f'known_translation {self.known_translation!r}: {problem}')


# The half-turn alternatives the translations did not choose (_alternative_odds): counted in
# the uncertainty and said in a warning from this total probability on (below it a half-turn
# adds less than 0.006 deg to the expected error), and "do not use this estimate" from this
# one on.
HALF_TURN_DOUBT_SAID = 1e-9
HALF_TURN_DOUBT_UNUSABLE = 0.01

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
        return {'rotation': quat.xyzw_json(self.quaternion),
                'translation': quat.xyz_json(self.translation),
                'uncertainty_deg': finite_or_none(self.uncertainty_deg),
                'translation_uncertainty_mm': finite_or_none(self.translation_uncertainty_mm)}


@dataclass(frozen=True)
class CalibrationResult:
    """The estimate and everything needed to judge it."""

    quaternion: np.ndarray          # (w, x, y, z), w >= 0
    matrix: np.ndarray              # 3x3
    samples: int
    motions: int                    # motions formed from the samples
    inliers: int                    # motions between the good samples (the least squares')
    inlier_samples: int
    residual_rms_deg: float         # RMS residual angle of those motions (eq. (38))
    uncertainty_deg: float          # expected RMS error angle, sqrt(trace(cov))
    noise_deg: float                # estimated per-axis rotation noise of one sample
    excitation: float               # weakest / strongest information eigenvalue, 0..1
    weakest_axis: np.ndarray        # unit axis (parent frame) that is least determined
    hint: str
    setup: str
    pairs: str
    rejected: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    translation: np.ndarray = None  # (3,) metres, of the published estimate
    translation_uncertainty_mm: float = float('nan')
    translation_noise_mm: float = float('nan')   # per-axis noise of one sample's position
    method: str = 'closed-form'     # which estimate the top-level fields hold
    closed_form: Estimate = None    # Chou-Kamel rotation and closed-form translation
    refined: Estimate = None        # the joint refinement, when it ran
    noise_model: dict = None        # the fitted sensor noise (refine.py), JSON-ready
    noisy: list = field(default_factory=list)     # down-weighted samples
    validation: dict = None         # validation.validate's JSON object
    sample_ok: np.ndarray = None    # bool per sample: used (not a bad detection)
    # What the motions do not determine (reduced-DOF robots): [{what, direction, frame, reason}].
    unobservable: list = field(default_factory=list)
    # The scale of the sensor's positions that fits best (sensor_scale.py), or None.
    sensor_scale: object = None
    invert_sensor: bool = False     # as configured: the sensor poses were inverted
    # The fit on the board corners' pixels (vision/reprojection.py), JSON-ready, when the
    # top-level fields hold it (method reprojection); else None.
    reprojection: dict = None

    def sample_states(self, count):
        """Return 'used', 'noisy' (down-weighted) or 'rejected' for each of `count` samples."""
        ok = (np.ones(count, bool) if self.sample_ok is None
              else np.asarray(self.sample_ok, bool))
        states = ['used' if good else 'rejected' for good in ok]
        for item in self.noisy:
            if ok[item['sample']]:
                states[item['sample']] = 'noisy'
        return states

    @property
    def usable(self):
        """Return False when a warning says not to use this estimate (units.DO_NOT_USE)."""
        return not any(DO_NOT_USE in warning for warning in self.warnings)

    def to_json_dict(self):
        """Return the JSON object of DESIGN.md contract 3 (plus extra keys, never renamed)."""
        return {
            'rotation': quat.xyzw_json(self.quaternion),
            'matrix': [[float(v) for v in row] for row in self.matrix],
            'samples': self.samples,
            'motions': self.motions,
            'inliers': self.inliers,
            'residual_rms_deg': finite_or_none(self.residual_rms_deg),
            'uncertainty_deg': finite_or_none(self.uncertainty_deg),
            'rejected': self.rejected,
            'warnings': self.warnings,
            'setup': self.setup,
            'invert_sensor': self.invert_sensor,
            'pairs': self.pairs,
            'inlier_samples': self.inlier_samples,
            'noise_deg': finite_or_none(self.noise_deg),
            'excitation': self.excitation,
            'weakest_axis': [float(v) for v in self.weakest_axis],
            'hint': self.hint,
            'translation': quat.xyz_json(self.translation),
            'translation_uncertainty_mm': finite_or_none(self.translation_uncertainty_mm),
            'translation_noise_mm': finite_or_none(self.translation_noise_mm),
            'method': self.method,
            'closed_form': self.closed_form.to_json_dict(),
            'refined': self.refined.to_json_dict() if self.refined else None,
            'noise_model': self.noise_model,
            'noisy': self.noisy,
            'validation': self.validation,
            'unobservable': self.unobservable,
            'sensor_scale': (self.sensor_scale.to_json_dict()
                             if self.sensor_scale is not None else None),
            'usable': self.usable,
            **({'reprojection': self.reprojection} if self.reprojection is not None else {}),
        }


def calibrate(samples, options=CalibrationOptions()):
    """
    Estimate A_z from still samples (list of pose.Sample); see the module docstring.

    Every sample counts as a measurement: exact copies (a row written twice) are the caller's
    to drop, as session.Session does for the tools and the node.

    Raises DegenerateMotionError (a ValueError) with the reason and the motion that would
    help when the samples cannot determine the rotation.
    """
    return _solve(samples, options).result


@dataclass(frozen=True)
class _Fit:
    """The rotation stage: which samples are good, the closed-form rotation, its information."""

    q_z: np.ndarray              # the closed-form (Chou-Kamel least-squares) rotation
    sample_ok: np.ndarray        # bool per sample
    info: quality.Information    # of the motions the least squares used
    inliers: int                 # those motions
    residual_rms: float          # their RMS residual angle (radians)
    rejected: list
    residuals: np.ndarray        # (N, 3) quality.sample_residuals at q_z about the good ones
    object_orientation: np.ndarray   # the mean object orientation they are about


@dataclass(frozen=True)
class _Solution:
    """An estimate: its CalibrationResult and the refinement it publishes (or None)."""

    result: CalibrationResult
    refinement: object           # refine.Refinement or None: the start of warm-started steps
    # The full solve's frame-convention warnings, which stand through the warm solves after
    # it (they re-fit every convention: a full solve's work).
    convention: tuple = ()


def _solve(samples, options, previous=None):
    """
    Run the pipeline of the module docstring on `samples`; return its _Solution.

    previous: the _Solution of fewer of the same samples, or None. Given it, its published
    rotation replaces the consensus search and its refinement starts the new one (a warm
    solve, what the live calibrator runs between full solves).
    """
    n = len(samples)
    if n < 3:
        raise InsufficientDataError(
            f'{n} sample(s): at least 3 are needed (two motions about different axes); '
            'move the robot to new poses, rotating the link by 20-40 degrees each time')
    rotations = SampleRotations.from_samples(samples, options.setup, options.invert_sensor)
    positions = SamplePositions.from_samples(samples, rotations)
    start = previous.result.quaternion if previous is not None else None
    try:
        if options.pairs == 'all':
            fit = _all_pairs(rotations, options, start)
        else:
            fit = _consecutive(rotations, options, start)
    except DegenerateMotionError as error:
        advice = (conventions.warnings(samples, options)   # (not 'not checked yet' here)
                  if previous is None and n >= conventions.CHECKED_FROM_SAMPLES else [])
        motion = reduced_dof.reduced_motion(rotations, options.min_motion_deg)
        if motion is not None:   # a SCARA or a gantry: solve what the translations fix
            try:
                return _Solution(_reduced_result(samples, rotations, positions, motion,
                                                 options, check=previous is None), None)
            except reduced_dof.EssentialSampleError as reduced:
                advice.append(f'(The translations can fix it, but {reduced}.)')
            except DegenerateMotionError as reduced:   # (said once: 'nor can ... either')
                why = str(reduced).removeprefix(reduced_dof.NOT_EITHER)
                advice.append(f'(Nor can the translations fix it: {why}.)')
        raise type(error)(' '.join([str(error)] + advice)) from None
    return _estimate(samples, rotations, positions, fit, options, previous)


def _reduced_result(samples, rotations, positions, motion, options, check=True):
    """
    Return the CalibrationResult of reduced-DOF motions (reduced_dof.py).

    check: compare the other conventions too (a full solve; the live node's warm solves
    between full ones skip it, as the full-DOF path does).
    """
    found = reduced_dof.fit(rotations, positions, motion, options.known_translation)
    n = len(samples)
    deg, mm = uncertainties(found.covariance)
    model = uncertainties(found.model_covariance)
    spread, axes = np.linalg.eigh(found.covariance[:3, :3])
    frame = _parent_frame(options)
    given = options.known_translation is not None
    value = found.x_t @ found.undetermined.T
    if motion.kind == 'single_axis':
        reason = (f'every motion turns the link about this one axis (in the {frame} frame; a '
                  'SCARA-like robot): no motion shows the offset along it')
        what = (f'the link turns about one axis only, {_axis_text(motion.axis)} in the {frame} '
                'frame: the rotation comes from the translations, and the translation along '
                'that axis is not determined by the data')
    else:
        reason = 'the link never turns (a gantry): no motion shows the offset at all'
        what = ('the link never turns: the rotation comes from the translations alone, and '
                'the translation is not determined by the data at all')
    source = ('from known_translation' if given else
              'set to zero: measure it and give known_translation (--known-translation)')
    warning = (f'{what}; its value there ({", ".join(f"{v:.4f}" for v in value)} m) is '
               f'{source}; the uncertainty covers only what the data determine')
    rotation_rms = _all_pairs_rms(found.rotation_residuals)
    closed = Estimate(found.start_q, found.start_t, float('nan'), float('nan'))
    refined = Estimate(found.x_q, found.x_t, deg, mm)
    noise_deg, noise_mm = np.degrees(found.noise[0]), 1e3 * found.noise[3]
    rigid = conventions.rigid_fit_warnings(np.degrees(rotation_rms), noise_mm, options.robust)
    warnings = [warning, *rigid,
                *(_reduced_convention_warnings(samples, options, found.noise[3]) if check
                  else [])]
    return CalibrationResult(
        quaternion=found.x_q, matrix=quat.matrix_from_quaternion(found.x_q), samples=n,
        motions=motion_count(n, options.pairs), inliers=motion_count(n, options.pairs),
        inlier_samples=n, residual_rms_deg=float(np.degrees(rotation_rms)),
        uncertainty_deg=deg, noise_deg=float(noise_deg),
        excitation=float(spread[0] / spread[-1]) if spread[-1] > 0 else 0.0,
        weakest_axis=axes[:, -1],
        hint=('reduced-DOF motions (the link cannot turn freely): more positions spread across '
              'the workspace' + (', and turns by different angles,' if motion.kind == 'single_axis'
                                 else '') + ' reduce the uncertainty'),
        setup=options.setup, invert_sensor=options.invert_sensor, pairs=options.pairs,
        rejected=[], warnings=warnings,
        translation=found.x_t, translation_uncertainty_mm=mm,
        translation_noise_mm=float(noise_mm), method='refined', closed_form=closed,
        refined=refined,
        noise_model=_noise_json(np.full(3, noise_deg), np.full(3, noise_mm), np.eye(6),
                                math.inf, 'isotropic', False, 'sandwich', (deg, mm), model,
                                'none'),
        noisy=[], validation=validate(found.leave_one_out, np.arange(n), options.validation),
        sample_ok=np.ones(n, bool),
        unobservable=[{'what': 'translation', 'direction': [float(v) for v in d],
                       'frame': frame, 'reason': reason} for d in found.undetermined])


# Another convention fits reduced-DOF samples this much better (position scatter): say so.
CONVENTION_GAIN = 3.0


def _reduced_convention_warnings(samples, options, noise_m):
    """Name the setup and sensor direction under which reduced-DOF samples fit far better."""
    best = None
    for setup in SETUPS:
        for invert in conventions.inversions(options):
            if (setup, invert) == (options.setup, options.invert_sensor):
                continue
            rotations = SampleRotations.from_samples(samples, setup, invert)
            motion = reduced_dof.reduced_motion(rotations, options.min_motion_deg)
            if motion is None:
                continue
            try:
                fit = reduced_dof.fit(rotations,
                                      SamplePositions.from_samples(samples, rotations), motion)
            except (DegenerateMotionError, np.linalg.LinAlgError):
                continue
            if best is None or fit.noise[3] < best[0]:
                best = fit.noise[3], setup, invert
    if best is None or not best[0] * CONVENTION_GAIN < noise_m:
        return []
    scatter, setup, invert = best
    return [f'the samples fit a rigid mounting far better with setup {setup} and '
            f'invert_sensor {str(invert).lower()} ({conventions.fix(options, setup, invert)}): '
            f'position scatter {1e3 * scatter:.2g} mm against {1e3 * noise_m:.2g} mm as given; '
            'check the convention before using this estimate']


def _axis_text(axis):
    return '[' + ', '.join(f'{v:.2f}' for v in axis) + ']'


def _all_pairs_rms(residuals):
    """
    Return the RMS residual angle (radians) of all pairs' motions from the samples' residuals.

    Over all pairs, sum_{i<j} |e_j - e_i|^2 = K sum_i |e_i - mean|^2 (to first order the
    motion residual angle is |e_j - e_i|), over the K (K - 1) / 2 motions.
    """
    centred = residuals - residuals.mean(axis=0)
    return float(np.sqrt(2.0 * np.sum(centred ** 2) / max(len(residuals) - 1, 1)))


# --- rotation stage --------------------------------------------------------------------------

def _all_pairs(rotations, options, start):
    """Run the rotation stage over all pairs of samples (module docstring, steps 1-3)."""
    n = len(rotations)
    sample_ok, detections, residuals = np.ones(n, dtype=bool), None, None
    if start is None or not options.robust:   # (a warm start only skips the robust search)
        screen = _pair_screen(rotations, options)
        _require_motions(screen, options.min_motion_deg)
        q_z = all_pairs_rotation(rotations, sample_ok)
    if options.robust and start is None:
        # Samples whose motions' rotation angles all agree (a bad detection spoils most of
        # its motions' angles) and which all agree about the least squares of them all are
        # clean: the consensus search and a second round could only end where they began.
        if screen.consistent:
            detections, residuals, mean = _detections(rotations, q_z)
        if detections is None or detections.bad.any():
            candidates = (screen.candidates if screen.candidates is not None
                          else _candidates(rotations, options))
            q_z = _consensus(rotations, candidates, options,
                             least_squares_rotation(candidates.q_a, candidates.q_b))
            detections = residuals = None
            for _ in range(2):
                detections = _detections(rotations, q_z, detections)[0]
                sample_ok = ~detections.bad
                _require_samples(sample_ok)
                q_z = all_pairs_rotation(rotations, sample_ok, q_z)
    elif options.robust:   # a warm start (the last published rotation) is already clean
        detections = _detections(rotations, start)[0]
        sample_ok = ~detections.bad
        _require_samples(sample_ok)
        q_z = all_pairs_rotation(rotations, sample_ok, start)
    k = _count(sample_ok)
    info = _check_excitation(quality.Information.all_pairs(rotations.link_matrices, sample_ok),
                             motion_count(k), options)
    if residuals is None:
        residuals, mean = quality.object_residuals(rotations, q_z, sample_ok)
    good = residuals[sample_ok]
    return _Fit(q_z, sample_ok, info, motion_count(k), _all_pairs_rms(good),
                _rejected_samples(rotations, q_z, sample_ok, detections, 'all'), residuals, mean)


def _consecutive(rotations, options, start):
    """Run the rotation stage over consecutive pairs of samples only."""
    n = len(rotations)
    motions = Motions.between(rotations, *pair_indices(n, 'consecutive'))
    usable, limit, _ = _screen(motions, options)
    sample_ok, detections = np.ones(n, dtype=bool), None
    if options.robust:
        if start is None:
            fit = motions.subset(usable)
            _require_motions(fit, options.min_motion_deg)
            q_z = _consensus(rotations, fit, options, least_squares_rotation(fit.q_a, fit.q_b))
        else:
            q_z = start
        for _ in range(2):
            detections = _detections(rotations, q_z, detections)[0]
            sample_ok = ~detections.bad
            fit = motions.subset(usable & sample_ok[motions.i] & sample_ok[motions.j])
            _require_motions(fit, options.min_motion_deg)
            q_z = least_squares_rotation(fit.q_a, fit.q_b, reference=q_z)
    else:
        fit = motions.subset(usable)
        _require_motions(fit, options.min_motion_deg)
        q_z = least_squares_rotation(fit.q_a, fit.q_b)
    system = MotionSystem()
    system.add(fit.q_a, fit.q_b, reference=q_z if options.robust or _near_half_turns(fit)
               else None)
    q_z = system.solve()[0]
    info = _check_excitation(quality.Information.of(rotations.link_matrices, fit.i, fit.j),
                             len(fit), options)
    rejected = (_rejected_motions(motions, usable, sample_ok, limit, options)
                + _rejected_samples(rotations, q_z, sample_ok, detections, 'consecutive'))
    rms = float(np.sqrt(np.mean(fit.residual_angles(q_z) ** 2)))
    return _Fit(q_z, sample_ok, info, len(fit), rms, rejected,
                *quality.object_residuals(rotations, q_z, sample_ok))


def _count(mask):
    return int(np.sum(mask))


def _candidates(rotations, options):
    """Return the screened candidate motions of the consensus search (a bounded set)."""
    motions = Motions.between(rotations, *_candidate_pairs(len(rotations), options))
    return motions.subset(_screen(motions, options)[0])


def _candidate_pairs(n, options):
    """Return the sample pairs (i, j) of the candidate motions: all, or the consecutive first."""
    if motion_count(n) <= CANDIDATE_MOTIONS:
        return pair_indices(n, 'all')
    extra = max(CANDIDATE_MOTIONS - (n - 1), 0)
    a, b = random_integers(options.seed, (n, extra), (n - 1, extra))
    b = b + (b >= a)   # any other sample
    first = np.arange(n - 1)
    return (np.concatenate([first, np.minimum(a, b)])[:CANDIDATE_MOTIONS],
            np.concatenate([first + 1, np.maximum(a, b)])[:CANDIDATE_MOTIONS])


@dataclass(frozen=True)
class _PairScreen:
    """The screening of every pair of samples as motions, from their rotation angles alone."""

    usable: int           # motions usable for the estimate (_screen)
    consistent: bool      # no motion large enough to inform has angles that disagree
    candidates: Motions = None   # the screened candidate motions, when it formed them

    def __len__(self):
        return self.usable


def _pair_screen(rotations, options):
    """
    Screen all pairs of samples as `_screen` screens candidate motions, without forming one.

    The rotation angle of A_a = inv(link_i) link_j is 2 acos |link_i . link_j| (the quaternions'
    dot product is the cosine of half the angle between them), and that of A_b the same of the
    sensor quaternions: two N x N products give every pair's angles. Up to CANDIDATE_MOTIONS
    pairs; beyond, the candidates' motions are formed and screened (as _candidates), and kept
    for the consensus search.
    """
    n = len(rotations)
    if motion_count(n) > CANDIDATE_MOTIONS:
        motions = Motions.between(rotations, *_candidate_pairs(n, options))
        usable, _, consistent = _screen(motions, options)
        return _PairScreen(int(usable.sum()), consistent, motions.subset(usable))
    i, j = pair_indices(n)
    angle_a = pair_angles(rotations.link)[i, j]
    angle_b = pair_angles(rotations.sensor)[i, j]
    usable, _, consistent = _screen_angles(angle_a, angle_b, options)
    return _PairScreen(int(usable.sum()), consistent)


def _near_half_turns(motions):
    """Return whether a motion is within ~6 deg of a half turn (erratum 3's sign rule fails)."""
    return bool(np.any(np.minimum(np.abs(motions.q_a[:, 0]), np.abs(motions.q_b[:, 0])) < 0.05))


def _screen(motions, options):
    """
    Return the motions usable for the estimate (bool mask) and the |theta_a - theta_b| limit.

    And whether the limit screened none of those large enough to inform.
    """
    return _screen_angles(motions.angle_a, motions.angle_b, options)


def _screen_angles(angle_a, angle_b, options):
    """Return `_screen`'s answer for motions of these rotation angles (radians)."""
    large = _usable(angle_a, angle_b, options.min_motion_deg, np.inf)
    limit = np.inf
    if options.robust and np.any(large):
        # |theta_a - theta_b| of a good motion is Gaussian: 5 robust sigmas, within bounds.
        sigma = median(np.abs(angle_a - angle_b)[large]) / 0.6745
        limit = np.clip(5.0 * sigma, np.radians(0.1), np.radians(options.max_angle_mismatch_deg))
    usable = _usable(angle_a, angle_b, options.min_motion_deg, limit)
    return usable, limit, bool(np.array_equal(usable, large))


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
            reason = (f'too small to inform: the link rotates {a:.2f} deg, the sensor '
                      f'{b:.2f} deg (minimum {options.min_motion_deg:g} deg)')
        else:
            reason = (f'rotation angles disagree: link {a:.2f} deg, sensor {b:.2f} deg '
                      f'(limit {np.degrees(limit):.2f} deg)')
        rejected.append({'motion': [int(i), int(j)], 'reason': reason})
    return rejected


def _consensus(rotations, candidates, options, everything):
    """
    Return the least-median-of-squares consensus of two-motion hypotheses.

    Each hypothesis solves two candidate motions about axes at least
    HYPOTHESIS_AXIS_SEPARATION_DEG apart exactly (for exact data; the least squares of eq. (41)
    over the two, the answer of the paper's two-motion method, solved for every hypothesis at
    once), and is scored by the median residual of the samples' object orientations about
    their mean; `everything` (the least squares of all candidates) is a hypothesis too.
    """
    _require_motions(candidates, options.min_motion_deg)
    draws, = random_integers(options.seed, (len(candidates), (4 * options.hypotheses, 2)))
    first, second = candidates.q_a[draws[:, 0], 1:], candidates.q_a[draws[:, 1], 1:]
    # |cos| of the angle between the two motions' axes (their quaternions' vector parts)
    across = np.abs(np.einsum('ki,ki->k', first, second))
    lengths = np.sqrt(np.einsum('ki,ki->k', first, first) * np.einsum('ki,ki->k', second, second))
    separated = (draws[:, 0] != draws[:, 1]) & (across <= COS_HYPOTHESIS_SEPARATION * lengths)
    draws = draws[separated][:options.hypotheses]
    B = b_matrices(candidates.q_a[draws.ravel()], candidates.q_b[draws.ravel()])
    normal = (np.swapaxes(B, 1, 2) @ B).reshape(len(draws), 2, 4, 4).sum(axis=1)
    hypotheses = np.vstack([everything[None], null_vectors(normal, everything)])
    # Every hypothesis's object orientations Z_i = A_i p at once: (H, N, 4).
    Z = np.swapaxes(hypotheses @ np.swapaxes(rotations.matrices, 1, 2), 0, 1)
    return quat.canonical(hypotheses[int(np.argmin(median(_spread(Z), axis=1)))])


def _spread(Z, iterations=3):
    """
    Return sin^2(theta / 2) of each Z_hn (H, N, 4) from its set's mean, (H, N).

    The mean is sum_n Z_hn Z_hn^T's top eigenvector (quat.average) by power iteration: a set
    that fits one rotation has one large eigenvalue and the others at the noise, so a few
    products give it to rounding; for a scattered set (a poor hypothesis) the spread stays
    large whatever the mean. sin^2(theta / 2) orders the samples as theta does.
    """
    scatter = np.swapaxes(Z, 1, 2) @ Z
    # From the scatter's column of its largest diagonal entry: the direction most samples
    # share (a single sample could be a half-turn flip, orthogonal to all the others).
    largest = np.argmax(np.diagonal(scatter, axis1=1, axis2=2), axis=1)
    mean = np.take_along_axis(scatter, largest[:, None, None], axis=2)[..., 0]
    for _ in range(iterations):
        mean = (scatter @ mean[..., None])[..., 0]
        mean = mean / np.sqrt(np.einsum('hi,hi->h', mean, mean))[:, None]
    along = (Z @ mean[..., None])      # (H, N, 1)
    off = Z - along * mean[:, None, :]
    return np.einsum('hni,hni->hn', off, off)


def _detections(rotations, q_z, previous=None):
    """
    Judge every sample's object orientation against the others (heavy_tails.bad_detections).

    The residuals are taken about the mean orientation of the samples weighted by their
    probability of being good (all samples alike at first), so the verdicts never rest on a
    set trimmed by an earlier verdict; the earlier verdict's noise fit starts the EM. Returns
    the Detections, the residuals (N, 3) and the mean orientation they are about.
    """
    if previous is None:
        residuals, mean = _robustly_centred(rotations, q_z)
    else:
        Z = rotations.object_orientations(q_z)
        mean = quat.average(Z, previous.good_probability)
        residuals = quat.rotation_vector(quat.multiply(Z, quat.conjugate(mean)))
    return heavy_tails.bad_detections(residuals, start=previous), residuals, mean


def _robustly_centred(rotations, q_z):
    """
    Return quality.object_residuals about the mean, or about that of the samples near the median.

    A few bad detections pull the plain mean: two 70-deg flips among ten samples move it 13
    deg, every good sample then lies 13 deg from it, and the noise fitted to such residuals
    explains the flips. The coordinate-wise median of the residuals is not pulled; where the
    residuals' median angle about it is less than 1/RECENTRE_RATIO of that about the mean,
    the residuals are taken about the mean of the samples within START_SIGMAS robust sigmas
    of the median instead (clean samples: the two medians agree, nothing changes). Not with
    three samples, whose median is no firmer than their mean (the ratio passes 2 on 4 % of
    clean ones; from four samples on, on none of 400 clean cells at 0.5 deg).
    """
    residuals, mean = quality.object_residuals(rotations, q_z)
    if len(residuals) < 4:
        return residuals, mean
    about_mean = np.linalg.norm(residuals, axis=1)
    about_median = np.linalg.norm(residuals - median(residuals, axis=0), axis=1)
    spread = median(about_median)
    if not median(about_mean) > RECENTRE_RATIO * spread:
        return residuals, mean
    near = about_median <= heavy_tails.START_SIGMAS * spread / heavy_tails.CHI3_MEDIAN
    return quality.object_residuals(rotations, q_z, near)


def _rejected_samples(rotations, q_z, sample_ok, detections, pairs):
    """Return reasons for each bad detection; pairs: 'all' or 'consecutive' (its motions)."""
    if detections is None or np.all(sample_ok):
        return []
    n = len(sample_ok)
    angles = np.degrees(np.linalg.norm(
        quality.sample_residuals(rotations, q_z, sample_ok), axis=1))
    noise = detections.noise
    sigma_deg = np.degrees(np.sqrt(noise.covariance[0, 0]))
    return [_sample_rejection(i, angles[i], sigma_deg, noise.nu,
                              detections.good_probability[i],
                              n - 1 if pairs == 'all' else int(i > 0) + int(i < n - 1))
            for i in np.flatnonzero(~sample_ok)]


def _sample_rejection(index, angle_deg, sigma_deg, nu, good_probability, spoiled):
    """
    Return the `rejected` entry of a bad sample.

    Its `motion` is one of the motions it takes part in (with the sample before it; the first
    sample's with the one after it), for readers of contract 3's entries of rejected motions.
    """
    tails = 'Gaussian' if not np.isfinite(nu) else f't with {nu:g} degrees of freedom'
    index = int(index)
    return {'sample': index, 'motion': [index - 1, index] if index else [0, 1], 'reason': (
        f'its object orientation disagrees with the other samples by {angle_deg:.2f} deg, '
        f'which the fitted noise ({sigma_deg:.3f} deg per axis, {tails}) cannot explain '
        f'(probability of a good detection {good_probability:.1e}): a bad detection such as a '
        f'marker flip; '
        + (f'its {spoiled} motions are not used' if spoiled != 1 else 'its motion is not used'))}


def _require_samples(sample_ok):
    if _count(sample_ok) < 3:
        raise InsufficientDataError(
            f'only {_count(sample_ok)} sample(s) agree with each other: at least 3 are needed; '
            'check the detections and move the robot to new poses')


def _require_motions(fit, min_motion_deg):
    if len(fit) < 2:
        raise InsufficientDataError(
            f'only {len(fit)} usable motion(s) after screening: at least two motions about '
            'different axes are needed, each turning the link by at least min_motion_deg '
            f'({min_motion_deg:g} deg); rotate the link by 20-40 degrees about a new axis')


def _check_excitation(info, count, options):
    """Return info, refusing Case 1 (all motion axes parallel)."""
    ratio, axis = info.excitation()
    if ratio < np.sin(np.radians(options.min_axis_spread_deg)) ** 2:
        frame = _parent_frame(options)
        raise DegenerateMotionError(
            f'Case 1: all {count} usable motions rotate about (nearly) the same axis, '
            f'{quality.nearest_axis_name(axis, frame)} ({_axis_text(axis)}), so the rotation '
            'about it is undetermined; '
            + quality.next_motion_hint(0.0, axis, frame))
    return info


def _parent_frame(options):
    return 'link' if options.setup == 'eye_in_hand' else 'base'


# --- estimates -------------------------------------------------------------------------------

def _estimate(samples, rotations, positions, fit, options, previous):
    """
    Return the _Solution of the rotation stage `fit`: the estimates and their quality.

    The closed form is the Chou-Kamel rotation fit.q_z with the closed-form translation. The
    joint refinement starts from it (warm-started from `previous`'s, with a few steps, between
    full solves); it is published when it lands near the closed form (_plausible), else the
    closed form is, with a warning.
    """
    fit, half_turn_warnings, others = _settle_half_turns(rotations, positions, fit, options)
    ok = fit.sample_ok
    rotation_residuals = fit.residuals
    sigma = quality.noise_sigma(rotation_residuals[ok])
    covariance = fit.info.covariance(sigma)
    factor = quality.unknown_noise_factor(_count(ok))
    translation = solve_translation(rotations, positions, fit.q_z, fit.info, ok, covariance,
                                    factor)
    closed = _with_alternatives(Estimate(fit.q_z, translation.translation,
                                         quality.uncertainty_deg(covariance * factor),
                                         translation.uncertainty_mm), others)
    convention = (list(previous.convention) if previous is not None else conventions.warnings(
        samples, options, conventions.misfit(rotation_residuals, translation.residuals)))
    warnings = half_turn_warnings + convention
    if options.known_translation is not None:   # (a robot that turns freely needs none)
        warnings.append('known_translation is not used: the motions determine the whole '
                        'translation (it fills only what a SCARA or a gantry leaves open)')
    own = sensor_covariance_factors(samples, options.invert_sensor)
    if previous is None and own is None:
        warnings += _unused_covariances(samples)
    arrays = (rotations.link[ok], positions.link[ok], rotations.sensor[ok], positions.sensor[ok])
    refinement = None
    if _count(ok) >= MIN_REFINE_SAMPLES:
        warm = previous.refinement if previous is not None else None
        published = options.method == 'refined'   # its uncertainty is published: resample it
        refinement = refine(*arrays, fit.q_z, translation.translation, robust=options.robust,
                            link_R=rotations.link_matrices[ok],
                            start=warm, max_iterations=(MAX_ITERATIONS if warm is None
                                                        else WARM_ITERATIONS),
                            sensor_factor=None if own is None else own[ok],
                            resample=published and warm is None,
                            object_start=(fit.object_orientation, translation.object_position))
        if published and warm is not None:
            refinement = with_jackknife_of(refinement, warm)
    published_refinement = refinement if options.method == 'refined' else None
    if published_refinement is not None and not _plausible(refinement, closed):
        published_refinement = None
        warnings.append('the joint refinement did not converge to a plausible answer: '
                        'the closed-form estimate is published instead')
    refined = None if published_refinement is None else _with_alternatives(Estimate(
        refinement.quaternion, refinement.translation, refinement.uncertainty_deg,
        refinement.translation_uncertainty_mm), others)
    if refined is None:
        noise = (np.degrees(sigma), 1e3 * translation.noise_m)
    else:
        noise = (refinement.rotation_noise_deg, refinement.translation_noise_mm)
    answer = refined or closed
    scale = sensor_scale.fit(
        rotations.link_matrices[ok], positions.link[ok], positions.sensor[ok],
        quat.matrix_from_quaternion(answer.quaternion),
        None if refinement is None else refinement.noise_covariance[3:, 3:])
    # A scale is judged only where a rigid mounting fits: else the misfit is what it sees.
    fits = not convention and not np.degrees(fit.residual_rms) > conventions.NOT_RIGID_DEG
    if not (fits and sensor_scale.grossly_off(scale)):   # (its long mounting is the scale's)
        warnings += conventions.exchanged_warnings(
            options.setup, answer.translation,
            translation.object_position if refined is None else refinement.object_translation)
    warnings += [text for text in (sensor_scale.warning(scale),) if text and fits]
    millimetres = sensor_scale.all_in_millimetres(positions.link[ok], positions.sensor[ok])
    warnings += [millimetres] if millimetres else []
    result = _report(fit, options, closed, refined, noise, warnings, refinement, scale)
    return _Solution(result, refinement, tuple(convention))


def _settle_half_turns(rotations, positions, fit, options):
    """
    Return the rotation stage at the half-turn alternative whose translation fits best.

    And warnings that say so (half_turns: the rotations alone cannot tell the alternatives
    apart; the object positions they give can), and the other alternatives with their
    probabilities (_alternative_odds). `fit` itself, no warning and no alternative, for data
    without the ambiguity.
    """
    alike = half_turns.alternatives(rotations, fit.q_z, fit.sample_ok)
    if len(alike) == 1 and alike[0] is fit.q_z:
        return fit, [], []
    ok = fit.sample_ok
    scored = []
    for q in alike:
        translation = solve_translation(rotations, positions, q, fit.info, ok)
        scored.append((float(np.sqrt(np.mean(np.sum(translation.residuals[ok] ** 2, axis=1)))),
                       q, translation.translation))
    scored.sort(key=lambda item: item[0])
    best_m, q, _ = scored[0]
    residuals, mean = quality.object_residuals(rotations, q, ok)
    rms = _all_pairs_rms(residuals[ok]) if options.pairs == 'all' else fit.residual_rms
    if np.degrees(rms) > conventions.NOT_RIGID_DEG:   # no rotation fits: not this ambiguity
        return fit, [], []
    settled = replace(fit, q_z=q, residual_rms=rms, residuals=residuals, object_orientation=mean)
    if len(scored) == 1:   # the least squares had landed off the one that fits
        return settled, [], []
    others = _alternative_odds(scored, _count(ok))
    doubt = sum(p for p, _, _ in others)
    if doubt < HALF_TURN_DOUBT_SAID:   # the translations rule the others out
        if q is fit.q_z:
            return fit, [], []
        others = []
    said = (f'the motions are near half-turns: {len(scored)} rotations fit them alike (the '
            'rotations alone cannot tell them apart), and the translations chose this one '
            f'(object positions {1e3 * best_m:.1f} mm RMS from their mean, '
            f'{1e3 * scored[1][0]:.1f} mm at the next')
    if others:
        said += (f'; the others together keep a probability of {doubt:.2g}, which the '
                 'reported uncertainty includes')
    said += ')'
    if doubt >= HALF_TURN_DOUBT_UNUSABLE:
        said += (f'; too close to tell apart: {DO_NOT_USE}, add motions about '
                 'other axes that are not half-turns')
    return (fit if q is fit.q_z else settled), [said], others


def _alternative_odds(scored, count):
    """
    Return (probability, rotation, translation) of each half-turn alternative but the best.

    scored: (object positions' RMS scatter, rotation, translation) of every alternative, best
    first. With the position noise unknown, alternative k's likelihood goes as its residual
    sum of squares to the power -dof / 2 (dof = 3 count - 6: the residuals less the
    translation's and the object position's unknowns), so its probability against the others
    is proportional to (best RMS / its RMS)^dof.
    """
    dof = 3 * count - 6
    best = scored[0][0]
    odds = np.array([(best / m) ** dof if m > 0.0 else 1.0 for m, _, _ in scored])
    odds /= odds.sum()
    return [(float(p), q, t) for p, (_, q, t) in zip(odds[1:], scored[1:])]


def _with_alternatives(estimate, others):
    """
    Return `estimate` with its uncertainties widened by the half-turn alternatives it may be.

    When the translations could not rule an alternative out, the estimate is that far off with
    its probability: the expected squared error gains p_k times the squared distance to it
    (others: _alternative_odds).
    """
    if not others:
        return estimate
    angles = np.array([np.degrees(quat.angle_between(q, estimate.quaternion))
                       for _, q, _ in others])
    offsets = np.array([1e3 * np.linalg.norm(t - estimate.translation) for _, _, t in others])
    p = np.array([probability for probability, _, _ in others])
    return replace(
        estimate,
        uncertainty_deg=float(np.sqrt(estimate.uncertainty_deg ** 2 + p @ angles ** 2)),
        translation_uncertainty_mm=float(np.sqrt(estimate.translation_uncertainty_mm ** 2
                                                 + p @ offsets ** 2)))


def sensor_covariance_factors(samples, invert_sensor=False):
    """
    Return the Cholesky factors L_i (N, 6, 6) of the samples' own sensor covariances, or None.

    C_i = L_i L_i^T as refine weighs them (refine.whitening_of). Used only when every sample
    has one (Pose.covariance: ROS order, re-ordered to the residual's rotation, translation);
    with invert_sensor they are carried to the inverted poses (pose.inverse_perturbation):
    A_i C_i A_i^T = (A_i L_i)(A_i L_i)^T, whose factor is taken from the QR decomposition of
    (A_i L_i)^T without forming the product (formed, a covariance exact to a nanometre along
    one axis and a tenth of a radian across, which pose.covariance_problem takes, lost its
    smallest eigenvalue to rounding and was no longer positive definite). Raises ValueError
    naming the first sample whose covariance is not of its form (pose.covariance_form_problem)
    or not positive definite (the file and message readers refuse those, and more, before
    they get here: pose.covariance_problem).
    """
    given = [s.sensor.covariance for s in samples]
    if not given or any(c is None for c in given):
        return None
    for index, covariance in enumerate(given):
        problem = ('not 6x6' if np.shape(covariance) != (6, 6)
                   else covariance_form_problem(covariance))
        if problem:
            raise ValueError(f'sample {index}: its sensor covariance is unusable: {problem}')
    covariances = residual_order(np.array(given, dtype=float))
    try:
        factors = np.linalg.cholesky(covariances)
    except np.linalg.LinAlgError:
        for index, covariance in enumerate(covariances):
            try:
                np.linalg.cholesky(covariance)
            except np.linalg.LinAlgError:
                raise ValueError(f'sample {index}: its sensor covariance is unusable: not '
                                 'positive definite') from None
        raise
    if not invert_sensor:
        return factors
    A = inverse_perturbation(
        quat.matrix_from_quaternion(np.array([s.sensor.quaternion for s in samples])),
        np.array([s.sensor.position for s in samples]))
    upper = np.linalg.qr(np.transpose(A @ factors, (0, 2, 1)), mode='r')   # (A L)^T = Q U
    signs = np.sign(np.diagonal(upper, axis1=1, axis2=2))
    return np.transpose(signs[:, :, None] * upper, (0, 2, 1))   # U^T U = A C A^T, diagonal > 0


def _unused_covariances(samples):
    """Return a warning when some samples give a covariance that is not used (not all do)."""
    given = sum(s.sensor.covariance is not None for s in samples)
    if not given:
        return []
    return [f'{given} of {len(samples)} samples give their own sensor covariance: one is used '
            'only when every sample gives one, so all are weighed by the fitted noise model']


def _report(fit, options, closed, refined, noise, warnings, refinement, scale=None):
    """Return the CalibrationResult: the published estimate with its quality figures."""
    published = refined or closed
    ratio, axis = fit.info.excitation()
    used = np.flatnonzero(fit.sample_ok)
    warnings = warnings + conventions.rigid_fit_warnings(np.degrees(fit.residual_rms),
                                                         noise[1], options.robust)
    return CalibrationResult(
        quaternion=published.quaternion, matrix=quat.matrix_from_quaternion(published.quaternion),
        samples=len(fit.sample_ok), motions=motion_count(len(fit.sample_ok), options.pairs),
        inliers=fit.inliers, inlier_samples=len(used),
        residual_rms_deg=float(np.degrees(fit.residual_rms)),
        uncertainty_deg=published.uncertainty_deg,
        noise_deg=float(noise[0]), excitation=ratio, weakest_axis=axis,
        hint=quality.next_motion_hint(ratio, axis, _parent_frame(options)),
        setup=options.setup, invert_sensor=options.invert_sensor, pairs=options.pairs,
        rejected=fit.rejected, warnings=warnings,
        translation=published.translation,
        translation_uncertainty_mm=published.translation_uncertainty_mm,
        translation_noise_mm=float(noise[1]), method='refined' if refined else 'closed-form',
        closed_form=closed, refined=refined,
        noise_model=_noise_model(refinement, options.robust),
        noisy=_noisy(refinement, used) if options.robust else [],
        validation=(validate(refinement.leave_one_out, used, options.validation)
                    if refinement is not None else
                    not_enough_samples(len(used), MIN_REFINE_SAMPLES, options.validation)),
        sample_ok=fit.sample_ok, sensor_scale=scale)


def _noise_model(refinement, robust):
    """Return the fitted sensor noise as JSON: per-axis RMS, correlation, tail weight."""
    if refinement is None:
        return None
    covariance = refinement.noise_covariance
    sd = np.sqrt(np.diag(covariance))
    correlation = covariance / np.outer(sd, sd)
    np.fill_diagonal(correlation, 1.0)   # (by definition; the division left 1 - 1e-16)
    return _noise_json(np.degrees(sd[:3]), 1e3 * sd[3:], correlation,
                       refinement.noise.nu, refinement.noise.shape.name, robust,
                       _uncertainty_source(refinement), uncertainties(refinement.covariance),
                       uncertainties(refinement.model_covariance),
                       'input' if refinement.whitening is not None else 'none')


def _noise_json(rotation_deg, translation_mm, correlation, nu, shape, robust, source,
                sandwich, model, sample_covariances):
    """Return the "noise_model" JSON object: per-axis noise, its shape, the uncertainties."""
    return {'rotation_noise_deg': np.asarray(rotation_deg, dtype=float).tolist(),
            'translation_noise_mm': np.asarray(translation_mm, dtype=float).tolist(),
            'frame': 'sensor',
            'sample_covariances': sample_covariances,
            'correlation': np.asarray(correlation, dtype=float).tolist(),
            'tail_degrees_of_freedom': finite_or_none(nu),
            'distribution': ('gaussian' if not np.isfinite(nu) else 'student_t'),
            'shape': shape,
            'robust': bool(robust),
            'uncertainty_from': source,
            'sandwich_uncertainty_deg': finite_or_none(sandwich[0]),
            'sandwich_translation_uncertainty_mm': finite_or_none(sandwich[1]),
            'model_uncertainty_deg': finite_or_none(model[0]),
            'model_translation_uncertainty_mm': finite_or_none(model[1])}


def _uncertainty_source(refinement):
    if refinement.resampled is None:
        return 'sandwich'
    return ('block_jackknife_scaled' if refinement.resampled_from_earlier
            else 'block_jackknife')


def _noisy(refinement, used):
    """Return the samples the heavy-tailed noise model down-weighted below NOISY_WEIGHT."""
    if refinement is None:
        return []
    weights = refinement.noise.weights
    return [{'sample': int(used[k]), 'weight': round(float(weights[k]), 3),
             'reason': f'noisy: weighted {weights[k]:.2f} of a typical sample in the refinement'}
            for k in np.flatnonzero(weights < NOISY_WEIGHT)]


def _plausible(refinement, closed):
    """
    Return whether the refinement converged near the closed-form Estimate `closed`.

    Within 10 of its sigmas + 1 deg in rotation and 10 of its sigmas + 0.1 m in translation;
    its sigmas count as at least 0.01 deg and 1 mm, and as that when unknown (NaN). (A
    refinement that diverges, such as --no-robust on a handful of samples with a flipped
    marker, can land at 10^7 m.)
    """
    if not (np.all(np.isfinite(refinement.quaternion))
            and np.all(np.isfinite(refinement.translation))):
        return False
    sigma_deg = closed.uncertainty_deg if closed.uncertainty_deg > 0.01 else 0.01
    moved_deg = np.degrees(quat.angle_between(refinement.quaternion, closed.quaternion))
    sigma_mm = (closed.translation_uncertainty_mm if closed.translation_uncertainty_mm > 1.0
                else 1.0)
    moved_mm = 1e3 * np.linalg.norm(refinement.translation - closed.translation)
    return bool(moved_deg < 10.0 * sigma_deg + 1.0 and moved_mm < 10.0 * sigma_mm + 100.0)


# Full solves come at least every 1/FULL_SOLVE_SHARE of the samples (Calibrator).
FULL_SOLVE_SHARE = 5


class Calibrator:
    """
    Samples in, an estimate of all of them out on request: what session.Session drives.

    add_sample and add_samples only store; estimate() brings the estimate up to date. Every
    estimate covers all samples in O(N). Between full solves (after one new sample), the
    previous published rotation stands in for the consensus search and the refinement is
    warm-started (a few Gauss-Newton steps). The full pipeline of `calibrate` runs while the
    samples are few (up to `small`), on every `full_solve_step`-th sample (every
    `full_solve_every`-th up to 5 times that many samples, then spaced to a fifth of the
    samples, so an early misjudgement cannot persist), when there is no estimate to extend,
    and when several samples came since the last estimate (a file, a resumed session, a
    replay that asks once at the end: its answer is then that of `calibrate`).
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
        self._full_at = 0     # samples the last full solve (successful or not) was of

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
        warm = (new == 1 and self._solution is not None and n > self.small
                and n % self.full_solve_step(n))
        if not warm:
            self._full_at = n
        try:
            self._solution = _solve(self.samples, self.options,
                                    self._solution if warm else None)
        except DegenerateMotionError as error:
            self._solution = None
            self.last_error = str(error)
            return [f'no estimate yet: {error}']
        except np.linalg.LinAlgError as error:   # input checks should make this unreachable
            self.last_error = f'the solver failed numerically at {n} samples ({error})'
            return [f'estimate not updated: {self.last_error}; the earlier estimate stands']
        if warm:
            newest = [r for r in self._solution.result.rejected if r.get('sample') == n - 1]
            return [f'sample {n - 1} rejected: {r["reason"]}' for r in newest]
        return []

    def solve_fully(self):
        """
        Have the next estimate() run the full pipeline unless it ran on these samples.

        Its answer is then that of `calibrate` on the same samples (what `solve` of the
        journal gives), not a warm-started one: the node asks before it saves.
        """
        if self._full_at != len(self.samples):
            self._estimated = 0

    def full_solve_step(self, n):
        """
        Return the spacing of full solves at n samples.

        It is full_solve_every, doubled while the full solves would come more often than
        every 1/FULL_SOLVE_SHARE of the samples: early misjudgements are corrected often
        while they matter (at 200 samples: every 40th).
        """
        step = self.full_solve_every
        while step * FULL_SOLVE_SHARE < n:
            step *= 2
        return step
