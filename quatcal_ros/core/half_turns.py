"""
Half-turn motions: rotations the rotation equations cannot tell apart, settled by translation.

The all-pairs least squares (leastsq.all_pairs_rotation) puts every sample's Z_i = A_i p on
one hemisphere with the sign rule of erratum 3, and a motion near a half-turn decides no sign
(its scalar parts are near zero). When every sample has such a motion to some other, the
signs, and with them the answer, are left to the noise. Worse, the answer can be ambiguous
itself: if X fits every sample (Z_i = L_i X S_i the same for all i), so does X R for a
rotation R of the sensor frame that commutes with every sensor motion S_i S_j^-1, and a
half-turn about n commutes with any turn about n and with a half-turn about any axis
perpendicular to n. Three samples, at home and turned 180 degrees about x and about y, fit
four rotations exactly, a half-turn apart; the least squares picked one by the noise and 25 of
40 such cells came out 180 degrees off with a tiny uncertainty. The translations are not
ambiguous: at a wrong rotation the object positions scatter by decimetres.

`alternatives` returns, for such samples only (`undecided`), every rotation that fits their
orientations as well as the best: for up to ENUMERATED samples the least squares of every
sign pattern, else the least squares with the signs of the answer and of its half-turns about
the sensor motions' axes and their cross products (twice: from the best of the first round).
The caller keeps the one whose translation fits best. Samples whose signs are decided (every
ordinary cell) get the least squares' answer alone, unchanged.
"""

import itertools

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.leastsq import all_pairs_rotation, ANCHORS
from quatcal_ros.core.quality import object_residuals

# A motion whose scalar parts |a_0| and |b_0| (link and sensor) are both below this decides no
# sign: it turns by more than about 155 degrees (cos(77.5 deg) = 0.22). (Samples of another
# setup or convention, whose sensor motions alone look like half-turns, are not such data.)
NEAR_HALF_TURN = 0.22
# Up to this many samples every sign pattern is tried (2^(n-1) 4x4 decompositions).
ENUMERATED = 10
# A rotation that fits the samples' orientations within this factor of the best one's RMS
# residual (plus an absolute allowance for noise-free data) is as good an answer to them.
AS_GOOD = 1.25
AS_GOOD_RAD = 1e-9
# Rotations closer than this (degrees) are one answer: the alternatives lie a half-turn apart.
SAME_DEG = 20.0
# The first motions whose axes (and their cross products) are tried as half-turn axes.
AXES_TRIED = 6


def undecided(rotations, sample_ok):
    """
    Return whether no sample decides every other's hemisphere sign (module docstring).

    As leastsq.hemisphere_signs looks for one: among up to ANCHORS samples.
    """
    link, sensor = rotations.link[sample_ok], rotations.sensor[sample_ok]
    if len(link) < 2:
        return False
    anchors = np.unique(np.linspace(0, len(link) - 1, ANCHORS).astype(int))   # O(N) memory
    half = (np.abs(link[anchors] @ link.T) < NEAR_HALF_TURN) & \
        (np.abs(sensor[anchors] @ sensor.T) < NEAR_HALF_TURN)   # both streams' motion
    return bool(half.any(axis=1).all())


def alternatives(rotations, q_z, sample_ok):
    """
    Return the rotations that fit the good samples' orientations best, and alike.

    [q_z] alone (the same object) when the samples decide their signs; else one rotation of
    each group (within SAME_DEG of each other: sign patterns that differ only on samples a
    half-turn apart land a noise's width apart) that fits within AS_GOOD of the best: q_z for
    its own group, the best fit for the others.
    """
    if not undecided(rotations, sample_ok):
        return [q_z]
    if np.count_nonzero(sample_ok) <= ENUMERATED:
        tried = [q_z] + _sign_patterns(rotations, sample_ok)
    else:   # the half-turns of q_z, each a reference for the signs; twice, from the best
        tried = [q_z]
        for _ in range(2):
            start = tried[int(np.argmin(_residual_rms(rotations, tried, sample_ok)))]
            tried += [all_pairs_rotation(rotations, sample_ok, reference=q) for q in
                      [start] + _half_turns_of(rotations, start, sample_ok)]
    fits = _residual_rms(rotations, tried, sample_ok)
    good = np.flatnonzero(fits <= AS_GOOD * fits.min() + AS_GOOD_RAD)
    order = sorted(good.tolist(), key=lambda k: (k != 0, fits[k]))   # q_z first, if good
    same = np.cos(np.radians(SAME_DEG) / 2.0)
    kept = []
    for k in order:
        if all(abs(float(tried[k] @ other)) < same for other in kept):
            kept.append(tried[k])
    return kept


def _sign_patterns(rotations, sample_ok):
    """Return the least-squares rotation of every sign pattern (the first sample's +1)."""
    flat = rotations.matrices[sample_ok].reshape(-1, 16)
    signs = np.array([(1.0,) + pattern for pattern in
                      itertools.product((1.0, -1.0), repeat=len(flat) - 1)])
    S = (signs @ flat).reshape(-1, 4, 4)
    return [quat.canonical(p) for p in np.linalg.svd(S)[2][:, 0]]


def _half_turns_of(rotations, q_z, sample_ok):
    """Return q_z (x) r_pi(n) for the sensor motions' axes n and their cross products."""
    sensor = rotations.sensor[sample_ok]
    relative = quat.multiply(sensor[1:AXES_TRIED + 1], quat.conjugate(sensor[0]))[:, 1:]
    norms = np.linalg.norm(relative, axis=1)
    axes = relative[norms > 1e-6] / norms[norms > 1e-6, None]
    crossed = np.cross(axes[:, None, :], axes[None, :, :]).reshape(-1, 3)
    lengths = np.linalg.norm(crossed, axis=1)
    candidates = np.concatenate([axes, crossed[lengths > 1e-3] / lengths[lengths > 1e-3, None]])
    # X R_pi(n), n in the sensor frame: the quaternion of a half-turn about n is (0, n)
    return [quat.canonical(quat.multiply(q_z, np.concatenate([[0.0], n]))) for n in candidates]


def _residual_rms(rotations, rotations_tried, sample_ok):
    """Return each rotation's RMS angle (radians) of the good samples' Z_i about their mean."""
    residuals = object_residuals(rotations, np.asarray(rotations_tried, dtype=float),
                                 sample_ok)[0][:, sample_ok]                # (P, N, 3)
    return np.sqrt(np.mean(np.sum(residuals ** 2, axis=-1), axis=-1))
