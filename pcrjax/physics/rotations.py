"""Small rotation helpers written elementwise (3x3 products as sums of columns).

On XLA:CPU, elementwise 3-vector arithmetic fuses into one kernel, while tiny `dot`s do not
(each is a kernel of its own, and kernels are what a CPU step pays for).
"""

import jax.numpy as jnp


def cross(a, b):
    """$a \\times b$ for 3-vectors."""
    return jnp.stack(
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    )


def matvec(R, v):
    """$R v$ for a 3x3 matrix."""
    return R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2]


def rmatvec(R, v):
    """$R^T v$ for a 3x3 matrix."""
    return R[0, :] * v[0] + R[1, :] * v[1] + R[2, :] * v[2]


def matmul(A, B):
    """$A B$ for 3x3 matrices."""
    return jnp.stack([matvec(A, B[:, j]) for j in range(3)], axis=1)


def transpose_matmul(A, B):
    """$A^T B$ for 3x3 matrices."""
    return jnp.stack([rmatvec(A, B[:, j]) for j in range(3)], axis=1)


def hat(a):
    """Skew matrix $\\hat a$ with $\\hat a b = a \\times b$."""
    z = jnp.zeros_like(a[0])
    return jnp.stack(
        [
            jnp.stack([z, -a[2], a[1]]),
            jnp.stack([a[2], z, -a[0]]),
            jnp.stack([-a[1], a[0], z]),
        ]
    )


def skew_vee(R):
    """$\\frac12 (R - R^T)^\\vee$: for a rotation by angle $\\phi$ about $k$, $\\sin\\phi\\, k$."""
    return 0.5 * jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])


def cayley(a):
    """Rotation $R = (I - \\hat a/2)^{-1}(I + \\hat a/2)$, smooth for every $a$.

    Used to parametrise rotation unknowns in multiple shooting; rotation angle is
    $2\\arctan(|a|/2)$.
    """
    A = hat(a)
    c = 4.0 / (4.0 + jnp.dot(a, a))
    return jnp.eye(3, dtype=a.dtype) + c * (A + 0.5 * matmul(A, A))


def cayley_inverse(R):
    """Inverse of `cayley`: $a = 2 (R - R^T)^\\vee / (1 + \\mathrm{tr} R)$."""
    return 4.0 * skew_vee(R) / (1.0 + jnp.trace(R))


def quaternion(R):
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (Shepperd's method:
    the branch with the largest pivot, so every rotation, including angle pi, is handled)."""
    t = jnp.trace(R)
    cands = jnp.stack(
        [
            jnp.stack([1.0 + t, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]),
            jnp.stack([R[2, 1] - R[1, 2], 1.0 + 2 * R[0, 0] - t, R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]]),
            jnp.stack([R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], 1.0 + 2 * R[1, 1] - t, R[1, 2] + R[2, 1]]),
            jnp.stack([R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1.0 + 2 * R[2, 2] - t]),
        ]
    )
    pivots = jnp.stack([t, R[0, 0], R[1, 1], R[2, 2]])
    q = cands[jnp.argmax(pivots)]
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[0] < 0, -q, q)


def rotation_vector(R):
    """Rotation vector (axis times angle, rad) of a rotation matrix, angle in $[0, \\pi]$."""
    q = quaternion(R)
    sn = jnp.sqrt(jnp.dot(q[1:], q[1:]) + 1e-300)
    small = sn < 1e-8
    safe_sn = jnp.where(small, 1.0, sn)
    angle = 2.0 * jnp.arctan2(sn, q[0])
    scale = jnp.where(small, 2.0 / q[0], angle / safe_sn)  # 2 atan2(s, w)/s -> 2/w as s -> 0
    return scale * q[1:]


def exp_map(a):
    """Rotation $\\exp(\\hat a)$ by angle $|a|$ about $a$ (Rodrigues), smooth at $a = 0$."""
    t2 = jnp.dot(a, a)
    small = t2 < 1e-8
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    s1 = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    s2 = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / t2s)
    A = hat(a)
    return jnp.eye(3, dtype=a.dtype) + s1 * A + s2 * matmul(A, A)


def rotz(theta):
    """Rotation by ``theta`` (rad) about the global z axis."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    z, o = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])
