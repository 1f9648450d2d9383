"""Tests of the simulator: scene ray-caster, sensor model, simulated LMS100 device server."""
