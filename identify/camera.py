"""What the encoded-pattern camera sees of a simulated motion (thesis 5.1.2, DESIGN §4).

* **Frame transform**: the camera reports the pose in an unknown pattern frame, a planar rigid
  transform of the robot frame: ``[x, y]_cam = R(beta) [x, y] + offset``, ``theta_cam = theta + beta``.
* **Clock**: frame ``k`` at camera time ``t_k`` shows the robot at ``t_k + time_offset`` (the
  unknown delay between the actuator command, robot time 0, and the first frame).
* **Exposure**: each frame averages the motion over its exposure window (0.2 ms), by 3-point
  Gauss-Legendre quadrature of a Catmull-Rom (C1 cubic) interpolant of the simulated samples.
  114.44 frames/s puts Nyquist at 57.2 Hz, so the Triskele's third platform mode (85 Hz) aliases
  (to 30 Hz): the model is compared at the frame times, never step by step.

All functions are pure jnp and differentiable in every argument (offsets, rotation, time offset).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

_GL_NODES = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GL_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0


def catmull_rom(samples, dt, t):
    """Interpolate ``samples`` (T, d), taken at ``k dt`` (k = 0..T-1), at times ``t`` (M,).

    Clamped to the sampled range; C1, exact for quadratics, error O(dt^3) (away from the ends).
    """
    T = samples.shape[0]
    u = jnp.clip(t / dt, 0.0, T - 1.0)
    k = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, T - 2)
    s = (u - k)[:, None]
    p0 = samples[jnp.clip(k - 1, 0, T - 1)]
    p1 = samples[k]
    p2 = samples[k + 1]
    p3 = samples[jnp.clip(k + 2, 0, T - 1)]
    return 0.5 * (
        2.0 * p1 + (p2 - p0) * s + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * s**2 + (3.0 * p1 - p0 - 3.0 * p2 + p3) * s**3
    )


def exposure_average(samples, dt, frame_times, exposure):
    """Mean of the interpolated motion over ``[t - exposure/2, t + exposure/2]`` for each frame."""
    out = 0.0
    for xi, w in zip(_GL_NODES, _GL_WEIGHTS):
        out = out + w * catmull_rom(samples, dt, frame_times + 0.5 * exposure * xi)
    return out


def to_camera(pose, offset, rotation):
    """Robot-frame planar poses (M, 3) = x, y, theta -> camera pattern frame."""
    c, s = jnp.cos(rotation), jnp.sin(rotation)
    x = c * pose[:, 0] - s * pose[:, 1] + offset[0]
    y = s * pose[:, 0] + c * pose[:, 1] + offset[1]
    return jnp.stack([x, y, pose[:, 2] + rotation], axis=1)


def observe(pose_samples, dt, frame_times, exposure, offset, rotation, time_offset):
    """Camera poses (M, 3) of a simulated planar motion ``pose_samples`` (T, 3) sampled every ``dt``."""
    seen = exposure_average(pose_samples, dt, frame_times + time_offset, exposure)
    return to_camera(seen, offset, rotation)
