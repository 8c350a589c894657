"""Assertions several test files share."""

import math


def assert_rows_ok(rows):
    """Every validation row is ok, with finite numbers; the message lists the failures."""
    assert rows, "experiment returned no rows"
    bad = [r for r in rows if not r.ok]
    assert not bad, "\n".join(f"{r.experiment}: model {r.model} vs {r.paper} {r.unit} "
                              f"({r.reference}, {r.tolerance})" for r in bad)
    for r in rows:
        assert isinstance(r.ok, bool) and math.isfinite(r.model) and math.isfinite(r.paper)
