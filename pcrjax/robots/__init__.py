"""Robots: legs, their end condition (free tip or rigid platform), actuation, and the one assembly that solves them."""
