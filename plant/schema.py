"""Declaring config sections: a field with its unit, its range and its meaning.

Every key of a machine file is a dataclass field declared with :func:`key`.
The loader in :mod:`plant.config` reads the declarations, so the schema, the
checks and the documentation (``hil config-keys``) come from one place.
"""

from dataclasses import MISSING, Field, field, fields
from typing import Any

REQUIRED = MISSING


def key(
    unit: str,
    doc: str,
    default: Any = REQUIRED,
    *,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
    choices: tuple[str, ...] | None = None,
    only: str | None = None,
) -> Any:
    """Declare one config key.

    Args:
        unit: SI unit of the value ("1" for dimensionless, "-" for text/flags).
        doc: one sentence saying what the key means.
        default: value when the key is absent; REQUIRED makes it mandatory.
        gt, ge, le: numeric bounds (exclusive lower, inclusive lower, inclusive upper).
        choices: allowed values of a text key.
        only: name of the condition under which the key belongs (documentation
            and the "key not used by this model" check), e.g. "kind=linear".
    """
    meta = {"unit": unit, "doc": doc, "gt": gt, "ge": ge, "le": le,
            "choices": choices, "only": only}
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return field(default_factory=lambda: value, metadata=meta)
    return field(default=default, metadata=meta)


def is_required(f: Field) -> bool:
    """True when the field has neither a default nor a default factory."""
    return f.default is MISSING and f.default_factory is MISSING


def describe(section_cls: type) -> list[dict]:
    """Rows describing every key of a section: name, unit, range, doc, default."""
    rows = []
    for f in fields(section_cls):
        m = f.metadata
        bounds = []
        if m.get("gt") is not None:
            bounds.append(f"> {m['gt']:g}")
        if m.get("ge") is not None:
            bounds.append(f">= {m['ge']:g}")
        if m.get("le") is not None:
            bounds.append(f"<= {m['le']:g}")
        if m.get("choices"):
            bounds.append(" | ".join(m["choices"]))
        if is_required(f):
            default = "required"
        elif f.default_factory is not MISSING:
            default = repr(list(f.default_factory()))
        elif f.default is None:  # the loader derives it from other keys (the doc says how)
            default = "derived"
        else:
            default = repr(f.default)
        rows.append({"key": f.name, "unit": m.get("unit", ""), "range": ", ".join(bounds),
                     "default": default, "only": m.get("only") or "", "doc": m.get("doc", "")})
    return rows
