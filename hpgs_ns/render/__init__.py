"""Rendering beside splatfacto's own: per-(view, Gaussian) pair renders for FisherRF, and camera conventions."""
