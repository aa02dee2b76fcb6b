"""
A noise model with heavy tails, fitted to residuals: Student's t, and bad detections beside it.

Real pose sensors are not Gaussian: most samples scatter by a little, a few by several times
that (motion blur, a grazing view of the target), and now and then a detection is simply wrong
(a marker flip, the wrong marker). The model here has two parts:

- the sensor noise: a d-dimensional Student t with scale matrix S and nu degrees of freedom,
  fitted by expectation-maximisation (Lange, Little and Taylor 1989); nu is chosen from NU_GRID
  by the likelihood, so Gaussian data give nu = inf and plain least squares. Its weights
  (nu + d) / (nu + delta_i), delta_i = r_i^T S^-1 r_i, down-weight noisy samples smoothly;
- bad detections (`bad_detections`): a mixture of that t with the uniform distribution of
  rotations (Haar measure), so a sample is called bad only when a rotation drawn at random
  explains its residual better than the fitted noise does. Every sample takes part in the fit
  with its probability of being good, so no threshold is re-derived from an already-trimmed
  set and decisions do not cascade (only the first fit leaves out what lies beyond a generous
  START_SIGMAS robust sigmas).
"""

from dataclasses import dataclass
import math

import numpy as np

NU_GRID = (3.0, 5.0, 10.0, 30.0, math.inf)
EM_ITERATIONS = 12


@dataclass(frozen=True)
class NoiseFit:
    """The fitted t: scale matrix (d x d), degrees of freedom, per-sample weights and delta."""

    scale: np.ndarray
    nu: float
    weights: np.ndarray     # (nu + d) / (nu + delta_i); 1 for nu = inf
    delta: np.ndarray       # squared Mahalanobis distances r_i^T S^-1 r_i
    log_likelihood: float

    @property
    def covariance(self):
        """Return the covariance of the fitted t, nu / (nu - 2) S (S for nu = inf)."""
        return self.scale * (1.0 if math.isinf(self.nu) else self.nu / (self.nu - 2.0))


def t_weights(delta, d, nu):
    """Return the EM weights (nu + d) / (nu + delta) (ones for nu = inf)."""
    if math.isinf(nu):
        return np.ones_like(delta)
    return (nu + d) / (nu + delta)


def t_log_density(delta, d, nu, log_det):
    """Return the log-density of a d-dimensional t (Gaussian for nu = inf) at delta_i."""
    if math.isinf(nu):
        return -0.5 * (d * math.log(2.0 * math.pi) + log_det + delta)
    return (math.lgamma(0.5 * (nu + d)) - math.lgamma(0.5 * nu)
            - 0.5 * (d * math.log(nu * math.pi) + log_det)
            - 0.5 * (nu + d) * np.log1p(delta / nu))


def fit_t(residuals, lost_samples=0.0, structure=None, floor=None, grid=NU_GRID,
          prior=None):
    """
    Fit the t of the module docstring to residuals (N, d); return the best NoiseFit on `grid`.

    lost_samples: samples' worth of degrees of freedom spent on fitted parameters (the scale
    is divided by N - lost_samples); structure: a function that projects a d x d scatter
    matrix onto the allowed form (e.g. isotropic blocks), None for a full matrix; floor: d
    variances added to the diagonal (so exact data do not divide by zero); prior: per-sample
    probabilities of being good (bad_detections), which weight each sample's part in the fit.
    """
    r = np.asarray(residuals, dtype=float)
    n, d = r.shape
    good = np.ones(n) if prior is None else prior
    count = max(good.sum() - lost_samples, 1.0)
    best = None
    for nu in grid:
        w = np.ones(n)
        for _ in range(EM_ITERATIONS if not math.isinf(nu) else 1):
            scale = _scale(r, good * w, count, structure, floor)
            delta = _mahalanobis(r, scale)
            w = t_weights(delta, d, nu)
        scale = _scale(r, good * w, count, structure, floor)
        delta = _mahalanobis(r, scale)
        log_det = float(np.linalg.slogdet(scale)[1])
        log_likelihood = float(good @ t_log_density(delta, d, nu, log_det))
        if best is None or log_likelihood > best.log_likelihood:
            best = NoiseFit(scale, nu, t_weights(delta, d, nu), delta, log_likelihood)
    return best


