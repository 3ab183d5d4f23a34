"""Generate the shipped synthetic recordings (DESIGN §4): ``python experiments_data/generate.py``.

No measured log of the Triskele-bot is public, so these recordings are simulated from stated
"true" parameters that differ from the nominal scenes, then filmed by a model of the thesis's
encoded-pattern camera (5.1.2): 114.44 frames/s, 0.2 ms exposure (each frame averages the
motion over it), the pose reported in an unknown pattern frame (millimetres, degrees), a small
unknown delay between the actuator command and the first frame, sensor noise of nanometres and
microradians, and a few percent of frames that failed to decode (absent rows). Each CSV's
sidecar says ``synthetic = true`` and holds every generating number and the seed.

The first three are simulated with the solver settings written in the sidecar (the ones a fit
uses), so a fit can recover them to the noise level. The random-truth suite (`random_suite`,
names ending ``_r1``, ``_r2``) is not the fit's own model: its truths are drawn, seeded, inside
the prior a fit is promised to hold in (each length within 2 mm of nominal, the damping time
anywhere in a decade, the push within 10 % of the recorded one) and simulated on a finer grid
than the sidecar's (the sidecars' ``[provenance]`` says which): 9x in space on the Triskele-bot,
3x on the cantilever, and in time extrapolated to dt 0 from 5x and 10x (Triskele) or 50x and
100x (cantilever), so a fit meets the discretisation error it would meet on a real log. The
truth's grid is converged at the noise: at 5x in time alone the filmed pose was off the
converged motion by 17 um on the cantilever (noise 2 um) and 4.9 nm on the Triskele push (noise
2 nm), which put the fit's answer, extrapolated to dt 0, 38 standard errors from the
cantilever's drawn length; the Triskele truths are within about 0.2 nm of the converged motion
(`FINER` says how that was measured); the cantilever's extrapolation moved the filmed pose by
up to 0.07 um from dt / 100 alone.

``--draws N NAME``: NAME's truth filmed N times with other noise seeds (`noise_draws`), to
measure how far the noise alone moves a fit's answer against the errors it reports.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))

import pcrjax  # noqa: E402
from identify import camera, experiment  # noqa: E402
from identify.recording import OVERRIDES, Recording, load_recording, write_recording  # noqa: E402

SOLVER_TRISKELE = dict(nodes=10, integrator="rk4", dt=5e-4, alpha=-0.45, tol=1e-10)
# At the truth lengths the platform's lowest modes are 18.9, 46.8 and 84.7 Hz (the last aliased
# to 29.7 Hz by the camera). Kelvin-Voigt damping decays each at tau omega^2 / 2: tau = 0.4 ms
# gives 2.8 /s for the lowest (e^-2.8 within 1 s: the oscillations decay within about a second,
# as the issue asks), 17 /s and 57 /s for the others.
TRISKELE_TRUTH = dict(tau=4e-4, lengths=[0.0312, 0.0329, 0.0308])

# The thesis's camera (5.1.2) on the Triskele-bot, 2 s, nominal damping 0.15 ms switched on
# (the fits start from a factor 3 off the truth, as the issue asks).
TRISKELE_CAMERA = dict(
    scene="triskele",
    frame_rate=114.44,
    exposure=2e-4,
    seconds=2.0,
    solver=SOLVER_TRISKELE,
    effects=dict(damping=True),
    rod=dict(tau=1.5e-4),
)

RECORDINGS = {
    "triskele_push_release": dict(
        TRISKELE_CAMERA,
        experiment="push_release",
        description="Triskele-bot free motion after a push on the platform is released at t = 0 (thesis 5.2), 2 s.",
        load=dict(force=[0.02, 0.0, 0.0], moment=[0.0, 0.0, 4e-4], release_time=0.0),
        truth=dict(
            TRISKELE_TRUTH,
            push_force=[0.0168, 0.0044],
            push_moment=3.2e-4,
            frame_offset=[1.3e-3, -0.7e-3],
            frame_rotation=0.026,
            time_offset=3.1e-3,
            noise_position=2e-9,
            noise_angle=2e-6,
            missing_fraction=0.03,
            seed=11,
        ),
    ),
    "triskele_actuator_step": dict(
        TRISKELE_CAMERA,
        experiment="actuator_step",
        description="Triskele-bot actuator step: bases slide by +10, -5, +2.5 um in a 10 ms smooth step at t = 0.05 s "
        "(fast, yet no fibre is pushed near its 32 mN buckling load), 2 s.",
        load=dict(force=[0.0, 0.0, 0.0], moment=[0.0, 0.0, 0.0]),
        actuation=dict(initial=[0.0, 0.0, 0.0], final=[1e-5, -5e-6, 2.5e-6], kind="smooth_step", start_time=0.05, duration=0.01),
        truth=dict(
            TRISKELE_TRUTH,
            frame_offset=[-0.9e-3, 2.1e-3],
            frame_rotation=-0.035,
            time_offset=2.4e-3,
            noise_position=2e-9,
            noise_angle=2e-6,
            missing_fraction=0.03,
            seed=12,
        ),
    ),
    "cantilever_release": dict(
        scene="cantilever",
        experiment="release",
        description="Thesis cantilever released from a tip load at t = 0, tip marker filmed at 1 kHz in the bending plane "
        "(the setting of Till & Rucker's validation), 1 s.",
        frame_rate=1000.0,
        exposure=1e-4,
        seconds=1.0,
        solver=dict(nodes=20, integrator="rk4", dt=1e-3, alpha=-0.45, tol=1e-10),
        effects=dict(damping=True),
        rod=dict(tau=1e-3),
        tip=dict(force=[0.0, 0.0, -2.0], moment=[0.0, 0.0, 0.0], release_time=0.0),
        # first mode 8.9 Hz: tau = 1.9 ms gives zeta = 0.053, decaying by e^-3 within 1 s
        truth=dict(
            tau=1.9e-3,
            lengths=0.4016,
            push_force=[0.0, -1.93],
            frame_offset=[-0.21, 0.013],
            frame_rotation=0.012,
            time_offset=1.7e-3,
            noise_position=2e-6,
            noise_angle=2e-5,
            missing_fraction=0.02,
            seed=13,
        ),
    ),
}

# The prior of the random-truth suite: lengths within PRIOR_LENGTH of the scene's, tau log-uniform
# over a decade, the push released within PUSH_ERROR of the sidecar's; the fit starts from the
# nominal lengths and a tau a factor 3 off the truth.
PRIOR_LENGTH = 2e-3
PUSH_ERROR = 0.1
TAU_DECADE = {"triskele": (1e-4, 1e-3), "cantilever": (1e-3, 1e-2)}
# The truth's grid: nodes x9 on the Triskele-bot and x3 on the cantilever, and in time
# Richardson's extrapolation from dt / FINER and twice that (BDF-alpha is second order, so
# s(h) + (s(h) - s(2h)) / 3 removes the h^2 term). The cantilever's dt / 100 alone was 0.25
# standard errors of its fitted length off in time.
# Measured on the platform of `triskele_push_release_r2`'s truth (first 0.1 s at 30 nodes; first
# 0.3 s at 30, 60 and 120 nodes, dt 125 us): in time, dt / 5 alone is 4.9 nm off, and the
# extrapolation from dt / 5 and dt / 10 is 0.04 nm from the one from dt / 20 and dt / 40, which is
# better than dt / 40 alone (0.08 nm off); in space, RK4 is fourth order (30 to 60 nodes 13 nm,
# 60 to 120 nodes 0.81 nm, ratio 15.7), so 90 nodes are about 0.17 nm off. The noise is 2 nm.
FINER = dict(nodes={"triskele": 9, "cantilever": 3}, dt={"push_release": 10, "release": 100, "actuator_step": 10})


def _camera_truth(rng, seed: int) -> dict:
    return dict(
        frame_offset=np.round(rng.uniform(-2e-3, 2e-3, 2), 6).tolist(),
        frame_rotation=round(float(rng.uniform(-0.04, 0.04)), 4),
        time_offset=round(float(rng.uniform(0.0, 4e-3)), 5),
        seed=seed,
    )


def _start_tau(rng, tau: float) -> dict:
    """The sidecar's [rod] table: the damping a fit starts from, a factor 3 off ``tau`` either way."""
    return dict(tau=round(float(tau * 3.0 ** rng.choice([-1, 1])), 7))


