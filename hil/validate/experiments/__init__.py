"""Importing this package registers every experiment (one module per topic); the order
here is the order of ``hil validate``'s table."""

from hil.validate.experiments import (  # noqa: F401, I001  (table order, not sorted)
    cogging,
    electrical,
    seed001_envelope,
    friction,
    mechanics,
    configuration,
    moves,
    seed002_disturbance,
    seed000_loops,
)
