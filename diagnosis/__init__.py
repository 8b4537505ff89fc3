"""Missing-physics diagnosis: locate the mismatch, name the physics, model it."""
