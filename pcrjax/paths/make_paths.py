"""Write the shipped platform paths (`pcrjax inverse SCENE --path NAME`), relative to the
shipped scenes' rest poses (their static equilibria).

* ``triskele_circle``: thesis section 4.3.2: from rest, a straight lead-in at 15.7 mm/s to a
  circle of radius 5 mm about the rest position, then one turn at 3.14 rad/s, sampled every 1 ms.
  As printed, the speed jumps from 0 to 15.7 mm/s at t = 0 and the lead-in meets the circle at a
  right angle: both need an unbounded force (a 40 g platform stopped and started within one 1 ms
  step needs about 1 N; the rods buckle at 32 mN), and no solver can follow that from rest. The
  shipped path is the thesis's convolved with a 0.1 s Hann window (delayed by half of it, so it
  starts from rest at t = 0): peak platform acceleration about 0.4 m/s^2, the path within
  0.3 mm of the thesis's near the start and the corner and on it elsewhere (2.42 s).
* ``triskele_move``: a 1 mm point-to-point move along x in 0.3 s (quintic smooth step, zero
  velocity and acceleration at both ends), then 0.1 s at rest.
* ``stewart_gough_circle``: the platform centre moves out 5 mm from its rest position in 0.5 s
  (quintic smooth step), then circles about it in its horizontal plane, the angular speed eased
  in over 0.5 s up to a turn in 2 s, while the platform's tilt axis follows the direction of
  travel (up to 2 degrees).

Run ``python -m pcrjax.paths.make_paths`` after changing a shipped scene's rest pose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).parent


def _smooth(u):
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)


def triskele_circle(x0, y0, theta0, radius=5e-3, speed=15.7e-3, omega=3.14, dt=1e-3, window=0.1):
    t_lead = radius / speed
    h = int(round(0.5 * window / dt))  # half window in samples
    T = t_lead + 2.0 * np.pi / omega + 2 * h * dt
    t = np.arange(0.0, T + 0.5 * dt, dt)
    tr = np.arange(-h, t.size + h) * dt - 2 * h * dt  # the thesis's clock, delayed by the window
    lead = tr <= t_lead
    x = np.where(tr < 0, 0.0, np.where(lead, speed * tr, radius * np.cos(omega * (tr - t_lead))))
    y = np.where(lead, 0.0, radius * np.sin(omega * (tr - t_lead)))
    k = np.hanning(2 * h + 3)[1:-1]
    k /= k.sum()
    xs, ys = np.convolve(x, k, mode="valid"), np.convolve(y, k, mode="valid")
    return t, np.stack([x0 + xs, y0 + ys, np.full_like(t, theta0)], axis=1)


def triskele_move(x0, y0, theta0, distance=1e-3, duration=0.3, rest=0.1, dt=1e-3):
    t = np.arange(0.0, duration + rest + 0.5 * dt, dt)
    return t, np.stack([x0 + distance * _smooth(t / duration), np.full_like(t, y0), np.full_like(t, theta0)], axis=1)


def stewart_gough_circle(p0, rv0, radius=5e-3, lead=0.5, ramp=0.5, period=2.0, tilt=np.deg2rad(2.0), dt=1.0 / 120.0):
    t = np.arange(0.0, lead + ramp + period + 0.5 * dt, dt)
    r = radius * _smooth(t / lead)
    # angular speed eased in over ``ramp`` after the lead-in: the path stays C2 (no velocity jump
    # where the radial lead-in turns into the circle)
    fine = np.linspace(0.0, t[-1], 20 * t.size + 1)
    omega = 2.0 * np.pi / period * _smooth((fine - lead) / ramp)
    phase = np.interp(t, fine, np.concatenate([[0.0], np.cumsum(0.5 * (omega[1:] + omega[:-1]) * np.diff(fine))]))
    x, y = r * np.cos(phase), r * np.sin(phase)
    wob = tilt * _smooth(t / lead)
    rv = np.stack([rv0[0] + wob * np.sin(phase), rv0[1] + wob * (1.0 - np.cos(phase)), np.full_like(t, rv0[2])], axis=1)
    return t, np.concatenate([np.stack([p0[0] + x, p0[1] + y, np.full_like(t, p0[2])], axis=1), rv], axis=1)


def _write(name, header, t, v):
    rows = [",".join(header)] + [",".join(f"{a:.17g}" for a in (ti, *vi)) for ti, vi in zip(t, v)]
    (HERE / f"{name}.csv").write_text("\n".join(rows) + "\n")


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    from pcrjax import load_scene, solve_static
    from pcrjax.io.tables import PLANAR_PATH, SPATIAL_PATH

    tri = solve_static(load_scene("triskele"))
    x0, y0, th0 = float(tri.position[0]), float(tri.position[1]), float(tri.rotation_vector[2])
    _write("triskele_circle", PLANAR_PATH, *triskele_circle(x0, y0, th0))
    _write("triskele_move", PLANAR_PATH, *triskele_move(x0, y0, th0))
    sg = solve_static(load_scene("stewart_gough"))
    _write("stewart_gough_circle", SPATIAL_PATH, *stewart_gough_circle(np.asarray(sg.position), np.asarray(sg.rotation_vector)))


if __name__ == "__main__":
    main()
