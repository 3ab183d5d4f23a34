"""Parallel continuum robots as PyTrees: legs, platform, actuation and loads.

A leg is a rod from the core, clamped at a base that its actuator moves and clamped to the
platform at ``attachment`` (platform frame) with the fixed relative rotation ``clamp`` (the rod's
tip frame in the platform frame). Two actuation kinds:

* ``"length"`` (Stewart-Gough): the rod is fed through a fixed hole; the actuator value is the
  free length $L_i(t)$ above the hole. The spatial grid stretches with the length
  ($s_j = j L_i(t)/N$) and the BDF-alpha history stays attached to the node index $j$; the
  material leaves the hole at speed $\\dot L_i$ along its axis (the base velocity). The history
  thus ignores the convective term $\\dot L\\,\\partial_s$ of material moving between nodes, an
  error of order $\\dot L/L$ times the strain rate: zero at constant length and small for the
  slow leg motions of this robot.
* ``"prismatic"`` (Triskele): the rod's base slides along its own tangent $d_i$ by the actuator
  value $q_i(t)$; the rod length is fixed.

Both kinds give the base material a velocity $\\dot a_i$ along the local tangent, with
$\\dot a_i$ from BDF-alpha on the actuator values (zero while they are constant).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .platform import Platform
from .rod import Effects, Rod
from .signals import Actuation, PlatformLoad

ACTUATION_KINDS = ("length", "prismatic")


class Legs(eqx.Module):
    """Per-leg data, stacked along a leading axis of size n (every rod leaf has shape (n, ...))."""

    rod: Rod
    base_position: jnp.ndarray  # (n, 3) hole centre (length) or actuator origin Q_i (prismatic)
    base_rotation: jnp.ndarray  # (n, 3, 3) rod frame at the base; column 2 is the tangent d_i
    attachment: jnp.ndarray  # (n, 3) platform frame
    clamp: jnp.ndarray  # (n, 3, 3) rod tip frame in the platform frame
    kind: str = eqx.field(static=True, default="length")

    @property
    def count(self) -> int:
        return self.base_position.shape[0]

    def lengths(self, a):
        """Free rod lengths for actuator values ``a``."""
        return a if self.kind == "length" else self.rod.length

    def base_positions(self, a):
        if self.kind == "length":
            return self.base_position
        return self.base_position + a[:, None] * self.base_rotation[:, :, 2]


class ParallelScene(eqx.Module):
    """A parallel continuum robot scene (robot = "stewart_gough" | "triskele")."""

    legs: Legs
    platform: Platform
    reference_position: jnp.ndarray  # (3,) start of the equilibrium search; planar: z of the bearing
    reference_rotation: jnp.ndarray  # (3, 3)
    actuation: Actuation
    load: PlatformLoad
    gravity: jnp.ndarray
    effects: Effects
    solver: "Solver"  # noqa: F821  (scene.Solver)
    name: str = eqx.field(static=True, default="robot")
    robot: str = eqx.field(static=True, default="stewart_gough")
