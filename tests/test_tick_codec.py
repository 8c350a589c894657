"""The group codec's precomputed checks (issue 12 part 6: the tick's decode and encode of
a machine of several axes) against the per-element definition they replace.

:class:`io_adapters.codec._Check` must say what :func:`io_adapters.codec._valid` says for
every array, and a group message must encode to the same bytes (or fail with the same
error) as converting every field first (:func:`io_adapters.codec._converted`), for
values hypothesis draws: exact ints and floats, ints out of range, bools, numpy scalars,
NaN, strings, None.
"""

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from io_adapters.base import FrameError
from io_adapters.codec import (
    GROUP_SCHEMAS,
    VERSION_GROUP,
    _Check,
    _converted,
    _valid,
)
from io_adapters.messages import FeedbackGroup, SetpointGroup, message_pair

_VALUE = st.one_of(
    st.integers(-2**64, 2**64), st.integers(0, 0xFFFF), st.floats(allow_nan=True),
    st.booleans(), st.just(None), st.text(max_size=2),
    st.floats(-1e9, 1e9).map(np.float64), st.integers(0, 2**31).map(np.int64))


def _reference(schema, group, session, frame) -> bytes:
    """GroupSchema.encode as it was: every field converted and checked."""
    name = schema.group_type.__name__
    common = _converted(schema.common, schema.get_common(group), name)
    axes = tuple(_converted(schema.axis, schema.get_axis(rec), f"{name}.axes[{i}]")
                 for i, rec in enumerate(group.axes))
    return msgpack.packb((VERSION_GROUP, schema.kind, session, frame) + common + (axes,))


def _outcome(encode, *args):
    try:
        return encode(*args)
    except FrameError as e:
        return f"FrameError: {e}"


@pytest.mark.parametrize("group_type", [SetpointGroup, FeedbackGroup])
@given(data=st.data())
def test_check_says_what_valid_says(group_type, data):
    schema = GROUP_SCHEMAS[group_type]
    for fields in (schema.header + schema.common, schema.axis):
        values = tuple(data.draw(st.one_of(
            _VALUE, st.integers(f.lo, f.hi) if f.type is int else st.floats()))
            for f in fields)
        assert _Check(fields)(values) == _valid(fields, values)


@pytest.mark.parametrize("setpoint", [True, False])
@given(data=st.data())
def test_group_encodes_as_converting_every_field(setpoint, data):
    sp, fb = message_pair(2)
    group = sp if setpoint else fb
    schema = GROUP_SCHEMAS[type(group)]
    for rec, names in ((group, schema.common_names),
                       *((a, schema.axis_names) for a in group.axes)):
        for name in names:
            if data.draw(st.booleans()):
                setattr(rec, name, data.draw(_VALUE))
    session, frame = 123456, 7
    expected = _outcome(_reference, schema, group, session, frame)
    got = _outcome(schema.encode, group, session, frame)
    assert got == expected