def _scale(r, w, count, structure, floor):
    scatter = (r * w[:, None]).T @ r / count
    if structure is not None:
        scatter = structure(scatter)
    return scatter if floor is None else scatter + np.diag(floor)


def _mahalanobis(r, scale):
    return np.einsum('ni,ni->n', r @ np.linalg.inv(scale), r)


def shrunk_to_blocks(samples, prior_samples, block=3):
    """
    Return a `structure` that shrinks a full scatter matrix towards isotropic blocks.

    The weight of the full matrix is samples / (samples + prior_samples): with few samples the
    21 entries of a 6x6 covariance are poorly known and the two variances win; with many the
    data's own shape (anisotropy, correlations) does, smoothly, with no step in between.
    """
    weight = samples / (samples + prior_samples)
    blocks = isotropic_blocks(block)

    def project(scatter):
        return weight * scatter + (1.0 - weight) * blocks(scatter)
    return project


def isotropic_blocks(block=3):
    """Return a `structure` for fit_t: sigma_k^2 I on each diagonal block of `block` axes."""
    def project(scatter):
        d = len(scatter)
        values = np.repeat([np.trace(scatter[k:k + block, k:k + block]) / block
                            for k in range(0, d, block)], block)
        return np.diag(values)
    return project


# --- bad detections -------------------------------------------------------------------------

# Prior probability floor of a bad detection: a sample is bad only against odds of 1 in 1000
# per sample when nothing in the data suggests bad detections.
MIN_BAD_FRACTION = 1e-3
MIXTURE_ITERATIONS = 8
# The mixture starts from the samples within this many robust sigmas (the median residual
# angle over the chi-3 median, 1.5382): a gross error must not take part in the first fit of
# the noise, or the tails it fits would explain it. Generous, so no noisy sample is left out.
START_SIGMAS = 8.0
CHI3_MEDIAN = 1.5382


@dataclass(frozen=True)
class Detections:
    """The verdict on each sample: probability of being good, the fitted noise of the good."""

    good_probability: np.ndarray
    noise: NoiseFit

    @property
    def bad(self):
        """Return the samples (bool mask) a random rotation explains better than the noise."""
        return self.good_probability < 0.5


def uniform_rotation_density(angles):
    """
    Return the density of a uniformly random rotation at rotation vectors of these angles.

    The Haar measure in rotation-vector coordinates: (1 - cos theta) / (4 pi^2 theta^2) per
    unit volume (it integrates to 1 over the ball of radius pi), 1 / (8 pi^2) at theta = 0.
    """
    theta = np.asarray(angles, dtype=float)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    return np.where(small, 1.0 / (8.0 * math.pi ** 2),
                    (1.0 - np.cos(safe)) / (4.0 * math.pi ** 2 * safe * safe))


def bad_detections(rotation_residuals, lost_samples=2.0, floor=1e-14):
    """
    Fit the mixture of the module docstring to rotation residuals (N, 3), radians.

    The good samples' rotation noise is an isotropic 3-D t; lost_samples as in fit_t (two of
    the mounting's three rotation parameters and the object's three, per three axes).
    Returns Detections.
    """
    r = np.asarray(rotation_residuals, dtype=float)
    angles = np.linalg.norm(r, axis=1)
    uniform = uniform_rotation_density(angles)
    start = START_SIGMAS * max(np.median(angles) / CHI3_MEDIAN, math.sqrt(floor))
    good = (angles <= start).astype(float)
    for _ in range(MIXTURE_ITERATIONS):
        noise = fit_t(r, lost_samples, isotropic_blocks(3), np.full(3, floor), prior=good)
        fraction = min(max(good.mean(), 0.5), 1.0 - MIN_BAD_FRACTION)
        log_det = float(np.linalg.slogdet(noise.scale)[1])
        density = np.exp(t_log_density(noise.delta, 3, noise.nu, log_det))
        updated = fraction * density / (fraction * density + (1.0 - fraction) * uniform)
        if np.allclose(updated, good, atol=1e-6):
            break
        good = updated
    return Detections(good, noise)
