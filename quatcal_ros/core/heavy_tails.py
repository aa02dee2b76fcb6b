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

from dataclasses import dataclass, replace
import math

import numpy as np

NU_GRID = (3.0, 5.0, 10.0, 30.0, math.inf)
EM_ITERATIONS = 12
WARM_EM_ITERATIONS = 1
RESUMED_EM_ITERATIONS = 3
# Models less probable than this are dropped from the average (and from the work).
MIN_PROBABILITY = 0.02


@dataclass(frozen=True)
class Shape:
    """A form the scale matrix may take: its name, projection and free parameters."""

    name: str
    project: object          # scatters (..., d, d) -> matrices of this shape; None: as they are
    parameters: int
    block: int = None        # sigma_k^2 I on blocks of this many axes: the EM's short path


def isotropic_blocks(d, block=3):
    """Return the Shape sigma_k^2 I on each diagonal block of `block` axes (d / block params)."""
    def project(scatter):
        variances = np.diagonal(scatter, axis1=-2, axis2=-1)
        means = variances.reshape(variances.shape[:-1] + (-1, block)).mean(axis=-1)
        return np.repeat(means, block, axis=-1)[..., None] * np.eye(d)
    return Shape('isotropic', project, d // block, block)


def full(d):
    """Return the Shape of any symmetric positive definite matrix (d (d + 1) / 2 params)."""
    return Shape('full', None, d * (d + 1) // 2)


@dataclass(frozen=True)
class Component:
    """One candidate noise model fitted to the residuals: a Shape and a nu."""

    shape: Shape
    nu: float
    scale: np.ndarray       # d x d
    precision: np.ndarray   # its inverse
    weights: np.ndarray     # (nu + d) / (nu + delta_i); 1 for nu = inf
    delta: np.ndarray       # squared Mahalanobis distances r_i^T S^-1 r_i
    log_density: np.ndarray  # per sample
    criterion: float        # the Bayesian information criterion of the fit

    @property
    def covariance(self):
        """Return the covariance of this t, nu / (nu - 2) S (S for nu = inf)."""
        return self.scale * (1.0 if math.isinf(self.nu) else self.nu / (self.nu - 2.0))


@dataclass(frozen=True)
class NoiseFit:
    """
    The fitted noise: candidate models averaged with their posterior probabilities.

    The probabilities come from the information criterion (exp(BIC_k) normalised): nearly
    always one model has all of it, but near a tie the estimate moves smoothly from one to
    the other instead of jumping when a sample's last digit changes.
    """

    components: tuple
    probabilities: np.ndarray

    @property
    def best(self):
        """Return the most probable Component."""
        return self.components[int(np.argmax(self.probabilities))]

    @property
    def nu(self):
        """Return the most probable tail degrees of freedom (inf: Gaussian)."""
        return self.best.nu

    @property
    def covariance(self):
        """Return the covariance of the noise (d x d), averaged over the models."""
        return sum(p * c.covariance for p, c in zip(self.probabilities, self.components))

    @property
    def weights(self):
        """Return each sample's weight relative to a typical sample, averaged over the models."""
        return sum(p * c.weights for p, c in zip(self.probabilities, self.components))

    def information(self):
        """Return each sample's information matrix sum_k p_k w_ik S_k^-1, (N, d, d)."""
        return sum(p * c.weights[:, None, None] * c.precision[None]
                   for p, c in zip(self.probabilities, self.components))

    def subset(self, mask):
        """Return this fit restricted to the samples `mask` selects (to warm-start a refit)."""
        return NoiseFit(tuple(replace(c, weights=c.weights[mask], delta=c.delta[mask],
                                      log_density=c.log_density[mask])
                              for c in self.components), self.probabilities)

    def refitted(self, residuals, lost_samples=0.0, floor=None):
        """Return the same models and probabilities with their scales fitted to `residuals`."""
        r = np.asarray(residuals, dtype=float)
        count = max(len(r) - lost_samples, 1.0)
        by_shape = {}
        for c in self.components:
            by_shape.setdefault(c.shape.name, []).append(c)
        fitted = {}
        for group in by_shape.values():
            for c in _fit_components(r, np.ones(len(r)), count, group[0].shape,
                                     [c.nu for c in group], floor, group):
                fitted[c.shape.name, c.nu] = c
        return NoiseFit(tuple(fitted[c.shape.name, c.nu] for c in self.components),
                        self.probabilities)

    def refitted_information(self, residuals, keep, lost_samples=0.0, floor=None):
        """
        Return each sample's information (B, N, d, d) with the scales refitted per row of keep.

        keep (B, N) bool: for each row b the scales (and weights) are refitted, as `refitted`
        does, to the samples it keeps, warm-started from this fit's weights; the samples it
        leaves out get zero. The models and their probabilities stay. All rows at once: the
        jackknife's replicates (refine.with_jackknife).
        """
        r = np.asarray(residuals, dtype=float)
        keep = np.asarray(keep, dtype=float)
        rows, n = keep.shape
        d = r.shape[1]
        count = np.maximum(keep.sum(axis=1) - lost_samples, 1.0)
        information = np.zeros((rows, n, d, d))
        arithmetic = {}
        for p, c in zip(self.probabilities, self.components):
            if c.shape.name not in arithmetic:
                arithmetic[c.shape.name] = _arithmetic(r, c.shape, floor)
            fit = arithmetic[c.shape.name]
            w = np.broadcast_to(c.weights, (rows, n))
            for _ in range(0 if math.isinf(c.nu) else WARM_EM_ITERATIONS):
                w = (c.nu + d) / (c.nu + fit.distances(keep * w, count))
            _, precision, delta, _ = fit.fitted(keep * w, count)
            w = 1.0 if math.isinf(c.nu) else (c.nu + d) / (c.nu + delta)
            information += p * (keep * w)[..., None, None] * precision[:, None]
        return information

    def density(self):
        """Return each sample's density under the noise, averaged over the models."""
        return sum(p * np.exp(c.log_density)
                   for p, c in zip(self.probabilities, self.components))


def fit_t(residuals, shapes, grid=NU_GRID, lost_samples=0.0, floor=None, prior=None,
          start=None):
    """
    Fit the t of the module docstring to residuals (N, d); return the NoiseFit.

    Every combination of a Shape in `shapes` and a nu on `grid` is fitted and weighed by the
    Bayesian information criterion (log-likelihood less half the free parameters times
    log N), so a full covariance counts only when the data show its shape clearly, and heavy
    tails only when the data need them. lost_samples: samples' worth of degrees of freedom
    spent on fitted parameters (the scale is divided by N minus them); floor: d variances
    added to the diagonal (so exact data do not divide by zero); prior: per-sample
    probabilities of being good (bad_detections), which weight each sample's part in the fit;
    start: a NoiseFit of similar residuals whose weights start the EM (fewer steps; a model it
    dropped starts from the distances of its nearest model).
    """
    r = np.asarray(residuals, dtype=float)
    n, d = r.shape
    good = np.ones(n) if prior is None else prior
    count = max(good.sum() - lost_samples, 1.0)
    earlier = {} if start is None else {(c.shape.name, c.nu): c for c in start.components}
    components = []
    for shape in shapes:
        components += _fit_components(r, good, count, shape, grid, floor,
                                      [_nearest(earlier, shape.name, nu) for nu in grid])
    criteria = np.array([c.criterion for c in components])
    probabilities = np.exp(criteria - criteria.max())
    keep = probabilities > MIN_PROBABILITY * probabilities.sum()   # no say: dropped
    return NoiseFit(tuple(c for c, k in zip(components, keep) if k),
                    probabilities[keep] / probabilities[keep].sum())


def _nearest(components, shape_name, nu):
    """
    Return the Component of this shape and nu in `components` ({(shape, nu): Component}).

    Failing that (a fit drops its improbable models), the one of the nearest finite nu, of this
    shape when there is one, whose distances start this nu's EM nearly as well; None when there
    is none.
    """
    if (shape_name, nu) in components or math.isinf(nu):
        return components.get((shape_name, nu))
    near = [(name != shape_name, abs(math.log(c.nu / nu)), key)
            for key, c in components.items() for name in [key[0]] if math.isfinite(c.nu)]
    return components[min(near)[2]] if near else None


def _fit_components(r, good, count, shape, nus, floor, warm):
    """
    Fit one Shape with each nu of `nus` by EM, all at once; return their Components.

    warm: for each nu an earlier Component to start from (of it, or of another finite nu or
    shape: the weights its distances give this nu), or None. Each model takes
    its own number of EM steps (none for nu = inf, fewer from a warm start), as if fitted
    alone: the batch only shares the arithmetic.
    """
    n, d = r.shape
    k = len(nus)
    nu = np.array(nus, dtype=float)
    w = np.ones((k, n))
    steps = np.full(k, EM_ITERATIONS)
    for i, component in enumerate(warm):
        if component is not None:   # of these samples, or of the first (a sample added since)
            m = min(n, len(component.weights))
            same = (component.shape.name, component.nu) == (shape.name, nu[i])
            w[i, :m] = (component.weights[:m] if same
                        else (nu[i] + d) / (nu[i] + component.delta[:m]))
            steps[i] = WARM_EM_ITERATIONS if m == n else RESUMED_EM_ITERATIONS
    steps[np.isinf(nu)] = 0
    arithmetic = _arithmetic(r, shape, floor)
    done = 0
    for until in np.unique(steps[steps > 0]):   # the rows still moving, a batch at a time
        rows = np.flatnonzero(steps >= until)     # finite nu only
        tails = nu[rows][:, None]
        moving = w[rows]
        for _ in range(int(until) - done):
            moving = (tails + d) / (tails + arithmetic.distances(good * moving, count))
        w[rows], done = moving, int(until)
    scale, precision, delta, log_det = arithmetic.fitted(good * w, count)
    weights = t_weights(delta, d, nu)
    log_density = t_log_density(delta, d, nu, log_det)
    free = shape.parameters + np.where(np.isinf(nu), 0, 1)
    criteria = log_density @ good - 0.5 * free * math.log(max(good.sum(), 2.0))
    return [Component(shape, float(nu[i]), scale[i], precision[i], weights[i], delta[i],
                      log_density[i], float(criteria[i])) for i in range(k)]


def t_log_density(delta, d, nu, log_det):
    """
    Return the log-density of d-dimensional t's (Gaussian for nu = inf) at delta (K, N).

    Row k is the t with nu[k] degrees of freedom whose scale has the log determinant
    log_det[k].
    """
    finite = np.isfinite(nu)
    safe = np.where(finite, nu, 1.0)
    norm = np.array([math.lgamma(0.5 * (v + d)) - math.lgamma(0.5 * v) for v in safe])
    t = ((norm - 0.5 * (d * np.log(safe * math.pi) + log_det))[:, None]
         - 0.5 * (safe + d)[:, None] * np.log1p(delta / safe[:, None]))
    gaussian = -0.5 * ((d * math.log(2.0 * math.pi) + log_det)[:, None] + delta)
    return np.where(finite[:, None], t, gaussian)


def t_weights(delta, d, nu):
    """Return the EM weights (nu + d) / (nu + delta_kn) (K, N), each row with its nu (K,)."""
    finite = np.isfinite(nu)[:, None]
    safe = np.where(finite, nu[:, None], 1.0)
    return np.where(finite, (safe + d) / (safe + delta), 1.0)


def _scale(r, w, count, shape, floor):
    """
    Return the scale matrices (K, d, d) of residuals r (N, d) with weights w (K, N).

    count: the samples' worth each is divided by, one for all or one per row (K,).
    """
    scatter = (np.swapaxes(w[:, :, None] * r, 1, 2) @ r) / np.reshape(count, (-1, 1, 1))
    if shape.project is not None:
        scatter = shape.project(scatter)
    return scatter if floor is None else scatter + np.diag(floor)


class _Matrices:
    """The scale matrices of any Shape, and the distances under them (K models at once)."""

    def __init__(self, r, shape, floor):
        self.r, self.shape, self.floor = r, shape, floor

    def distances(self, w, count):
        """Return r_n^T S_k^-1 r_n (K, N) under the scales S_k of the weights w (K, N)."""
        return self._solved(w, count)[2]

    def fitted(self, w, count):
        """Return the scales, their inverses (K, d, d), the distances (K, N), log dets (K,)."""
        scale, precision, delta = self._solved(w, count)
        return scale, precision, delta, np.linalg.slogdet(scale)[1]

    def _solved(self, w, count):
        scale = _scale(self.r, w, count, self.shape, self.floor)
        precision = np.linalg.inv(scale)
        return scale, precision, ((self.r @ precision) * self.r).sum(axis=-1)


class _Blocks:
    """
    The same for sigma_b^2 I on blocks of axes (Shape.block), without forming a matrix.

    The variances come from each sample's sum of squares per block (N, B), the distances
    from its squares per axis (each axis's variance is its block's plus its floor): the EM's
    inner loop, the same numbers as _Matrices to rounding.
    """

    def __init__(self, r, block, floor):
        n, d = r.shape
        self.squares = r * r
        self.block_squares = self.squares.reshape(n, d // block, block).sum(axis=-1)
        self.block, self.d = block, d
        self.floor = 0.0 if floor is None else floor

    def _variances(self, w, count):
        """Return each model's variance per axis (K, d)."""
        blocks = (w @ self.block_squares) / (self.block * np.reshape(count, (-1, 1)))
        return np.repeat(blocks, self.block, axis=1) + self.floor

    def distances(self, w, count):
        """Return r_n^T S_k^-1 r_n (K, N) under the scales S_k of the weights w (K, N)."""
        return (1.0 / self._variances(w, count)) @ self.squares.T

    def fitted(self, w, count):
        """Return the scales, their inverses (K, d, d), the distances (K, N), log dets (K,)."""
        variances = self._variances(w, count)
        inverse = 1.0 / variances
        eye = np.eye(self.d)
        return (variances[:, :, None] * eye, inverse[:, :, None] * eye,
                inverse @ self.squares.T, np.log(variances).sum(axis=1))


def _arithmetic(r, shape, floor):
    """Return the _Blocks of a Shape of isotropic blocks, else its _Matrices."""
    return _Matrices(r, shape, floor) if shape.block is None else _Blocks(r, shape.block, floor)


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


def bad_detections(rotation_residuals, lost_samples=2.0, floor=1e-14, start=None):
    """
    Fit the mixture of the module docstring to rotation residuals (N, 3), radians.

    The good samples' rotation noise is an isotropic 3-D t; lost_samples as in fit_t (two of
    the mounting's three rotation parameters and the object's three, per three axes); start:
    the Detections of similar residuals, whose noise starts the EM (fit_t's start).
    Returns Detections.
    """
    r = np.asarray(rotation_residuals, dtype=float)
    angles = np.linalg.norm(r, axis=1)
    uniform = uniform_rotation_density(angles)
    limit = START_SIGMAS * max(np.median(angles) / CHI3_MEDIAN, math.sqrt(floor))
    good = (angles <= limit).astype(float)
    noise = None if start is None else start.noise
    for _ in range(MIXTURE_ITERATIONS):
        noise = fit_t(r, (isotropic_blocks(3),), NU_GRID, lost_samples, np.full(3, floor),
                      prior=good, start=noise)
        fraction = min(max(good.mean(), 0.5), 1.0 - MIN_BAD_FRACTION)
        density = noise.density()
        updated = fraction * density / (fraction * density + (1.0 - fraction) * uniform)
        if np.allclose(updated, good, atol=1e-6):
            break
        good = updated
    return Detections(good, noise)