def _as_recorded(rng, push) -> list:
    """The push as the sidecar records it: each component within PUSH_ERROR of the truth's."""
    return [p * (1 + rng.uniform(-PUSH_ERROR, PUSH_ERROR)) for p in push]


def random_suite(seed: int = 2026) -> dict:
    """Recordings whose truths are drawn (with ``seed``) inside the prior, two of each kind:
    Triskele push-release and actuator step, and the cantilever released from a tip load."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in (1, 2):
        tau = float(np.exp(rng.uniform(*np.log(TAU_DECADE["triskele"]))))
        lengths = np.round(0.032 + rng.uniform(-PRIOR_LENGTH, PRIOR_LENGTH, 3), 6).tolist()
        angle, size = rng.uniform(0, 2 * np.pi), rng.uniform(0.012, 0.025)
        push = [size * np.cos(angle), size * np.sin(angle), float(rng.choice([-1, 1]) * rng.uniform(1e-4, 4e-4))]
        told = _as_recorded(rng, push)
        base = RECORDINGS["triskele_push_release"]
        out[f"triskele_push_release_r{k}"] = dict(
            base,
            description=f"Triskele-bot push-release, truth drawn at random inside the prior (suite seed {seed}), "
            "simulated on a grid 9x finer in space, extrapolated to dt 0 from 5x and 10x in time.",
            rod=_start_tau(rng, tau),
            load=dict(force=np.round(told[:2], 5).tolist() + [0.0], moment=[0.0, 0.0, round(told[2], 6)], release_time=0.0),
            truth=dict(
                base["truth"],
                tau=round(tau, 7),
                lengths=lengths,
                push_force=np.round(push[:2], 6).tolist(),
                push_moment=round(push[2], 7),
                **_camera_truth(rng, seed + 10 * k + 1),
            ),
        )
    for k in (1, 2):
        tau = float(np.exp(rng.uniform(*np.log(TAU_DECADE["triskele"]))))
        lengths = np.round(0.032 + rng.uniform(-PRIOR_LENGTH, PRIOR_LENGTH, 3), 6).tolist()
        move = (rng.choice([-1, 1], 3) * rng.uniform(2e-6, 1e-5, 3)).round(7).tolist()
        base = RECORDINGS["triskele_actuator_step"]
        out[f"triskele_actuator_step_r{k}"] = dict(
            base,
            description=f"Triskele-bot actuator step (bases by {', '.join(f'{m * 1e6:+.2f}' for m in move)} um in 10 ms at "
            f"0.05 s), truth drawn at random inside the prior (suite seed {seed}), simulated 9x finer in space, extrapolated to dt 0 from 5x and 10x in time.",
            rod=_start_tau(rng, tau),
            actuation=dict(base["actuation"], final=move),
            truth=dict(base["truth"], tau=round(tau, 7), lengths=lengths, **_camera_truth(rng, seed + 10 * k + 2)),
        )
    for k in (1, 2):
        tau = float(np.exp(rng.uniform(*np.log(TAU_DECADE["cantilever"]))))
        push = [rng.uniform(-0.2, 0.2), -rng.uniform(1.5, 2.5)]
        told = _as_recorded(rng, push)
        base = RECORDINGS["cantilever_release"]
        out[f"cantilever_release_r{k}"] = dict(
            base,
            description=f"Cantilever released from a tip load, truth drawn at random inside the prior (suite seed {seed}), "
            "simulated 3x finer in space, extrapolated to dt 0 from 50x and 100x in time.",
            rod=_start_tau(rng, tau),
            tip=dict(force=[round(told[0], 4), 0.0, round(told[1], 4)], moment=[0.0, 0.0, 0.0], release_time=0.0),
            truth=dict(
                base["truth"],
                tau=round(tau, 7),
                lengths=round(0.4 + float(rng.uniform(-PRIOR_LENGTH, PRIOR_LENGTH)), 6),
                push_force=np.round(push, 5).tolist(),
                **{k_: v for k_, v in _camera_truth(rng, seed + 10 * k + 3).items() if k_ != "frame_offset"},
                frame_offset=[round(float(rng.uniform(-0.25, -0.15)), 5), round(float(rng.uniform(-0.02, 0.02)), 5)],
            ),
        )
    for spec in out.values():
        solver = spec["solver"]
        spec["truth_solver"] = dict(
            solver, nodes=solver["nodes"] * FINER["nodes"][spec["scene"]], dt=solver["dt"] / FINER["dt"][spec["experiment"]]
        )
    return out


RECORDINGS.update(random_suite())

# A recording made by another code than pcrjax (`independent_rod.py`: finite volumes in space,
# SciPy's error-controlled BDF in time) on a converged grid: the 0.5 m rod of
# scenes/rod_half_metre.toml, a 20 g tip weight cut loose at t = 0, filmed at 1 kHz. The scene's
# length is the tape measure's (1.2 mm short); its damping time is a factor 3 off the truth's.
INDEPENDENT = {
    "cantilever_independent": dict(
        scene="scenes/rod_half_metre.toml",
        experiment="release",
        description="A 0.5 m steel rod hanging sideways under gravity, a 20 g tip weight cut loose at t = 0, tip marker "
        "filmed at 1 kHz; simulated by experiments_data/independent_rod.py (not pcrjax) on a converged grid.",
        frame_rate=1000.0,
        exposure=1e-4,
        seconds=1.0,
        truth=dict(
            tau=2e-3,
            lengths=0.5,
            push_force=[-0.1962, 0.0],
            frame_offset=[-0.18203, 0.01127],
            frame_rotation=-0.0214,
            time_offset=0.00137,
            noise_position=2e-6,
            noise_angle=2e-5,
            missing_fraction=0.02,
            seed=2101,
        ),
        # Richardson's extrapolation of 640 and 1280 edges (the scheme is second order: from 320
        # to 640 and 640 to 1280 edges the tip moved by at most 0.96 and 0.24 um in x, 2.8 and
        # 0.70 urad, a ratio of 4.001): 640 edges alone lie 0.32 um from the limit, a sixth of
        # the camera noise but the same in every frame, which moved a fitted length by 1.9
        # standard errors; the extrapolation's own error is some 1e-4 of that
        grid=dict(nodes=(640, 1280), rtol=1e-9, atol=1e-13, sample_dt=1e-4),
    )
}


def frame_times(spec: dict) -> np.ndarray:
    """The times of every frame of ``spec``'s film (before any goes missing)."""
    return np.arange(int(spec["seconds"] * spec["frame_rate"]) + 1) / spec["frame_rate"]


