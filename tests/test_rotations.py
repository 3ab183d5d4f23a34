"""The elementwise rotation helpers against numpy's products and closed forms."""

import jax
import jax.numpy as jnp
import numpy as np

from pcrjax.physics import rotations as rot


def _rotation(rng):
    """A random proper rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_products_are_numpys():
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=3), rng.normal(size=3)
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    f = jax.jit(
        lambda a, b, A, B: (
            rot.cross(a, b),
            rot.matvec(A, a),
            rot.rmatvec(A, a),
            rot.matmul(A, B),
            rot.transpose_matmul(A, B),
            rot.hat(a) @ b,
        )
    )
    got = f(a, b, A, B)
    want = (np.cross(a, b), A @ a, A.T @ a, A @ B, A.T @ B, np.cross(a, b))
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape and np.allclose(g, w, rtol=0, atol=1e-14)
    # batched over a leading axis, as the legs are
    batch = jax.vmap(rot.cross)(jnp.stack([a, b]), jnp.stack([b, a]))
    assert np.allclose(batch, [np.cross(a, b), np.cross(b, a)], rtol=0, atol=1e-14)


def test_quaternion_and_rotation_vector_invert_the_exponential():
    """Random rotation vectors of every angle up to pi (Shepperd's four branches), and a half
    turn about each axis, come back from exp_map through rotation_vector; the quaternion's
    vector part is sin(angle/2) times the axis."""
    rng = np.random.default_rng(11)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0.0, np.pi * (1 - 1e-9), size=40)
    vecs = np.concatenate([axes * angles[:, None], np.pi * (1 - 1e-9) * np.eye(3)])
    back = jax.jit(jax.vmap(lambda a: rot.rotation_vector(rot.exp_map(a))))(vecs)
    assert np.allclose(back, vecs, rtol=0, atol=1e-6)  # near pi the axis is conditioned as 1/sin
    q = jax.jit(jax.vmap(lambda a: rot.quaternion(rot.exp_map(a))))(vecs[:40])
    assert np.allclose(q[:, 1:], axes * np.sin(angles / 2)[:, None], rtol=0, atol=1e-12)
    assert np.allclose(q[:, 0], np.cos(angles / 2), rtol=0, atol=1e-12)
    R = _rotation(rng)
    assert np.allclose(
        rot.skew_vee(R), 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]), rtol=0, atol=1e-15
    )
