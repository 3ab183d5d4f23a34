"""Physics: rotations, the Cosserat rod and the rigid platform (no discretisation, no robots)."""