def film(path: Path, samples, dt: float, t_frames, exposure: float, truth: dict, side: dict):
    """Film the planar motion ``samples`` (T, 3), taken every ``dt`` s, with the camera model at
    ``t_frames`` and ``truth``'s frame, delay, noise and missing frames (seeded), write it to
    ``path`` with the sidecar ``side``, and return it as users will load it."""
    clean = camera.observe(
        jnp.asarray(samples),
        dt,
        jnp.asarray(t_frames),
        exposure,
        jnp.asarray(truth["frame_offset"], jnp.float64),
        jnp.asarray(truth["frame_rotation"], jnp.float64),
        jnp.asarray(truth["time_offset"], jnp.float64),
    )
    rng = np.random.default_rng(truth["seed"])
    noise = rng.standard_normal(clean.shape) * np.array([truth["noise_position"], truth["noise_position"], truth["noise_angle"]])
    keep = rng.random(t_frames.size) >= truth["missing_fraction"]
    keep[0] = True
    write_recording(path, t_frames[keep], np.asarray(clean)[keep] + noise[keep], side)
    return load_recording(path, require_sidecar=True)


def independent_rod(scene, truth: dict, nodes: int):
    """The planar rod of `independent_rod.py` for a rod ``scene`` (its material, gravity and base
    direction) with ``truth``'s length and damping time."""
    from independent_rod import PlanarRod

    rod = scene.legs.rod
    one = lambda a: float(np.asarray(a).ravel()[0])  # noqa: E731  (the scene's one leg)
    direction = np.asarray(scene.legs.base_rotation[0])[:, 2]
    g = np.asarray(scene.gravity) if scene.effects.gravity else np.zeros(3)
    return PlanarRod(
        length=float(truth["lengths"]),
        radius=one(rod.radius),
        youngs_modulus=one(rod.youngs_modulus),
        shear_modulus=one(rod.shear_modulus),
        density=one(rod.density),
        tau=float(truth["tau"]),
        gravity=(float(g[0]), float(g[2])),
        base_angle=float(np.arctan2(direction[2], direction[0])),
        nodes=nodes,
    )


