"""
The next pose to visit: the link pose that most shrinks the mounting's expected uncertainty.

From the current estimate (mounting X, object pose O, the fitted sensor noise) the Fisher
information of the 12 unknowns is sum_i J_i^T M J_i (refine.jacobian at the samples used,
M the inverse noise covariance of one sample). A candidate pose adds its own J^T M J; the
criterion is D-optimal on the mounting: the determinant of X's 6 x 6 block of the inverse
information (O is a nuisance, so the block is the Schur complement), which does not depend on
the units of rotation and translation. Candidates keep the target in the sensor's view: the
target's position in the sensor frame within `cone_deg` of the optical axis (z) and within
the distances seen so far, its orientation within `tilt_deg` of one seen; each gives the link
pose that would see it, kept when it lies within `max_rotation_deg` of the last sample's link
orientation and inside the workspace box (the seen link positions grown by `margin_m`, or the
user's). The best of `candidates` random ones is proposed, with the uncertainty expected
after it. `plan_session` plans a fresh calibration the same way, pose after pose, from a start
pose and guesses of the mounting and the object (the `plan` tool), with a weak prior that keeps
the criterion finite before the poses determine every unknown.
"""

from dataclasses import dataclass, replace

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.motions import SampleRotations
from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.core.refine import jacobian, lever, object_pose, uncertainties
from quatcal_ros.core.translation import SamplePositions


@dataclass(frozen=True)
class PlanLimits:
    """Where the next pose may be (module docstring); lengths in metres, angles in degrees."""

    max_rotation_deg: float = 45.0
    cone_deg: float = 20.0
    tilt_deg: float = 40.0
    margin_m: float = 0.1
    box_min: tuple = None          # workspace box of the link position, base frame
    box_max: tuple = None
    candidates: int = 400
    seed: int = 0


@dataclass(frozen=True)
class NextPose:
    """The proposed link pose T_base_link and the uncertainty expected after visiting it."""

    link: Pose
    uncertainty_deg: float
    translation_uncertainty_mm: float
    current_uncertainty_deg: float
    current_translation_uncertainty_mm: float

    def to_json_dict(self):
        """Return contract 6's "next_pose": position, orientation (x, y, z, w), the gains."""
        return {'position': quat.xyz_json(self.link.position),
                'orientation': quat.xyzw_json(self.link.quaternion),
                'frame': 'robot base (the frame of the link poses)',
                'expected_uncertainty_deg': float(self.uncertainty_deg),
                'expected_translation_uncertainty_mm': float(self.translation_uncertainty_mm),
                'current_uncertainty_deg': float(self.current_uncertainty_deg),
                'current_translation_uncertainty_mm':
                    float(self.current_translation_uncertainty_mm)}


def noise_covariance(noise_model):
    """Return the 6x6 sensor noise (rad, m) of a result's JSON-ready noise_model."""
    sd = np.concatenate([np.radians(noise_model['rotation_noise_deg']),
                         1e-3 * np.asarray(noise_model['translation_noise_mm'])])
    return np.asarray(noise_model['correlation']) * np.outer(sd, sd)


def plan_next_pose(samples, result, setup='eye_in_hand', invert_sensor=False,
                   limits=PlanLimits(), prior_information=None):
    """
    Return the NextPose for `samples` and their CalibrationResult, or None (no refinement).

    prior_information: a 12 x 12 information added to the samples' (plan_session's weak
    prior, which keeps the criterion defined before the samples determine everything).
    """
    if result is None or result.noise_model is None or result.sample_ok is None \
            or getattr(result, 'unobservable', None):   # a reduced-DOF robot reaches few poses
        return None
    used = np.asarray(result.sample_ok, dtype=bool)
    rotations = SampleRotations.from_samples(samples, setup, invert_sensor)
    positions = SamplePositions.from_samples(samples, rotations)
    link_q, link_t = rotations.link[used], positions.link[used]
    sensor_q, sensor_t = rotations.sensor[used], positions.sensor[used]
    x_q, x_t = np.asarray(result.quaternion, float), np.asarray(result.translation, float)
    o_q, o_t = object_pose(link_q, link_t, sensor_q, sensor_t, x_q, x_t)
    M = np.linalg.inv(noise_covariance(result.noise_model))
    information = _information(link_q, link_t, x_q, x_t, o_t, M).sum(axis=0)
    if prior_information is not None:
        information = information + prior_information
    candidates = _candidate_sensor_poses(sensor_q, sensor_t, limits)
    # The link pose (as refine takes it) that sees each: L = O inv(S) inv(X).
    O, X_inv = Pose(o_t, o_q), Pose(x_t, x_q).inverse()
    refine_links = [O @ Pose(t, q).inverse() @ X_inv for q, t in zip(*candidates)]
    cand_q = np.array([p.quaternion for p in refine_links])
    cand_t = np.array([p.position for p in refine_links])
    base_links = [p if setup == 'eye_in_hand' else p.inverse() for p in refine_links]
    keep = _within_limits(base_links, samples, used, limits)
    if not keep.any():
        return None
    added = _information(cand_q[keep], cand_t[keep], x_q, x_t, o_t, M)
    covariances = np.linalg.inv(information[None] + added)[:, :6, :6]
    signs, log_dets = np.linalg.slogdet(covariances)
    best = int(np.argmin(np.where(signs > 0, log_dets, np.inf)))
    current = uncertainties(np.linalg.pinv(information)[:6, :6])
    after = uncertainties(covariances[best])
    return NextPose(np.array(base_links, dtype=object)[keep][best], after[0], after[1],
                    current[0], current[1])


