"""Numerics: BDF-alpha in time, RK4/Euler along the rod, multiple shooting, Newton with implicit gradients."""