def generate_independent(name: str, spec: dict, out_dir: Path) -> Path:
    """Simulate ``spec`` with `independent_rod.py`, film it with the camera model, write the
    recording and its sidecar (which points at the scene file; nothing of pcrjax's dynamics used)."""
    truth, grid = spec["truth"], spec["grid"]
    scene = pcrjax.load_scene(ROOT / spec["scene"])
    t_frames = frame_times(spec)
    span = spec["seconds"] + truth["time_offset"] + spec["exposure"] + 2 * grid["sample_dt"]
    tips, nfev = [], 0
    for nodes in grid["nodes"]:
        rod = independent_rod(scene, truth, nodes)
        _, tip, n = rod.release(tuple(truth["push_force"]), span, grid["sample_dt"], rtol=grid["rtol"], atol=grid["atol"])
        tips.append(tip)
        nfev += n
    coarse, fine = tips
    print(
        f"{name}: the tip moved by up to {np.max(np.abs(fine - coarse), axis=0).tolist()} (m, m, rad) from {grid['nodes'][0]} edges"
    )
    tip = fine + (fine - coarse) / 3.0  # second order in the edge length
    side = dict(
        _sidecar_head(spec),
        truth=dict(truth),
        provenance=dict(
            generator="experiments_data/generate.py",
            model="experiments_data/independent_rod.py",
            truth_nodes=list(grid["nodes"]),
            truth_extrapolated="Richardson, second order in the edge length",
            truth_rtol=grid["rtol"],
            truth_atol=grid["atol"],
            rhs_evaluations=int(nfev),
        ),
    )
    path = out_dir / f"{name}.csv"
    back = film(path, tip, grid["sample_dt"], t_frames, spec["exposure"], truth, side)
    print(f"{path}: {back.frames} frames, tip swings {np.ptp(back.pose[:, 0]) * 1e3:.3g} mm, {np.ptp(back.pose[:, 2]):.3g} rad")
    return path


