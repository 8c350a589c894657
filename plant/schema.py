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
    zero: str | None = None,
    choices: tuple[str, ...] | None = None,
    only: str | None = None,
) -> Any:
    """Declare one config key.

    Every number key has a physical range: the values a real axis can have, with a margin,
    so that a typing error (a mass of 1e300, a PWM frequency of 1 MHz) is refused with
    the range rather than run.  A list of numbers has the range for each element.

    Args:
        unit: SI unit of the value ("1" for dimensionless, "-" for text/flags).
        doc: one sentence saying what the key means.
        default: value when the key is absent; REQUIRED makes it mandatory.
        gt, ge, le: numeric bounds (exclusive lower, inclusive lower, inclusive upper).
        zero: what a value of 0 means where 0 is allowed outside ``gt``/``ge`` (e.g.
            "automatic", "none", "not used"); None: 0 is held to the bounds like any value.
        choices: allowed values of a text key.
        only: name of the condition under which the key belongs (documentation
            and the "key not used by this model" check), e.g. "kind=linear".
    """
    meta = {"unit": unit, "doc": doc, "gt": gt, "ge": ge, "le": le, "zero": zero,
            "choices": choices, "only": only}
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return field(default_factory=lambda: value, metadata=meta)
    return field(default=default, metadata=meta)


def is_required(f: Field) -> bool:
    """True when the field has neither a default nor a default factory."""
    return f.default is MISSING and f.default_factory is MISSING


def in_range(meta: dict, value: float) -> bool:
    """True when ``value`` is within the bounds declared in ``meta`` (a field's metadata)."""
    if value == 0.0 and meta.get("zero"):
        return True
    return ((meta.get("gt") is None or value > meta["gt"])
            and (meta.get("ge") is None or value >= meta["ge"])
            and (meta.get("le") is None or value <= meta["le"]))


def range_text(meta: dict) -> str:
    """The bounds declared in ``meta`` in words, without the unit: '> 0 and <= 1e+06',
    '0 (automatic) or >= 1000 and <= 1e+13', '' when unbounded."""
    parts = []
    if meta.get("gt") is not None:
        parts.append(f"> {meta['gt']:g}")
    if meta.get("ge") is not None:
        parts.append(f">= {meta['ge']:g}")
    if meta.get("le") is not None:
        parts.append(f"<= {meta['le']:g}")
    text = " and ".join(parts)
    if meta.get("zero") and text:
        text = f"0 ({meta['zero']}) or {text}"
    return text


def describe(section_cls: type) -> list[dict]:
    """Rows describing every key of a section: name, unit, range, doc, default."""
    rows = []
    for f in fields(section_cls):
        m = f.metadata
        bounds = [range_text(m)] if range_text(m) else []
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
