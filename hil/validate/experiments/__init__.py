"""Importing this package registers every experiment (one module per topic)."""

from hil.validate.experiments import cogging, electrical, friction, mechanics  # noqa: F401
