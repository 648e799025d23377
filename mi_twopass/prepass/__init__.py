"""Prepasses: the radiosity solution over scene patches (and, elsewhere, per-integrator structures)."""
from .radiosity import RadiositySolution, solve_radiosity

__all__ = ["RadiositySolution", "solve_radiosity"]
