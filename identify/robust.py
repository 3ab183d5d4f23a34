r"""A Huber loss for frames that a decoding error threw off, as a transform of the residuals.

Least squares minimises ``0.5 sum z^2`` of the whitened residuals ``z``. The Huber loss
``rho(z) = z^2 / 2`` for ``|z| <= k``, ``k |z| - k^2 / 2`` beyond, grows only linearly, so a frame
a hundred noise levels off pulls with the weight of ``k`` levels. Levenberg-Marquardt minimises
it unchanged when it is given the transformed residuals ``sign(z) sqrt(2 rho(z))`` (equal to ``z``
inside the threshold) and their Jacobian ``J * d/dz`` of the transform.

Wild frames are told from the model's own error by `spikes`: a decoding error throws one frame
off alone, while a model error (a discretisation's, say) is smooth from frame to frame. The
noise levels are the residuals' RMS over the other frames, so they include the model error, and
the Huber threshold lies beyond it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

NONE = 1e100  # a threshold no residual reaches: least squares (finite: inf - inf is NaN)
HUBER = 3.0  # noise levels: Gaussian frames lie within it (99.7 %), the loss is quadratic there
OUTLIER = 8.0  # robust levels: a frame this far from what its neighbours predict is an outlier
AROUND = 15  # frames: the stretch over which the typical miss is measured (short: model errors come in bursts)
MAD_TO_SIGMA = 1.0 / 0.6744897501960817  # median |z| of a unit Gaussian


def _xp(z):
    """The array module of ``z``: numpy for numpy's arrays (no program to compile for them)."""
    return jnp if isinstance(z, jax.Array) else np


def huber(z, k):
    """The residuals ``z`` transformed so that ``0.5 |out|^2`` is the Huber loss with threshold
    ``k`` (inf: unchanged)."""
    xp = _xp(z)
    a = xp.abs(z)
    outer = xp.sqrt(xp.maximum(2.0 * k * a - k * k, k * k))  # the max keeps the unused branch finite
    return xp.where(a <= k, z, xp.sign(z) * outer)


def unhuber(r, k):
    """The whitened residuals whose `huber` transform is ``r``."""
    xp = _xp(r)
    a = xp.abs(r)
    return xp.where(a <= k, r, xp.sign(r) * (a * a + k * k) / (2.0 * k))


def huber_slope(z, k):
    """d `huber` / dz at ``z``."""
    xp = _xp(z)
    a = xp.abs(z)
    return xp.where(a <= k, 1.0, k / xp.sqrt(xp.maximum(2.0 * k * a - k * k, k * k)))


def _sliding_median(a, width: int):
    """Median of ``a`` (K, 3) over ``width`` (odd) frames about each frame, the ends padded."""
    h = width // 2
    padded = np.pad(a, ((h, h), (0, 0)), mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, width, axis=0), axis=-1)


def _from_neighbours(r):
    """Each frame of ``r`` (K, 3) as the cubic through the two frames either side predicts it
    (exact for a cubic in time; the ends mirrored)."""
    p = np.pad(r, ((2, 2), (0, 0)), mode="reflect")
    return (-p[:-4] + 4.0 * p[1:-3] + 4.0 * p[3:-1] - p[4:]) / 6.0


def spikes(residuals, keep) -> np.ndarray:
    """Indices of the counted frames (``keep``) that a decoding error threw off: a residual (M, 3)
    that misses what its neighbours predict (`_from_neighbours`) by more than `OUTLIER` times
    the typical miss around it (the median over `AROUND` frames) in some column, and more than
    its neighbours miss. A model's own error is smooth from frame to frame and its neighbours
    predict it; a frame thrown off is off alone. Found one by one in each stretch, each replaced
    by its prediction before the next is sought, so a wild frame does not hide a neighbour."""
    idx = np.flatnonzero(keep)
    r = np.array(residuals, float)[idx]
    wild = np.zeros(r.shape[0], bool)
    if r.shape[0] < AROUND:
        return np.zeros(0, int)
    for _ in range(r.shape[0]):
        pred = _from_neighbours(r)
        miss = np.abs(r - pred)
        level = MAD_TO_SIGMA * np.maximum(_sliding_median(miss, AROUND), np.median(miss, axis=0))
        ratio = np.max(miss / np.maximum(level, 1e-300), axis=1)
        padded = np.pad(ratio, 2)
        peak = np.all([ratio >= padded[2 + k : 2 + k + ratio.size] for k in (-2, -1, 1, 2)], axis=0)
        new = peak & (ratio > OUTLIER) & ~wild
        if not np.any(new):
            break
        r[new] = pred[new]
        wild |= new
    return idx[wild]


def noise_level(residuals) -> float:
    """The root-mean-square of ``residuals`` (any shape)."""
    return float(np.sqrt(np.mean(np.square(residuals))))


def noise_levels(residuals) -> np.ndarray:
    """Noise levels (m, m, rad) of the three columns from ``residuals`` (M, 3) in their units:
    one level (`noise_level`) for the two positions, one for the angle."""
    return np.maximum([noise_level(residuals[:, :2])] * 2 + [noise_level(residuals[:, 2])], 1e-15)


def clean_noise_levels(residuals, keep) -> np.ndarray:
    """`noise_levels` of ``residuals`` (M, 3) over the counted frames ``keep`` that a decoding
    error did not throw off (`spikes`)."""
    clean = np.array(keep, bool)
    clean[spikes(residuals, keep)] = False
    return noise_levels(np.asarray(residuals)[clean])
