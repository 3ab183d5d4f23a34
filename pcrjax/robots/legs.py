"""Legs: rods whose base an actuator holds or moves, stacked along a leading axis.

Every robot is a set of legs and an end condition (`ends.py`); the cantilever is one fixed leg
with a free tip. Three kinds of base, one per robot family:

* ``"fixed"`` (cantilever): the clamp never moves; the robot has no actuators.
* ``"length"`` (Stewart-Gough): the rod is fed through a fixed hole; the actuator value is the
  free length $L_i(t)$ above the hole. The spatial grid stretches with the length
  ($s_j = j L_i(t)/N$) and the BDF-alpha history stays attached to the node index $j$; the
  material leaves the hole at speed $\\dot L_i$ along its axis (the base velocity). The history
  thus ignores the convective term $\\dot L\\,\\partial_s$ of material moving between nodes, an
  error of order $\\dot L/L$ times the strain rate: zero at constant length and small for the
  slow leg motions of this robot.
* ``"prismatic"`` (Triskele): the rod's base slides along its own tangent $d_i$ by the actuator
  value $q_i(t)$; the rod length is fixed.

Moving bases give the base material a velocity $\\dot a_i$ along the local tangent, with
$\\dot a_i$ from BDF-alpha on the actuator values (zero while they are constant).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..physics.rod import Rod

BASE_KINDS = ("fixed", "length", "prismatic")


class Legs(eqx.Module):
    """Per-leg data, stacked along a leading axis of size n (every rod leaf has shape (n, ...))."""

    rod: Rod
    base_position: jnp.ndarray  # (n, 3) clamp, hole centre (length) or actuator origin Q_i (prismatic)
    base_rotation: jnp.ndarray  # (n, 3, 3) rod frame at the base; column 2 is the tangent d_i
    kind: str = eqx.field(static=True, default="fixed")

    def __check_init__(self):
        if self.kind not in BASE_KINDS:
            raise ValueError(f"leg kind must be one of {BASE_KINDS}, got {self.kind!r}")

    @property
    def count(self) -> int:
        return self.base_position.shape[0]

    @property
    def actuated(self) -> bool:
        return self.kind != "fixed"

    def first_rod(self) -> Rod:
        return jax.tree.map(lambda a: a[0], self.rod)

    def lengths(self, a):
        """Free rod lengths (n,) for actuator values ``a`` (None for fixed legs)."""
        return a if self.kind == "length" else self.rod.length

    def base_positions(self, a):
        if self.kind == "prismatic":
            return self.base_position + a[:, None] * self.base_rotation[:, :, 2]
        return self.base_position

    def base_states(self, a, adot, inertia: bool):
        """(n, dim) rod states at s = 0 with zero wrench: clamp position and frame, and in dynamics
        the base material's velocity ``adot`` along the local tangent (zero for fixed legs)."""
        n = self.count
        parts = [self.base_positions(a), self.base_rotation.reshape(n, 9), jnp.zeros((n, 6), self.base_rotation.dtype)]
        if inertia:
            z = jnp.zeros((n,), self.base_rotation.dtype)
            speed = adot if self.actuated and adot is not None else z
            parts += [jnp.stack([z, z, speed], axis=1), jnp.zeros((n, 3), z.dtype)]
        return jnp.concatenate(parts, axis=1)
