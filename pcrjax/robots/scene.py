"""The scene: one PyTree for every robot (legs, end condition, actuation, effects, solver).

Structure (effect switches, node counts, integrator, number of steps, leg and end kinds) is
static; every number you may differentiate, fit or `vmap` over (lengths, moduli, density,
damping, masses, loads, actuator values, dt, alpha) is a float64 leaf.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..numerics import solver as solver_mod
from ..physics.rod import Effects
from .ends import AbstractEnd
from .legs import Legs
from .signals import Actuation


class Scene(eqx.Module):
    """A robot: ``legs`` (n rods), the ``end`` their tips meet (`FreeTip` or `RigidPlatform`),
    the ``actuation`` of the legs' bases over time (None: fixed bases), gravity (m/s^2),
    effect switches and solver settings. ``robot`` names the scene file's kind (for outputs)."""

    legs: Legs
    end: AbstractEnd
    actuation: Actuation | None
    gravity: jnp.ndarray
    effects: Effects
    solver: solver_mod.Solver
    name: str = eqx.field(static=True, default="scene")
    robot: str = eqx.field(static=True, default="rod")

    def actuator_values(self, t):
        """Actuator values (n_act,) at time ``t``; no entries for fixed legs."""
        if self.actuation is None:
            return jnp.zeros((0,), self.gravity.dtype)
        return self.actuation(t)

    @property
    def load(self):
        """The load on the end (platform centre or free tip)."""
        return self.end.load

    def structure_result(self):
        """`results.STALE_STRUCTURE` if the scene's numbers outgrew its compiled structure."""
        lengths = self.legs.lengths(self.actuator_values(jnp.zeros((), self.gravity.dtype)))
        return solver_mod.structure_result(self.solver, self.legs.rod, lengths)