CAMERA_TRUTH = ("frame_offset", "frame_rotation", "time_offset")
SENSOR = ("noise_position", "noise_angle", "missing_fraction", "seed")


def _sidecar_head(spec: dict) -> dict:
    """The sidecar's top-level keys of a synthetic recording."""
    head = {k: spec[k] for k in ("scene", "experiment", "frame_rate", "exposure")}
    return dict(head, synthetic=True, description=spec["description"])


def sidecar(name: str, spec: dict) -> dict:
    side = _sidecar_head(spec)
    for table in OVERRIDES:
        if table in spec:
            side[table] = dict(spec[table])
    side["solver"]["duration"] = spec["seconds"] + 0.05
    side["truth"] = dict(spec["truth"])
    side["provenance"] = dict(
        generator="experiments_data/generate.py", pcrjax=pcrjax.__version__ if hasattr(pcrjax, "__version__") else "0.1.0"
    )
    if "truth_solver" in spec:  # the truth simulated on another grid than the fit's
        side["provenance"].update(truth_nodes=spec["truth_solver"]["nodes"], truth_dt=spec["truth_solver"]["dt"])
        side["provenance"]["truth_extrapolated_from_dt"] = [2 * spec["truth_solver"]["dt"], spec["truth_solver"]["dt"]]
    return side


