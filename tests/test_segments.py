"""Multiple shooting with equal segments integrates them side by side (one scan over N/M steps
with the segments as extra legs). Each segment must be exactly the plain integration of that
piece of rod from its own start state: nodes, RK4 stage points, arrivals and forward
sensitivities, against the single-segment path run segment by segment."""

import jax.numpy as jnp
import numpy as np

import pcrjax
from pcrjax import simulation
from pcrjax.bench.cases import cases
from pcrjax.numerics import shooting, spatial
from pcrjax.robots import dynamics


def _piece(rods: spatial.Rods, a: int, b: int) -> spatial.Rods:
    """The rods from node a to node b (steps a..b-1)."""
    return spatial.Rods(
        rods.history[:, a : b + 1], rods.stage_history[:, a:b], rods.k, rods.ds, rods.effects, rods.integrator, rods.unroll
    )


def test_equal_segments_side_by_side_are_the_pieces_integrated_one_by_one():
    case = next(c for c in cases("cantilever") if c.label == "till")
    scene = pcrjax.with_solver(case.scene, nodes=12, dt=2e-3, duration=4e-3, segments=4)
    _, state = simulation._initial(scene)  # at rest the BDF-alpha histories hold -c0 times the strains: not zero
    prob = dynamics._problem(scene, state, dynamics._coefficients(scene, state), state.a1, scene.solver.dt)
    lay, rods = prob.layout, prob.rods
    assert lay.segments == 4 and lay.starts == (3, 6, 9)
    xl = prob.split(state.unknowns[0])[1] + 1e-3  # off the solution: the junctions do not close
    restarts = shooting._restarts(lay, xl, prob.leg_R_ref, prob.sc)
    y0 = shooting._starts(prob.y0, xl, prob.sc)
    nodes, arrivals, stages = spatial.integrate(y0, rods, lay.starts, restarts, return_stages=True)

    bounds = [0, *lay.starts, 12]
    starts = [y0] + [restarts[:, k] for k in range(3)]
    for k in range(4):
        a, b = bounds[k], bounds[k + 1]
        ref_nodes, _, ref_stages = spatial.integrate(starts[k], _piece(rods, a, b), return_stages=True)
        scale = np.abs(np.asarray(ref_nodes)).max(axis=(0, 1)) + 1e-30
        np.testing.assert_allclose(np.asarray(nodes[:, a:b]) / scale, np.asarray(ref_nodes[:, :-1]) / scale, rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.asarray(stages[:, a:b]), np.asarray(ref_stages), rtol=1e-12, atol=1e-13 * scale.max())
        end = arrivals[:, k] if k < 3 else nodes[:, -1]
        np.testing.assert_allclose(np.asarray(end) / scale, np.asarray(ref_nodes[:, -1]) / scale, rtol=0, atol=1e-13)

    # forward sensitivities: the last node's and the arrivals' tangents, piece by piece
    C = 3
    Y0 = jnp.asarray(np.random.default_rng(0).standard_normal((1, C, y0.shape[1]))) * 1e-3
    RT = jnp.asarray(np.random.default_rng(1).standard_normal((1, 3, C, y0.shape[1]))) * 1e-3
    y_last, Y_last, arr, arr_t = spatial.integrate_tangents(y0, Y0, rods, lay.starts, restarts, RT)
    tangent_starts = [Y0] + [RT[:, k] for k in range(3)]
    for k in range(4):
        a, b = bounds[k], bounds[k + 1]
        ref_y, ref_Y, _, _ = spatial.integrate_tangents(starts[k], tangent_starts[k], _piece(rods, a, b))
        got_y, got_Y = (arr[:, k], arr_t[:, k]) if k < 3 else (y_last, Y_last)
        np.testing.assert_allclose(np.asarray(got_y), np.asarray(ref_y), rtol=1e-12, atol=1e-14 * np.abs(ref_y).max())
        np.testing.assert_allclose(np.asarray(got_Y), np.asarray(ref_Y), rtol=1e-10, atol=1e-12 * np.abs(ref_Y).max())


def test_automatic_segments_are_equal_and_keep_the_conditioning():
    """The automatic split gives equal segments (a divisor of the internal grid's steps), two at
    least for a single rod, never fewer than the conditioning asks (lambda l <= 6 per segment)."""
    from pcrjax.numerics.shooting import SEGMENT_CONDITIONING
    from pcrjax.numerics.solver import _divisor_at_least, auto_segments, boundary_layer_rate

    assert [_divisor_at_least(40, m) for m in (1, 2, 3, 6, 7, 9, 21, 41)] == [1, 2, 4, 8, 8, 10, 40, 40]
    # (grid steps, segments the conditioning needs) -> segments: two at least, equal where that
    # costs at most twice the need, else the need unequal
    cases_ = {(40, 1): 2, (20, 3): 4, (5, 1): 1, (3, 1): 1, (7, 2): 2, (50, 7): 10, (49, 5): 7, (47, 5): 5, (150, 1): 2}
    assert {k: auto_segments(*k) for k in cases_} == cases_
    # several legs: only what the conditioning needs, equal where it can be
    assert [auto_segments(50, 1, 3), auto_segments(20, 3, 6), auto_segments(47, 5, 3)] == [1, 4, 5]
    case = next(c for c in cases("cantilever") if c.label == "thesis")
    rod = case.scene.legs.rod
    for nodes, dt in ((20, 1e-3), (21, 1e-4), (40, 1e-5), (50, 2e-5)):
        s = pcrjax.with_solver(case.scene, nodes=nodes, dt=dt).solver
        c0 = (1.5 - 0.4) / (dt * (1.0 - 0.4))  # BDF-alpha's c0 = (1.5 + alpha) / (dt (1 + alpha)), alpha -0.4
        lam = float(boundary_layer_rate(rod.radius[0], rod.youngs_modulus[0], rod.shear_modulus[0], rod.density[0], c0))
        steps = s.nodes * s.refine
        assert steps % s.segments == 0 and s.segments >= 2, (nodes, dt, s)
        assert lam * float(rod.length[0]) / s.segments <= SEGMENT_CONDITIONING, (nodes, dt, s)


def test_the_motion_does_not_depend_on_the_shooting_segments():
    """Multiple shooting is a way of solving the discrete equations, not a part of them: the
    released thesis cantilever (N 10, dt 2 ms, 10 steps) shot in 2 equal segments (side by
    side), 4 unequal ones (starts at nodes 2, 5, 8) and 5 equal ones has the same node positions
    to the Newton tolerance. RK4 drifts off the rotations at O(ds^4) while a segment's start
    rotation is exact, so without `spatial._on_rotations` every segment start reset that drift
    and the tip moved 1.3e-7 m from 2 to 4 segments in the first step, 6.7e-7 m over 0.2 s."""
    base = pcrjax.with_solver(pcrjax.load_scene("cantilever"), nodes=10, dt=2e-3, duration=0.02)
    runs = {}
    for m in (2, 4, 5):
        scene = pcrjax.with_solver(base, segments=m)
        assert scene.solver.segments == m and scene.solver.grid_nodes == 10
        runs[m] = np.asarray(simulation.simulate(scene).positions)
    for m in (4, 5):
        gap = np.max(np.abs(runs[m] - runs[2]))
        print(f"{m} segments against 2: node positions within {gap:.2e} m")
        assert gap < 1e-10, (m, gap)
