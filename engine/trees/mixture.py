"""A Gaussian mixture with full covariances, fitted by expectation-maximisation (EM).

The leaf-wood separation (:mod:`~forestreg.engine.trees.leafwood`) fits a mixture of a few
components to some thousand feature rows and then evaluates the posteriors of millions of rows.
This is the textbook algorithm (Bishop 2006, sec. 9.2), with scikit-learn's conventions:
k-means++ seeding and Lloyd's k-means as the initial responsibilities, ``reg_covar`` added to
every covariance's diagonal, Cholesky factors of the precisions, and a stop when the mean
log-likelihood gains less than ``tol`` in an iteration. It is here rather than imported because
importing scikit-learn's mixture took 58 MB and 0.5 s of every ``forestreg trees`` run (the
command's peak memory); the fit itself is a few milliseconds.

Units: whatever the rows' columns are in; the model is in the same units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular
from scipy.special import logsumexp

__all__ = ["GaussianMixture", "fit_gaussian_mixture", "kmeans"]


@dataclass(frozen=True)
class GaussianMixture:
    """A fitted mixture of ``k`` Gaussians in ``d`` dimensions.

    ``weights`` (k,) sum to 1; ``means`` (k, d); ``covariances`` (k, d, d) (with the
    regularisation added); ``precision_cholesky`` (k, d, d) upper factors ``U`` with
    ``inverse(covariance) = U @ U.T``; ``converged`` whether the stop rule was met within the
    iterations, after ``iterations`` of them; ``log_likelihood`` the mean per row at the end.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    precision_cholesky: np.ndarray
    converged: bool
    iterations: int
    log_likelihood: float

    def log_weighted(self, x: np.ndarray) -> np.ndarray:
        """``log(weight_j) + log N(x_i | mean_j, cov_j)`` (n, k) of rows ``x`` (n, d)."""
        x = np.asarray(x, dtype=np.float64)
        n, d = x.shape
        out = np.empty((n, len(self.weights)))
        for j, (mean, u) in enumerate(zip(self.means, self.precision_cholesky)):
            y = (x - mean) @ u
            out[:, j] = -0.5 * np.einsum("ij,ij->i", y, y)
        log_det = np.log(np.diagonal(self.precision_cholesky, axis1=1, axis2=2)).sum(axis=1)
        out += -0.5 * d * np.log(2.0 * np.pi) + log_det + np.log(self.weights)
        return out

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        """Posterior probabilities (n, k) of the components for rows ``x`` (n, d); rows sum to 1."""
        log_weighted = self.log_weighted(x)
        return np.exp(log_weighted - logsumexp(log_weighted, axis=1, keepdims=True))


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, *, max_iter: int = 300, tol: float = 1e-4) -> np.ndarray:
    """Cluster labels (n,) of rows ``x`` (n, d) into ``k`` clusters: k-means++ seeding (each
    next centre drawn with probability proportional to the squared distance to the nearest
    centre so far, the best of ``2 + log k`` draws), then Lloyd's iterations until no label
    changes or the centres move (sum of squares) less than ``tol`` times the rows' mean variance
    per column. A cluster left empty takes the row farthest from its centre."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    sq = np.einsum("ij,ij->i", x, x)
    centres = np.empty((k, x.shape[1]))
    centres[0] = x[rng.integers(n)]
    closest = np.maximum(sq - 2.0 * x @ centres[0] + centres[0] @ centres[0], 0.0)
    trials = 2 + int(np.log(k))
    for c in range(1, k):
        total = closest.sum()
        if total <= 0.0:  # fewer distinct rows than clusters: any row
            picks = rng.integers(n, size=trials)
        else:
            picks = np.minimum(np.searchsorted(np.cumsum(closest), rng.random(trials) * total), n - 1)
        d2 = np.maximum(sq[:, None] - 2.0 * x @ x[picks].T + sq[picks][None, :], 0.0)
        candidates = np.minimum(closest[:, None], d2)
        best = int(np.argmin(candidates.sum(axis=0)))
        centres[c] = x[picks[best]]
        closest = candidates[:, best]
    labels = np.full(n, -1)
    shift_tol = tol * float(np.mean(np.var(x, axis=0)))
    for _ in range(max_iter):
        d2 = sq[:, None] - 2.0 * x @ centres.T + np.einsum("ij,ij->i", centres, centres)[None, :]
        new = np.argmin(d2, axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=k)
        before = centres.copy()
        for c in range(k):
            if counts[c]:
                centres[c] = x[labels == c].mean(axis=0)
            else:  # an empty cluster: the row farthest from its own centre starts it again
                far = int(np.argmax(d2[np.arange(n), labels]))
                centres[c] = x[far]
                labels[far] = c
        if counts.all() and float(((centres - before) ** 2).sum()) <= shift_tol:
            break
    return labels


def _m_step(x: np.ndarray, resp: np.ndarray, reg_covar: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weights, means, covariances and precision Cholesky factors from responsibilities (n, k)."""
    nk = resp.sum(axis=0) + 10.0 * np.finfo(np.float64).eps
    means = (resp.T @ x) / nk[:, None]
    d = x.shape[1]
    covariances = np.empty((len(nk), d, d))
    factors = np.empty((len(nk), d, d))
    for j in range(len(nk)):
        diff = x - means[j]
        covariances[j] = (resp[:, j, None] * diff).T @ diff / nk[j]
        covariances[j].flat[:: d + 1] += reg_covar
        try:
            lower = np.linalg.cholesky(covariances[j])
        except np.linalg.LinAlgError as exc:
            raise np.linalg.LinAlgError(
                f"the mixture's component {j} has a singular covariance: increase reg_covar ({reg_covar:g})"
            ) from exc
        factors[j] = solve_triangular(lower, np.eye(d), lower=True).T
    return nk / len(x), means, covariances, factors


def fit_gaussian_mixture(
    x: np.ndarray, k: int, *, reg_covar: float = 1e-6, max_iter: int = 100, tol: float = 1e-3, seed: int = 0
) -> GaussianMixture:
    """Fit a ``k``-component full-covariance Gaussian mixture to rows ``x`` (n, d) by EM.

    Initial responsibilities are the one-hot labels of :func:`kmeans` (seeded with ``seed``);
    each iteration takes the expectation then the maximisation step, and the fit stops when the
    mean log-likelihood per row gains less than ``tol`` (or after ``max_iter`` iterations:
    ``converged`` is then False). ``reg_covar`` is added to every covariance's diagonal.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or len(x) < k:
        raise ValueError(f"a mixture of {k} components needs at least {k} rows of shape (n, d), got {x.shape}")
    rng = np.random.default_rng(seed)
    resp = np.zeros((len(x), k))
    resp[np.arange(len(x)), kmeans(x, k, rng)] = 1.0
    model_parts = _m_step(x, resp, reg_covar)
    previous, converged, iterations = -np.inf, False, 0
    log_likelihood = -np.inf
    for iterations in range(1, max_iter + 1):
        model = GaussianMixture(*model_parts, converged=False, iterations=iterations, log_likelihood=previous)
        log_weighted = model.log_weighted(x)
        log_norm = logsumexp(log_weighted, axis=1)
        log_likelihood = float(log_norm.mean())
        resp = np.exp(log_weighted - log_norm[:, None])
        model_parts = _m_step(x, resp, reg_covar)
        if abs(log_likelihood - previous) < tol:
            converged = True
            break
        previous = log_likelihood
    return GaussianMixture(*model_parts, converged=converged, iterations=iterations, log_likelihood=log_likelihood)