@dataclass(frozen=True)
class Guess:
    """
    What plan_session assumes before any data: the result fields plan_next_pose reads.

    quaternion, translation: the mounting X; noise_model: the sensor noise, as a result's.
    """

    quaternion: np.ndarray
    translation: np.ndarray
    noise_model: dict
    sample_ok: np.ndarray


# plan_session's prior: 1 rad on each rotation and 1 m on each translation of the 12 unknowns;
# far weaker than one sample, it only makes the first steps' criterion finite.
PRIOR_INFORMATION = np.eye(12)


def plan_session(start, count, mounting, object_pose, setup='eye_in_hand',
                 noise=(0.1, 1.0), limits=PlanLimits()):
    """
    Return `count` link poses for a fresh calibration, start first, as NextPose objects.

    Each next pose is plan_next_pose's for the poses before it, with the sensor poses the
    model predicts (`mounting` X and `object_pose` O as guesses: eye-in-hand X = T_link_sensor,
    O = T_base_object; eye-to-hand X = T_base_sensor, O = T_link_object) and `noise`
    (rotation deg, translation mm per axis) for every sample. The expected uncertainties are
    the model's after each pose. Fewer poses come back when no candidate fits the limits.
    """
    X_inv = mounting.inverse()

    def seen(link):
        return (X_inv @ link.inverse() @ object_pose if setup == 'eye_in_hand'
                else X_inv @ link @ object_pose)

    noise_model = {'rotation_noise_deg': [noise[0]] * 3, 'translation_noise_mm': [noise[1]] * 3,
                   'correlation': np.eye(6).tolist()}
    samples = [Sample(0, start, seen(start))]
    planned = [NextPose(start, float('inf'), float('inf'), float('inf'), float('inf'))]
    for k in range(1, count):
        guess = Guess(mounting.quaternion, mounting.position, noise_model,
                      np.ones(len(samples), bool))
        proposal = plan_next_pose(samples, guess, setup,
                                  limits=replace(limits, seed=limits.seed + k),
                                  prior_information=PRIOR_INFORMATION)
        if proposal is None:
            break
        samples.append(Sample(k, proposal.link, seen(proposal.link)))
        planned.append(proposal)
    return planned


def _information(link_q, link_t, x_q, x_t, o_t, M):
    """Return each sample's Fisher information J^T M J (N, 12, 12) at the model."""
    R_L = quat.matrix_from_quaternion(link_q)
    J = jacobian(R_L, quat.matrix_from_quaternion(x_q), lever(link_q, link_t, x_t, o_t, R_L))
    return np.einsum('nai,ab,nbj->nij', J, M, J)


def _candidate_sensor_poses(sensor_q, sensor_t, limits):
    """Return random target poses in the sensor frame (q (K, 4), t (K, 3)), in view."""
    rng = np.random.default_rng(limits.seed)
    k = limits.candidates
    distances = np.linalg.norm(sensor_t, axis=1)
    d = rng.uniform(distances.min(), distances.max(), k)
    off_axis = np.radians(limits.cone_deg) * np.sqrt(rng.uniform(0, 1, k))
    azimuth = rng.uniform(0, 2 * np.pi, k)
    direction = np.column_stack([np.sin(off_axis) * np.cos(azimuth),
                                 np.sin(off_axis) * np.sin(azimuth), np.cos(off_axis)])
    axes = rng.normal(size=(k, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    turn = quat.from_rotation_vector(
        axes * np.radians(limits.tilt_deg) * rng.uniform(0, 1, (k, 1)) ** (1 / 3))
    seen = sensor_q[rng.integers(0, len(sensor_q), k)]
    return quat.multiply(turn, seen), direction * d[:, None]


def _within_limits(links, samples, used, limits):
    """Return which candidate link poses T_base_link the limits allow (bool, K)."""
    last = samples[-1].link   # where the robot is, whatever the verdict on its detection
    q = np.array([p.quaternion for p in links])
    t = np.array([p.position for p in links])
    turned = np.degrees(quat.angle_between(q, last.quaternion[None]))
    seen = np.array([s.link.position for s, ok in zip(samples, used) if ok])
    low = (np.asarray(limits.box_min, float) if limits.box_min is not None
           else seen.min(axis=0) - limits.margin_m)
    high = (np.asarray(limits.box_max, float) if limits.box_max is not None
            else seen.max(axis=0) + limits.margin_m)
    return (turned <= limits.max_rotation_deg) & np.all((t >= low) & (t <= high), axis=1)
