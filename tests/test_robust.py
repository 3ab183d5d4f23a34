"""The Huber loss as a transform of residuals, against its definition and finite differences."""

import jax.numpy as jnp
import numpy as np

from identify import robust


def test_huber_transform_gives_the_huber_loss_and_its_slope():
    z = np.linspace(-10.0, 10.0, 2001)
    k = 3.0
    rho = np.where(np.abs(z) <= k, 0.5 * z**2, k * np.abs(z) - 0.5 * k**2)
    r = np.asarray(robust.huber(jnp.asarray(z), k))
    assert np.allclose(0.5 * r**2, rho, rtol=1e-14, atol=1e-14)
    h = 1e-6
    fd = (np.asarray(robust.huber(jnp.asarray(z + h), k)) - np.asarray(robust.huber(jnp.asarray(z - h), k))) / (2 * h)
    away = np.abs(np.abs(z) - k) > 2 * h  # the slope is continuous; its derivative is not, at |z| = k
    assert np.allclose(np.asarray(robust.huber_slope(jnp.asarray(z), k))[away], fd[away], rtol=1e-7)
    assert np.allclose(np.asarray(robust.unhuber(jnp.asarray(r), k)), z, rtol=1e-13)
    # no threshold: least squares
    assert np.array_equal(np.asarray(robust.huber(jnp.asarray(z), robust.NONE)), z)


def test_spikes_are_single_wild_frames_not_a_smooth_model_error():
    rng = np.random.default_rng(0)
    t = np.arange(2000) * 1e-3
    res = rng.standard_normal((2000, 3)) * 2e-6
    res[:, 0] += 3e-4 * np.exp(-t / 0.02) * np.sin(2 * np.pi * 9 * t)  # a model error 150 noise levels large
    wild = rng.random(2000) < 0.01
    res[wild, 1] += 2e-4  # 1 % of frames 100 noise levels off
    keep = np.ones(2000, bool)
    assert set(robust.spikes(res, keep)) == set(np.flatnonzero(wild))
    keep[np.flatnonzero(wild)[:3]] = False  # frames not counted are not reported
    assert set(robust.spikes(res, keep)) == set(np.flatnonzero(wild)[3:])
