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

Every candidate model (a Shape of the scale and a nu) is one row of the arrays of a NoiseFit:
the EM steps, densities and information of all of them are computed at once.
"""

from dataclasses import dataclass
from functools import cached_property, lru_cache
import math

import numpy as np
from quatcal_ros.core.numerics import median

NU_GRID = (3.0, 5.0, 10.0, 30.0, math.inf)
EM_ITERATIONS = 6
WARM_EM_ITERATIONS = 1
RESUMED_EM_ITERATIONS = 3
# Models less probable than this have no say in the average (probability 0). They stay in the
# fit (every row costs the same in the batched arithmetic), so each model's EM always resumes
# from its own last weights.
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


def diagonal(d):
    """Return the Shape of any diagonal matrix: a variance per axis (d params)."""
    return Shape('diagonal', isotropic_blocks(d, 1).project, d, 1)


def full(d):
    """Return the Shape of any symmetric positive definite matrix (d (d + 1) / 2 params)."""
    return Shape('full', None, d * (d + 1) // 2)


@dataclass(frozen=True)
class Component:
    """One candidate noise model fitted to the residuals: a Shape and a nu (a NoiseFit's row)."""

    shape: Shape
    nu: float
    scale: np.ndarray       # d x d
    weights: np.ndarray     # (nu + d) / (nu + delta_i); 1 for nu = inf
    delta: np.ndarray       # squared Mahalanobis distances r_i^T S^-1 r_i

    @property
    def covariance(self):
        """Return the covariance of this t, nu / (nu - 2) S (S for nu = inf)."""
        return self.scale * _covariance_factor(self.nu)


def _covariance_factor(nu):
    return 1.0 if math.isinf(nu) else nu / (nu - 2.0)


@dataclass(frozen=True, eq=False)
class NoiseFit:
    """
    The fitted noise: candidate models averaged with their posterior probabilities.

    Row k of each array is model k (shapes[k], nus[k]). The probabilities come from the
    information criterion (exp(BIC_k) normalised, 0 below MIN_PROBABILITY): nearly always one
    model has all of it, but near a tie the estimate moves smoothly from one to the other
    instead of jumping when a sample's last digit changes. The scales are kept as their
    diagonals (`variances`, K x d) when every model's is diagonal, else as matrices
    (`matrices`: scales and precisions).
    """

    shapes: tuple                # (K,) Shape
    nus: tuple                   # (K,) float
    probabilities: np.ndarray    # (K,)
    model_weights: np.ndarray    # (K, N) (nu + d) / (nu + delta); 1 for nu = inf
    delta: np.ndarray            # (K, N) squared Mahalanobis distances
    log_density: np.ndarray      # (K, N)
    variances: np.ndarray = None  # (K, d) the diagonal scales, or None
    matrices: tuple = None       # (scales, precisions), each (K, d, d), when not diagonal

    @property
    def scales(self):
        """Return the scale matrices (K, d, d)."""
        return _as_matrices(self.variances) if self.matrices is None else self.matrices[0]

    @property
    def precisions(self):
        """Return the scales' inverses (K, d, d)."""
        return (_as_matrices(1.0 / self.variances) if self.matrices is None
                else self.matrices[1])

    @property
    def components(self):
        """Return the models with a say (probability > 0) as Components."""
        scales = self.scales
        return tuple(Component(self.shapes[k], self.nus[k], scales[k], self.model_weights[k],
                               self.delta[k]) for k in self.live)

    @cached_property
    def live(self):
        """Return the rows of the models with a say (probability > 0)."""
        return [k for k, p in enumerate(self.probabilities.tolist()) if p > 0.0]

    @property
    def best(self):
        """Return the most probable Component."""
        k = int(np.argmax(self.probabilities))
        return Component(self.shapes[k], self.nus[k], self.scales[k], self.model_weights[k],
                         self.delta[k])

    @property
    def nu(self):
        """Return the most probable tail degrees of freedom (inf: Gaussian)."""
        return self.nus[int(np.argmax(self.probabilities))]

    @property
    def shape(self):
        """Return the most probable model's Shape."""
        return self.shapes[int(np.argmax(self.probabilities))]

    @cached_property
    def covariance(self):
        """Return the covariance of the noise (d x d), averaged over the models."""
        factors = self.probabilities * _t_constants(self.nus, 1).covariance_factor
        covariance = (np.diag(factors @ self.variances) if self.variances is not None
                      else np.tensordot(factors, self.scales, axes=1))
        covariance.flags.writeable = False   # remembered: callers share it
        return covariance

    @property
    def weights(self):
        """Return each sample's weight relative to a typical sample, averaged over the models."""
        return self.probabilities @ self.model_weights

    def information(self):
        """Return each sample's information matrix sum_k p_k w_ik S_k^-1, (N, d, d)."""
        diagonal = self.information_diagonal()
        if diagonal is not None:
            return _as_matrices(diagonal)
        return np.einsum('kn,kij->nij', self.probabilities[:, None] * self.model_weights,
                         self.precisions)

    @cached_property
    def live_variances(self):
        """
        Return the diagonal scales (L, d) of the models with a say, when all have one.

        None when a model with a say has a full scale matrix. Models without a say add
        nothing to the information, whatever their shape.
        """
        live = self.live
        if self.variances is not None:
            return self.variances[live]
        if any(self.shapes[k].block is None for k in live):
            return None
        return np.diagonal(self.matrices[0][live], axis1=1, axis2=2)

    @property
    def diagonal(self):
        """Return whether each sample's information is diagonal: live_variances is not None."""
        return self.live_variances is not None

    def information_diagonal(self):
        """Return the information's diagonals (N, d) when it is diagonal, else None."""
        variances = self.live_variances
        if variances is None:
            return None
        live = self.live
        return (self.probabilities[live][:, None] * self.model_weights[live]).T @ (
            1.0 / variances)

    @cached_property
    def block(self):
        """Return b when every live model's scale is sigma^2 I on blocks of b axes, else None."""
        variances = self.live_variances
        blocks = {self.shapes[k].block for k in self.live}
        if variances is None or len(blocks) != 1:
            return None
        block = blocks.pop()
        per_block = variances[:, ::block]
        return block if np.array_equal(np.repeat(per_block, block, axis=1), variances) else None

    def information_per_block(self):
        """Return each sample's information per block of axes (N, d / block), given `block`."""
        live = self.live
        return ((self.probabilities[live][:, None] * self.model_weights[live]).T
                @ (1.0 / self.live_variances[:, ::self.block]))

    def efficiency(self, d):
        """
        Return the t's Fisher information of a location over the weighted normal matrix's.

        For a t with nu degrees of freedom in d dimensions the Fisher information of a
        location is (nu + d) / (nu + d + 2) times the Gaussian one with the scale matrix S;
        reweighted least squares has the weights' mean in place of that factor (averaged over
        the models).
        """
        factors = _t_constants(self.nus, d).fisher_factor
        mean_weights = np.maximum(self.model_weights.mean(axis=1), 1e-12)
        return float(self.probabilities @ (factors / mean_weights))

    def curvature(self, d):
        """
        Return the Hessian of a location's negative log-likelihood over the normal matrix's.

        Expected over the residuals' directions, given the fitted weights. The t's weights
        w_i = (nu + d) / (nu + delta_i) fall as a residual grows, so its Hessian is
        sum_i J_i^T (w_i P - 2 w_i^2 / (nu + d) P e_i e_i^T P) J_i (P = S^-1; the weighted
        normal matrix is the first term alone). Over the directions of e_i, P e_i e_i^T P
        averages to delta_i / d P, so the Hessian is the normal matrix times
        sum_i (w_i - 2 w_i^2 delta_i / (d (nu + d))) / sum_i w_i (averaged over the models):
        (nu + d) / (nu + d + 2) for residuals that follow the t, 1 for the Gaussian. Taken
        from the weights as fitted, as the normal matrix is, it stays consistent with it when
        a few samples' fitted scale makes every weight larger than its expectation of 1.
        """
        nu = np.array(self.nus, dtype=float)[:, None]
        w, delta = self.model_weights, self.delta
        finite = np.isfinite(nu[:, 0])
        bend = np.zeros_like(w)
        bend[finite] = 2.0 * w[finite] ** 2 * delta[finite] / (d * (nu[finite] + d))
        total = self.probabilities @ w.sum(axis=1)
        return float(self.probabilities @ (w - bend).sum(axis=1) / total) if total > 0 else 1.0

    def subset(self, mask):
        """Return this fit restricted to the samples `mask` selects (to warm-start a refit)."""
        return NoiseFit(self.shapes, self.nus, self.probabilities,
                        self.model_weights[:, mask], self.delta[:, mask],
                        self.log_density[:, mask], self.variances, self.matrices)

    def refitted(self, residuals, lost_samples=0.0, floor=None):
        """Return the same models and probabilities with their scales fitted to `residuals`."""
        r = np.asarray(residuals, dtype=float)
        count = max(len(r) - lost_samples, 1.0)
        parts = []
        for rows in _groups(self.shapes):
            constants = _t_constants(tuple(self.nus[k] for k in rows), r.shape[1])
            w, steps = _warm_start(self, rows, len(r), constants)
            parts.append(_fit_models(r, None, count, tuple(self.shapes[k] for k in rows),
                                     constants, floor, w, steps))
        return _noise_fit(parts, self.probabilities)

    def refitted_information(self, residuals, keep, lost_samples=0.0, floor=None):
        """
        Return each sample's information (B, N, d, d) with the scales refitted per row of keep.

        keep (B, N) bool: for each row b the scales (and weights) are refitted, as `refitted`
        does, to the samples it keeps, warm-started from this fit's weights; the samples it
        leaves out get zero. The models and their probabilities stay. All rows at once, as
        the jackknife's replicates need (refine._jackknife takes the compact form,
        refitted_information_blocks).
        """
        information = self.refitted_information_blocks(residuals, keep, lost_samples, floor)
        return _as_matrices(information) if self.diagonal else information

    def refitted_information_blocks(self, residuals, keep, lost_samples=0.0, floor=None,
                                    per_block=False):
        """
        Return `refitted_information`, as diagonals (B, N, d) when the scales are diagonal.

        Diagonals when every live model's scale is (`diagonal`), else matrices (B, N, d, d);
        per_block (given `block`): one per block of axes (B, N, d / block).
        """
        r = np.asarray(residuals, dtype=float)
        keep = np.asarray(keep, dtype=float)
        replicates, n = keep.shape
        count = np.maximum(keep.sum(axis=1) - lost_samples, 1.0)
        information = 0.0
        live = set(self.live)
        for models in _groups(self.shapes):
            models = [k for k in models if k in live]
            if not models:
                continue
            # Every model's replicates at once: (K B, N) weights, the K models in turn.
            constants = _t_constants(tuple(self.nus[k] for k in models), r.shape[1])
            arithmetic = _arithmetic(r, tuple(self.shapes[k] for k in models), floor,
                                     replicates)
            counts = np.tile(count, len(models))
            w = (keep * self.model_weights[models][:, None, :]).reshape(-1, n)
            repeat = (len(models), replicates, 1)
            nu = np.broadcast_to(constants.safe[:, None], repeat).reshape(-1, 1)
            numerator = np.broadcast_to(constants.numerator[:, None], repeat).reshape(-1, 1)
            kept = np.broadcast_to(keep, (len(models),) + keep.shape).reshape(-1, n)
            gaussian = None if constants.all_finite else constants.gaussian_rows
            for step in range(WARM_EM_ITERATIONS + 1):   # the last keeps the precisions
                delta = (arithmetic.fitted(w, counts)[1] if step == WARM_EM_ITERATIONS
                         else arithmetic.distances(w, counts))
                w = kept * (numerator / (nu + delta))
                if gaussian is not None:      # the Gaussian's weights stay those it kept
                    w.reshape(len(models), replicates, n)[gaussian] = keep
            p = self.probabilities[models][:, None, None]
            w = p * w.reshape(len(models), replicates, n)
            precision = arithmetic.precision.reshape(
                (len(models), replicates) + arithmetic.precision.shape[1:])
            if self.diagonal:   # precisions as diagonals (K, B, d), per block
                if per_block:
                    precision = precision[..., ::self.block]
                # sum_k w_kbn P_kbd as B products (N, K) @ (K, d)
                information = information + (np.swapaxes(w, 0, 1).transpose(0, 2, 1)
                                             @ np.swapaxes(precision, 0, 1))
            else:
                if precision.ndim == 3:   # diagonals of block shapes among matrices
                    precision = _as_matrices(precision)
                information = information + np.einsum('kbn,kbij->bnij', w, precision)
        return information

    def density(self):
        """Return each sample's density under the noise, averaged over the models."""
        return self.probabilities @ np.exp(self.log_density)


def _as_matrices(diagonals):
    """Return the diagonal matrices (..., d, d) of diagonals (..., d)."""
    return diagonals[..., None] * _eye(diagonals.shape[-1])


_EYES = {}


def _eye(d):
    if d not in _EYES:
        _EYES[d] = np.eye(d)
    return _EYES[d]


def _groups(shapes):
    """
    Return the rows fitted as one batch: [[rows]], in order.

    Consecutive shapes of isotropic blocks form one batch (_Blocks fits them at once); the
    rows of any other shape form one batch each.
    """
    groups = []
    for k, shape in enumerate(shapes):
        last = shapes[groups[-1][-1]] if groups else None
        if last is not None and (last.name == shape.name or
                                 last.block is not None and shape.block is not None):
            groups[-1].append(k)
        else:
            groups.append([k])
    return groups


def fit_t(residuals, shapes, grid=NU_GRID, lost_samples=0.0, floor=None, prior=None,
          start=None):
    """
    Fit the t of the module docstring to residuals (N, d); return the NoiseFit.

    Every combination of a Shape in `shapes` and a nu on `grid` is fitted and weighed by the
    Bayesian information criterion (log-likelihood less half the free parameters times
    log N), so a full covariance counts only when the data show its shape clearly, and heavy
    tails only when the data need them. lost_samples: samples' worth of degrees of freedom
    spent on fitted parameters (the scale is divided by N minus them); floor: d variances
    added to the diagonal (so exact data do not divide by zero; a Shape of isotropic blocks
    takes each block's mean of them: give them even within its blocks); prior: per-sample
    probabilities of being good (bad_detections), which weight each sample's part in the fit;
    start: a NoiseFit of similar residuals whose weights start the EM (fewer steps; a model it
    lacks starts from the distances of its nearest model).
    """
    r = np.asarray(residuals, dtype=float)
    n, d = r.shape
    total = n if prior is None else float(prior.sum())
    count = max(total - lost_samples, 1.0)
    constants = _t_constants(tuple(grid), d)
    k = len(grid)
    same = start is not None and start.shapes == tuple(s for s in shapes for _ in grid) and \
        start.nus == constants.nus * len(shapes)    # start's rows are these models in order
    starts = []
    for index, shape in enumerate(shapes):
        rows = (list(range(index * k, index * k + k)) if same
                else _rows_of(start, shape, constants.nus))
        starts.append(_warm_start(start, rows, n, constants) if rows is not None
                      else _nearest_start(start, shape, n, constants))
    parts = []
    for group in _groups(shapes):   # the shapes fitted as one batch
        w = (starts[group[0]][0] if len(group) == 1
             else np.concatenate([starts[index][0] for index in group]))
        steps = sum((tuple(starts[index][1]) for index in group), ())
        parts.append(_fit_models(r, prior, count, tuple(shapes[i] for i in group for _ in grid),
                                 _t_constants(constants.nus * len(group), d), floor, w, steps))
    log_density = (parts[0].log_density if len(parts) == 1
                   else np.concatenate([p.log_density for p in parts]))
    parameters = (np.repeat([shape.parameters for shape in shapes], k)
                  + np.tile(constants.finite, len(shapes)))
    criteria = ((log_density.sum(axis=1) if prior is None else log_density @ prior)
                - 0.5 * math.log(max(total, 2.0)) * parameters)
    probabilities = np.exp(criteria - criteria.max())
    probabilities[probabilities <= MIN_PROBABILITY * probabilities.sum()] = 0.0   # no say
    return _noise_fit(parts, probabilities / probabilities.sum())


def _rows_of(start, shape, nus):
    """Return the rows of `start` that hold this shape with these nus in order, or None."""
    if start is None:
        return None
    rows = [k for k, s in enumerate(start.shapes) if s.name == shape.name]
    if tuple(start.nus[k] for k in rows) != nus:
        return None
    return rows


@dataclass(frozen=True)
class _Models:
    """Models fitted together (_fit_models): a NoiseFit's rows in the making."""

    shapes: tuple
    nus: tuple
    variances: np.ndarray       # (K, d) diagonal scales, or None
    matrices: tuple             # (scales, precisions) (K, d, d), or None
    model_weights: np.ndarray
    delta: np.ndarray
    log_density: np.ndarray

    def matrix_form(self):
        """Return (scales, precisions) (K, d, d)."""
        if self.matrices is not None:
            return self.matrices
        return _as_matrices(self.variances), _as_matrices(1.0 / self.variances)


def _noise_fit(parts, probabilities):
    """Return the NoiseFit of the models fitted by _fit_models (`parts`)."""
    if len(parts) == 1:
        part = parts[0]
        return NoiseFit(part.shapes, part.nus, probabilities, part.model_weights, part.delta,
                        part.log_density, part.variances, part.matrices)
    weights, delta, log_density = (np.concatenate([getattr(p, name) for p in parts])
                                   for name in ('model_weights', 'delta', 'log_density'))
    variances, matrices = None, None
    if all(p.variances is not None for p in parts):
        variances = np.concatenate([p.variances for p in parts])
    else:
        forms = [p.matrix_form() for p in parts]
        matrices = tuple(np.concatenate([f[i] for f in forms]) for i in (0, 1))
    return NoiseFit(sum((p.shapes for p in parts), ()), sum((p.nus for p in parts), ()),
                    probabilities, weights, delta, log_density, variances, matrices)


def _warm_start(start, rows, n, constants):
    """
    Return the EM's starting weights (K, N) from the rows of `start`, and each model's steps.

    WARM_EM_ITERATIONS steps (none for nu = inf), RESUMED_EM_ITERATIONS when samples were
    added since `start` (those start from weight 1; without samples: the first N weights).
    """
    m = start.model_weights.shape[1]
    w = (start.model_weights[rows[0]:rows[-1] + 1] if rows[-1] - rows[0] == len(rows) - 1
         else start.model_weights[rows])
    if m != n:
        grown = np.ones((len(rows), n))
        grown[:, :min(m, n)] = w[:, :n]
        w = grown
    return w, (constants.warm_steps if m >= n else constants.resumed_steps)


def _nearest_start(start, shape, n, constants):
    """
    Return the starting weights and steps of models `start` lacks.

    Cold (ones), or each from the distances of the model of `start` with the nearest finite nu
    (of this shape when there is one), as warm.
    """
    cold = [EM_ITERATIONS if finite else 0 for finite in constants.finite.tolist()]
    w = np.ones((len(constants.nus), n))
    if start is None:
        return w, cold
    near = [(s.name != shape.name, k) for k, (s, nu) in enumerate(zip(start.shapes, start.nus))
            if math.isfinite(nu)]
    if not near:
        return w, cold
    m = min(n, start.model_weights.shape[1])
    steps = WARM_EM_ITERATIONS if m == n else RESUMED_EM_ITERATIONS
    d = constants.d
    for i, nu in enumerate(constants.nus):
        if math.isfinite(nu):
            _, k = min(near, key=lambda item: (item[0], abs(math.log(start.nus[item[1]] / nu))))
            w[i, :m] = (nu + d) / (nu + start.delta[k, :m])
            cold[i] = steps
    return w, cold


def _fit_models(r, good, count, shapes, constants, floor, w, steps):
    """
    Fit models (row k: Shape shapes[k], nu constants.nus[k]) by EM, all at once: _Models.

    The rows are of one Shape, or of Shapes of isotropic blocks (_arithmetic). good:
    per-sample prior weights (None: all 1); w (K, N): the starting weights; steps: each
    model's EM steps (none for nu = inf, fewer from a warm start), as if fitted alone: the
    batch only shares the arithmetic.
    """
    arithmetic = _arithmetic(r, shapes, floor)
    for repeat, moving in _em_levels(tuple(steps)):
        moved = arithmetic.em_steps(w, good, count, constants.safe, constants.numerator, repeat)
        w = moved if moving is None else np.where(moving, moved, w)   # the rest are done
    scale, delta, log_det = arithmetic.fitted(w if good is None else good * w, count)
    diagonal = scale.ndim == 2
    return _Models(shapes, constants.nus, scale if diagonal else None,
                   None if diagonal else (scale, arithmetic.precision),
                   constants.weights(delta), delta, constants.log_density(delta, log_det))


@lru_cache(maxsize=32)
def _em_levels(steps):
    """
    Return the EM's stages for the rows' `steps`: [(repeat, moving)].

    In turn, `repeat` more steps of every row, kept for the rows `moving` ((K, 1) bool, None
    for all): those that take at least that many steps in all.
    """
    levels, done = [], 0
    for until in sorted(set(steps) - {0}):
        moving = np.array([s >= until for s in steps])[:, None]
        moving.flags.writeable = False
        levels.append((until - done, None if moving.all() else moving))
        done = until
    return tuple(levels)


class _TConstants:
    """What the densities and weights of t's with these nus in d dimensions need, once."""

    def __init__(self, nus, d):
        self.nus = nus
        self.nu = np.array(nus, dtype=float)
        self.finite = np.isfinite(self.nu)
        # EM steps of each model from a warm start, and after samples were added (_warm_start)
        self.warm_steps = tuple(WARM_EM_ITERATIONS if f else 0 for f in self.finite.tolist())
        self.resumed_steps = tuple(RESUMED_EM_ITERATIONS if f else 0
                                   for f in self.finite.tolist())
        self.all_finite = bool(self.finite.all())
        safe = np.where(self.finite, self.nu, 1.0)[:, None]
        norm = np.array([math.lgamma(0.5 * (v + d)) - math.lgamma(0.5 * v)
                         for v in safe[:, 0].tolist()])[:, None]
        self.d = d
        self.base = norm - 0.5 * d * np.log(safe * math.pi)
        self.half_power = 0.5 * (safe + d)
        self.inverse_nu = 1.0 / safe
        self.numerator = safe + d
        self.safe = safe
        gaussian = np.flatnonzero(~self.finite)
        # the Gaussian's rows: a slice when there is one (an index, not a copy)
        self.gaussian_rows = (slice(gaussian[0], gaussian[0] + 1) if len(gaussian) == 1
                              else gaussian)
        self.gaussian_base = -0.5 * d * math.log(2.0 * math.pi)
        # Fisher information of a location over the Gaussian one's with the scale S
        self.fisher_factor = np.where(self.finite, (safe[:, 0] + d) / (safe[:, 0] + d + 2.0),
                                      1.0)
        self.covariance_factor = np.array([_covariance_factor(v) for v in nus])

    def weights(self, delta):
        """Return (nu + d) / (nu + delta) (K, N); 1 for nu = inf."""
        w = self.numerator / (self.safe + delta)
        if not self.all_finite:
            w[self.gaussian_rows] = 1.0
        return w

    def log_density(self, delta, log_det):
        """Return the log-densities (K, N) at the distances delta, log_det the scales' (K,)."""
        half_log_det = 0.5 * log_det[:, None]
        density = self.base - half_log_det - self.half_power * np.log1p(delta * self.inverse_nu)
        if not self.all_finite:
            rows = self.gaussian_rows
            density[rows] = self.gaussian_base - half_log_det[rows] - 0.5 * delta[rows]
        return density


_T_CONSTANTS = {}


def _t_constants(nus, d):
    key = (nus, d)
    if key not in _T_CONSTANTS:
        _T_CONSTANTS[key] = _TConstants(nus, d)
    return _T_CONSTANTS[key]


class _Matrices:
    """The scale matrices of any Shape, and the distances under them (K models at once)."""

    def __init__(self, r, shape, floor):
        n, d = r.shape
        self.d, self.shape = d, shape
        # r_n r_n^T flattened (N, d^2): every scatter and distance is then one product.
        self.outer = (r[:, :, None] * r[:, None, :]).reshape(n, d * d)
        self.floor = None if floor is None else np.diag(np.broadcast_to(floor, (d,)))
        self.precision = None

    def distances(self, w, count):
        """Return r_n^T S_k^-1 r_n (K, N) under the scales S_k of the weights w (K, N)."""
        return self._solved(w, count)[2]

    def em_steps(self, w, good, count, nu, numerator, steps):
        """Return the weights w (K, N) after `steps` EM steps (nu, numerator: (K, 1))."""
        for _ in range(steps):
            w = numerator / (nu + self.distances(w if good is None else good * w, count))
        return w

    def fitted(self, w, count):
        """Return the scales (K, d, d), the distances (K, N) and log dets (K,); keep S^-1."""
        scale, self.precision, delta = self._solved(w, count)
        return scale, delta, np.linalg.slogdet(scale)[1]

    def _solved(self, w, count):
        d = self.d
        scatter = (w @ self.outer).reshape(-1, d, d) / np.reshape(count, (-1, 1, 1))
        if self.shape.project is not None:
            scatter = self.shape.project(scatter)
        scale = scatter if self.floor is None else scatter + self.floor
        precision = np.linalg.inv(scale)
        return scale, precision, precision.reshape(-1, d * d) @ self.outer.T


class _Blocks:
    """
    The same for scales sigma^2 I on blocks of axes (Shape.block), without forming a matrix.

    A row's variances need only each sample's sum of squares per block of its Shape. `sums`
    (N, C) holds them for the blocks of every block size among the rows (a column per block),
    and row k uses the columns of its own size (`own`, (K, C) 0/1): one variance per block,
    so the Shapes' models are fitted as one batch and each block's axes have the same
    variance to the last bit. A block's floor is its axes' mean (every caller's floors are even
    within a block). The EM's inner loop: the same numbers as _Matrices to rounding.
    Scales and precisions are given as their diagonals (K, d). shapes: the Shape of each
    `repeat` consecutive rows.
    """

    def __init__(self, r, shapes, floor, repeat=1):
        d = r.shape[1]
        layout = _block_layout(tuple(shape.block for shape in shapes), d, repeat)
        self.sums = (r * r) @ layout.gather                         # (N, C)
        self.sums_t = self.sums.T.copy()
        self.layout = layout
        self.own = 1.0 if layout.own is None else layout.own   # every column every row's
        self.floor = 0.0 if floor is None else _block_floor(floor, layout)
        self.precision = None

    def _variances(self, w, count):
        """Return each row's variance per block (K, C): its own columns' are its variances."""
        return (w @ self.sums) * self._scale(count) + self.floor

    def _scale(self, count):
        """Return 1 / (axes times count) per block: (C,), or (K, C) for a count per row."""
        count = np.reshape(count, (-1, 1)) if np.ndim(count) else count
        return 1.0 / (self.layout.size * count)

    def distances(self, w, count):
        """Return r_n^T S_k^-1 r_n (K, N) under the scales S_k of the weights w (K, N)."""
        return (self.own / self._variances(w, count)) @ self.sums_t

    def em_steps(self, w, good, count, nu, numerator, steps):
        """Return _Matrices.em_steps: from the sums of squares per block."""
        sums = self.sums if good is None else good[:, None] * self.sums
        scale, floor, own, sums_t = self._scale(count), self.floor, self.own, self.sums_t
        for _ in range(steps):
            w = numerator / (nu + (own / ((w @ sums) * scale + floor)) @ sums_t)
        return w

    def fitted(self, w, count):
        """Return the scales as diagonals (K, d), distances (K, N), log dets; keep S^-1."""
        layout = self.layout
        variances = self._variances(w, count)
        inverse = self.own / variances
        logs = layout.size * np.log(variances)
        if layout.own is not None:   # each row's own blocks
            variances, logs = layout.own * variances, layout.own * logs
        self.precision = inverse @ layout.expand                      # one term per axis
        return variances @ layout.expand, inverse @ self.sums_t, logs.sum(axis=-1)


def _block_floor(floor, layout):
    """Return each block's floor: its axes' mean of `floor` (d,), or `floor` if one number."""
    floor = np.asarray(floor, dtype=float)
    return float(floor.reshape(-1)[0]) if floor.size == 1 else floor @ layout.mean


@dataclass(frozen=True)
class _BlockLayout:
    """The columns of _Blocks.sums: a block each, for the block sizes of a batch's rows."""

    gather: np.ndarray    # (d, C) 0/1: squares per axis -> sums per block
    mean: np.ndarray      # (d, C): values per axis -> their mean per block
    expand: np.ndarray    # (C, d) 0/1: a value per block -> to its axes
    size: np.ndarray      # (C,) each block's axes
    own: object           # (K, C) 0/1: each row's columns; None when all are every row's


@lru_cache(maxsize=32)
def _block_layout(blocks, d, repeat):
    """Return the _BlockLayout of rows whose Shapes have these block sizes, each `repeat` times."""
    sizes = sorted(set(blocks))
    columns = [(size, start) for size in sizes for start in range(0, d, size)]
    expand = np.zeros((len(columns), d))
    for c, (size, start) in enumerate(columns):
        expand[c, start:start + size] = 1.0
    size = np.array([float(size) for size, _ in columns])
    own = None
    if len(sizes) > 1:
        own = np.repeat([[float(column[0] == block) for column in columns] for block in blocks],
                        repeat, axis=0)
    layout = _BlockLayout(expand.T.copy(), expand.T / size, expand, size, own)
    for array in (layout.gather, layout.mean, layout.expand, layout.size, own):
        if array is not None:
            array.flags.writeable = False
    return layout


def _arithmetic(r, shapes, floor, repeat=1):
    """
    Return the _Blocks of rows of isotropic-block Shapes, else the _Matrices of one Shape.

    Each of `shapes` is the Shape of `repeat` consecutive rows.
    """
    if shapes[0].block is None:
        return _Matrices(r, shapes[0], floor)
    return _Blocks(r, shapes, floor, repeat)


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
ROTATION_NOISE = (isotropic_blocks(3),)


@lru_cache(maxsize=4)
def _rotation_floors(floor):
    floors = np.full(3, floor)
    floors.flags.writeable = False
    return floors


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
    angles = np.sqrt(np.einsum('ni,ni->n', r, r))
    uniform = uniform_rotation_density(angles)
    limit = START_SIGMAS * max(median(angles) / CHI3_MEDIAN, math.sqrt(floor))
    good = (angles <= limit).astype(float)
    noise = None if start is None else start.noise
    floors = _rotation_floors(floor)
    for _ in range(MIXTURE_ITERATIONS):
        noise = fit_t(r, ROTATION_NOISE, NU_GRID, lost_samples, floors, prior=good,
                      start=noise)
        fraction = min(max(good.mean(), 0.5), 1.0 - MIN_BAD_FRACTION)
        density = fraction * noise.density()
        updated = density / (density + (1.0 - fraction) * uniform)
        if np.all(np.abs(updated - good) <= 1e-6 + 1e-5 * good):   # np.allclose's test
            break
        good = updated
    return Detections(good, noise)
