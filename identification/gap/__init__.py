"""Sim-to-real gap diagnosis (METHOD.md §6): locate, attribute, quantify — honestly."""

from identification.gap.data import TouchData
from identification.gap.diagnose import Options, diagnose

__all__ = ["Options", "TouchData", "diagnose"]