def truth_motion(name: str, spec: dict, out_dir: Path):
    """The planar motion of ``spec``'s truth (T, 3) and its sample interval: simulated with the
    sidecar's solver settings, or on the truth's finer grid and extrapolated to dt 0."""
    side = sidecar(name, spec)
    truth = spec["truth"]
    t_frames = frame_times(spec)
    rec = Recording(
        path=out_dir / f"{name}.csv",
        t=t_frames,
        pose=np.zeros((t_frames.size, 3)),
        scene=spec["scene"],
        experiment=spec["experiment"],
        frame_rate=spec["frame_rate"],
        exposure=spec["exposure"],
        synthetic=True,
        overrides={k: side[k] for k in OVERRIDES if k in side},
        truth=truth,
    )
    if "truth_solver" in spec:
        rec.overrides["solver"] = dict(spec["truth_solver"], duration=side["solver"]["duration"])
    scene = experiment.build_scene(rec)
    params = {k: jnp.asarray(v, jnp.float64) for k, v in truth.items() if k not in SENSOR}
    s = experiment.apply(scene, params)
    traj = pcrjax.simulate(s, progress=True)
    samples, dt = experiment.planar_pose(s, traj), float(s.solver.dt)
    if "truth_solver" in spec:
        coarse = pcrjax.with_solver(s, dt=2 * dt)
        twice = np.asarray(experiment.planar_pose(coarse, pcrjax.simulate(coarse, progress=True)))
        fine = np.asarray(samples)[::2][: twice.shape[0]]
        print(
            f"{name}: the truth moved by up to {np.max(np.abs(fine - twice), axis=0).tolist()} (m, m, rad) from dt {2 * dt:.3g} s"
        )
        samples, dt = fine + (fine - twice[: fine.shape[0]]) / 3.0, 2 * dt
    return np.asarray(samples), dt


def _film_spec(path: Path, samples, dt: float, spec: dict, side: dict):
    back = film(path, samples, dt, frame_times(spec), spec["exposure"], spec["truth"], side)
    print(
        f"{path}: {back.frames} frames ({100 * back.missing_fraction():.1f} % missing), motion "
        f"{np.ptp(back.pose[:, 0]) * 1e6:.3g} x {np.ptp(back.pose[:, 1]) * 1e6:.3g} um, {np.ptp(back.pose[:, 2]) * 1e6:.3g} urad"
    )
    return path


def generate(name: str, spec: dict, out_dir: Path) -> Path:
    samples, dt = truth_motion(name, spec, out_dir)
    return _film_spec(out_dir / f"{name}.csv", samples, dt, spec, sidecar(name, spec))


def noise_draws(name: str, spec: dict, out_dir: Path, draws: int, first_seed: int) -> list[Path]:
    """``name``'s truth filmed ``draws`` times, the noise and missing frames drawn with seeds
    ``first_seed``, ``first_seed + 1``, ... (each in its sidecar): ``<name>_draw_<k>.csv``. A
    fit of each says how far the noise alone moves the answer, against its reported errors."""
    samples, dt = truth_motion(name, spec, out_dir)
    out = []
    for k in range(draws):
        drawn = dict(spec, truth=dict(spec["truth"], seed=first_seed + k))
        drawn["description"] = f"{spec['description']} Noise draw {k} (seed {first_seed + k})."
        out.append(_film_spec(out_dir / f"{name}_draw_{k:02d}.csv", samples, dt, drawn, sidecar(name, drawn)))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    everything = [*RECORDINGS, *INDEPENDENT]
    p.add_argument("names", nargs="*", help=f"recordings to generate (default: all of {', '.join(everything)})")
    p.add_argument("--out", help="output folder (default: experiments_data/; --draws needs one)")
    p.add_argument(
        "--draws",
        type=int,
        default=0,
        help="film each named recording's truth this many times with new noise (NAME_draw_K.csv) instead",
    )
    p.add_argument("--first-seed", type=int, default=5000, help="the first draw's noise seed (default 5000)")
    args = p.parse_args(argv)
    if args.draws:
        if args.draws < 0:
            p.error("--draws must be positive")
        if not args.names or any(n not in RECORDINGS for n in args.names):
            p.error(f"--draws: name recordings of {', '.join(RECORDINGS)}")
        if args.out is None:
            p.error("--draws: give --out (a folder beside the shipped recordings)")
        for name in args.names:
            noise_draws(name, RECORDINGS[name], Path(args.out), args.draws, args.first_seed)
        return
    out = ROOT if args.out is None else Path(args.out)
    for name in args.names or everything:
        if name in INDEPENDENT:
            generate_independent(name, INDEPENDENT[name], out)
        else:
            generate(name, RECORDINGS[name], out)


if __name__ == "__main__":
    main()
