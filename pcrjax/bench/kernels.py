"""Kernels per node step: what XLA:CPU runs for one RK4 (or Euler) step along a rod.

XLA:CPU's runtime pays a fixed cost per kernel (per fusion, copy, custom call...), so the time of
a scan over nodes is about (kernels in its body) x (cost per kernel) x (nodes). This module
compiles one leg's dynamic integration for a scene and counts the instructions of the scan's
loop body that launch work (parameters, tuples and their elements, constants and bitcasts do not).
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp

_FREE = {"parameter", "get-tuple-element", "tuple", "constant", "bitcast"}
_OP = re.compile(r"^\s*(?:ROOT\s+)?[%\w.\-]+\s*=\s*\S+(?:\[[^\]]*\])?(?:\{[^}]*\})?\s+([\w\-]+)\(")


def computations(hlo: str) -> dict[str, list[str]]:
    """Instruction opcodes of each computation of an HLO module text."""
    comps: dict[str, list[str]] = {}
    name = None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)  # computations start unindented
        if head:
            name = head.group(1)
            comps[name] = []
            continue
        if line.strip() == "}":
            name = None
            continue
        m = _OP.match(line)
        if name is not None and m:
            comps[name].append(m.group(1))
    return comps


def loop_body_kernels(hlo: str) -> int:
    """Kernels of the innermost while loop's body (the one that contains no loop itself)."""
    comps = computations(hlo)
    bodies = re.findall(r"while\(.*?body=%?([\w.\-]+)", hlo)
    counts = [sum(op not in _FREE for op in comps.get(b, [])) for b in bodies if "while" not in comps.get(b, [])]
    return min(counts) if counts else 0


def legs_integration(scene, xl):
    """The legs' integration (the bulk of a dynamic step's residual) of ``scene`` at the scaled
    unknowns ``xl`` (`unknowns_shape`), from rest histories and unit segment rotations."""
    from ..numerics import bdf_alpha
    from ..robots import assembly

    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    lay = assembly.layout(scene, True)
    n = scene.legs.count
    a = scene.actuator_values(jnp.zeros(()))
    R_ref = jnp.broadcast_to(jnp.eye(3), (n, lay.segments - 1, 3, 3))
    prob = assembly.Problem(scene, True, a, jnp.zeros_like(a), scene.gravity, assembly.zero_histories(scene), R_ref, co.c0, None)
    return prob.legs(xl, all_nodes=False)[1]


def unknowns_shape(scene) -> tuple[int, int]:
    """(legs, unknowns per leg) of ``scene``'s dynamic step."""
    from ..robots import assembly

    return scene.legs.count, assembly.layout(scene, True).size


def node_step_kernels(scene) -> int:
    """Kernels per node step of the legs' integration in a dynamic step's residual of ``scene``
    (the spatial scan's loop body; one scan serves every leg)."""
    hlo = jax.jit(lambda xl: legs_integration(scene, xl)).lower(jnp.zeros(unknowns_shape(scene))).compile().as_text()
    return loop_body_kernels(hlo)
