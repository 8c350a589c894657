"""Importing this package registers every experiment (one module per topic)."""

from hil.validate.experiments import (  # noqa: F401
    cogging,
    electrical,
    friction,
    mechanics,
    moves,
    seed000_loops,
)
