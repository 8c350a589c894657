"""Seed experiments that a plant alone can run, each compared with its paper or an
independent reference (``hil validate``)."""

from hil.validate.core import REGISTRY, Result, experiment, run_all

__all__ = ["REGISTRY", "Result", "experiment", "run_all"]
