"""The modeled moments' uncertainty: moving-block bootstrap draws of the modeling window (numerics/modeling.py)."""
import numpy as np

from rdsexp.numerics.modeling import block_bootstrap_steps, moment_draws
from rdsexp.numerics.systems import MomentModel


def test_block_bootstrap_steps_are_blocks_of_consecutive_steps():
    steps = block_bootstrap_steps(23, 50, 5, seed=1)
    assert steps.shape == (50, 23) and steps.min() >= 0 and steps.max() <= 22
    blocks = steps[:, :20].reshape(50, 4, 5)                        # the first four whole blocks
    assert np.all(np.diff(blocks, axis=-1) == 1)
    np.testing.assert_array_equal(steps, block_bootstrap_steps(23, 50, 5, seed=1))
    assert np.all(np.diff(block_bootstrap_steps(4, 3, 9, seed=0), axis=-1) == 1)    # one block of the window


def test_moment_draws_are_the_models_of_the_resampled_windows():
    """Each draw is `model_distribution` of the window's estimates taken at the bootstrap's steps (an
    independent computation through MomentModel.from_samples), with and without the filtered covariances."""
    rng = np.random.default_rng(0)
    xi, xi_cov = rng.normal(size=(41, 2)), np.abs(rng.normal(size=(41, 2, 2)))
    K0, K1 = 5, 30
    for covs in (None, xi_cov):
        mean, cov = moment_draws(xi, K0, K1, covs, resamples=7, block=4, seed=3)
        steps = block_bootstrap_steps(K1 + 1, 7, 4, seed=3)
        for b in range(7):
            model = MomentModel.from_samples(xi[K0:K0 + K1 + 1][steps[b]])
            extra = 0 if covs is None else covs[K0:K0 + K1 + 1][steps[b]].mean(axis=0)
            np.testing.assert_allclose(mean[b], model.mean, rtol=1e-13)
            np.testing.assert_allclose(cov[b], model.cov + extra, rtol=1e-12, atol=1e-15)
    # a window of constant estimates has no uncertainty
    mean, cov = moment_draws(np.ones((41, 2)), K0, K1, resamples=5, block=3)
    assert np.all(mean == 1) and np.allclose(cov, 0)


def test_path_moments_of_one_path_are_its_numbers_in_any_batch():
    """Each path's window moments (`path_moments`, the simulated estimator's summary) bit for bit the same alone
    and among others, for one component too (a contiguous axis that numpy would sum pairwise)."""
    from rdsexp.numerics.modeling import path_moments
    rng = np.random.default_rng(4)
    for p in (1, 3):
        xi, cov = rng.normal(size=(101, 7, p)), rng.normal(size=(101, 7, p, p))
        mean_all, cov_all = path_moments(xi, 20, 80, cov)
        for j in range(7):
            alone = [np.ascontiguousarray(a[:, j:j + 1]) for a in (xi, cov)]    # as a run of one path holds it
            mean_one, cov_one = path_moments(alone[0], 20, 80, alone[1])
            np.testing.assert_array_equal(mean_one[0], mean_all[j])
            np.testing.assert_array_equal(cov_one[0], cov_all[j])
