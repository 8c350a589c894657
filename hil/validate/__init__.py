"""Seed experiments that a plant alone can run, each row a verification, reproduction or
prediction with its verdict (``hil validate``)."""

from hil.validate.core import (
    REGISTRY,
    Kind,
    Result,
    SeedRef,
    experiment,
    failing_verifications,
    run_all,
)

__all__ = ["REGISTRY", "Kind", "Result", "SeedRef", "experiment", "failing_verifications",
           "run_all"]
