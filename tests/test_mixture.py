"""The Gaussian mixture fitted by EM (engine/trees/mixture.py): it recovers a known mixture, its
posteriors are probabilities, and it fits as well as scikit-learn's on the same rows."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.trees.mixture import fit_gaussian_mixture, kmeans


def _known_mixture(seed: int = 3):
    rng = np.random.default_rng(seed)
    means = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 1.0], [0.0, 5.0, -2.0]])
    weights = np.array([0.5, 0.3, 0.2])
    covs = [np.diag([1.0, 0.5, 0.2]), np.array([[1.0, 0.6, 0.0], [0.6, 1.0, 0.0], [0.0, 0.0, 0.3]]), 0.4 * np.eye(3)]
    counts = (weights * 12000).astype(int)
    x = np.vstack([rng.multivariate_normal(m, c, size=n) for m, c, n in zip(means, covs, counts)])
    truth = np.repeat(np.arange(3), counts)
    return x, truth, means, weights, covs


def test_em_recovers_a_known_mixture() -> None:
    x, truth, means, weights, covs = _known_mixture()
    model = fit_gaussian_mixture(x, 3, reg_covar=1e-6, seed=0)
    assert model.converged and model.iterations < 100
    # components in the order of the true means
    order = [int(np.argmin(np.linalg.norm(model.means - m, axis=1))) for m in means]
    assert sorted(order) == [0, 1, 2]
    np.testing.assert_allclose(model.means[order], means, atol=0.06)
    np.testing.assert_allclose(model.weights[order], weights, atol=0.01)
    for j, c in zip(order, covs):
        np.testing.assert_allclose(model.covariances[j], c, atol=0.08)
    posterior = model.predict_proba(x)
    np.testing.assert_allclose(posterior.sum(axis=1), 1.0, atol=1e-12)
    assert np.all((posterior >= 0) & (posterior <= 1))
    # the true component of each row is its most probable one for nearly all rows
    assert np.mean(np.argmax(posterior, axis=1) == np.asarray(order)[truth]) > 0.97


def test_precision_factors_invert_the_covariances() -> None:
    x, *_ = _known_mixture(5)
    model = fit_gaussian_mixture(x, 4, reg_covar=1e-4, seed=1)
    for cov, u in zip(model.covariances, model.precision_cholesky):
        np.testing.assert_allclose(u @ u.T @ cov, np.eye(3), atol=1e-9)
    # the log density is the textbook one
    from scipy.stats import multivariate_normal

    got = model.log_weighted(x[:50])
    want = np.column_stack(
        [
            np.log(w) + multivariate_normal(m, c).logpdf(x[:50])
            for w, m, c in zip(model.weights, model.means, model.covariances)
        ]
    )
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_fits_as_well_as_scikit_learn() -> None:
    sklearn_mixture = pytest.importorskip("sklearn.mixture")  # installed with hdbscan
    x, *_ = _known_mixture(7)
    ours = fit_gaussian_mixture(x, 3, reg_covar=1e-4, seed=0)
    theirs = sklearn_mixture.GaussianMixture(3, covariance_type="full", reg_covar=1e-4, random_state=0).fit(x)
    assert ours.log_likelihood == pytest.approx(theirs.score(x), abs=1e-3)


def test_kmeans_separates_clusters_and_refills_empty_ones() -> None:
    x, truth, *_ = _known_mixture(11)
    labels = kmeans(x, 3, np.random.default_rng(0))
    # each true component maps to one cluster for nearly all its rows
    agreement = sum(np.bincount(labels[truth == c], minlength=3).max() for c in range(3)) / len(x)
    assert agreement > 0.95
    # more clusters than distinct rows: every cluster still gets a row
    few = np.repeat(np.array([[0.0, 0.0], [1.0, 1.0]]), 5, axis=0)
    labels = kmeans(few, 3, np.random.default_rng(0))
    assert len(np.unique(labels)) == 3


def test_too_few_rows_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 6 rows"):
        fit_gaussian_mixture(np.zeros((4, 2)), 6)
