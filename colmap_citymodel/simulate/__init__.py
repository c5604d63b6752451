"""Simulated flights with known truth, mapped by COLMAP: scene, flight, observations, mapping,
sequences."""
