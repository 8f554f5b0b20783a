"""bench sweep's adaptive-bounce bound: the oracle allocation's ray saving
against its closed form on synthetic estimates with known per-texel noise."""
import numpy as np
import pytest

from prtt_addon.dev.bench.adaptive_bound import oracle_gain


def _pair(sigma, channels=400, seed=0):
    """Two independent estimates of zero per texel as (channels, T, 1)
    planes, texel i with total variance sigma_i^2 spread over ``channels``
    channels."""
    rng = np.random.default_rng(seed)
    s = (np.asarray(sigma, float) / np.sqrt(channels))[None, :, None]
    shape = (channels, len(sigma), 1)
    return rng.normal(size=shape) * s, rng.normal(size=shape) * s, np.ones((len(sigma), 1), bool)


def test_two_noise_levels_give_the_neyman_saving():
    sigma = np.r_[np.full(3600, 1.0), np.full(400, 10.0)]
    # T sum s^2 / (sum s)^2 = 4000 * 43600 / 7600^2
    r = oracle_gain(*_pair(sigma))
    assert r["gain"] == pytest.approx(4000 * 43600 / 7600 ** 2, rel=0.02)
    assert r["top10_share"] == pytest.approx(40000 / 43600, rel=0.01)     # the top 10 % are the sigma=10 texels


def test_even_noise_saves_nothing_and_a_masked_texel_is_ignored():
    a, b, mask = _pair(np.ones(3000))
    a[:, 0, 0] += 1e6                   # a texel outside the mask must not count
    mask[0] = False
    assert oracle_gain(a, b, mask)["gain"] == pytest.approx(1.0, abs=0.01)


def test_one_noisy_texel_in_many_gives_a_large_saving():
    sigma = np.r_[np.full(999, 0.01), [10.0]]
    assert oracle_gain(*_pair(sigma))["gain"] > 50
