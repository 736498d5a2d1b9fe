"""Numerics layer: random linear systems, the EnKF, modeling, synthesis, exact analysis, Monte Carlo.

Plain numpy/scipy/cvxpy functions and small dataclasses; nothing here imports Hydra, pandas,
Rerun or matplotlib, touches the file system or uses a global random state.
"""
from .analysis import empirical_rate, ms_rate, second_moments
from .synthesis import SynthesisResult, synthesize
from .systems import AffineRandomSystem, MomentModel

__all__ = ["AffineRandomSystem", "MomentModel", "SynthesisResult", "empirical_rate", "ms_rate", "second_moments",
           "synthesize"]
