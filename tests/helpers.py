"""Assertions several test files share."""

import math

from hil.validate.core import failing_verifications


def assert_rows_ok(rows):
    """Every verification row agrees (a failing one is a bug), with finite numbers; the
    message lists the failures.  Reproductions and predictions may disagree with their seed:
    tests/test_validate_rows.py checks those."""
    assert rows, "experiment returned no rows"
    bad = failing_verifications(rows)
    assert not bad, "\n".join(f"{r.experiment}: model {r.model} vs {r.paper} {r.unit} "
                              f"({r.reference}, {r.tolerance})" for r in bad)
    for r in rows:
        assert isinstance(r.ok, bool) and math.isfinite(r.model) and math.isfinite(r.paper)
