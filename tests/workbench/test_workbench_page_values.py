"""Every value the page sends is checked before viser applies it.

viser casts a browser's value to the widget's type in its event loop: ``int(nan)`` raised there ("Task exception
was never retrieved" in the terminal, nothing in the page) and ``int(14551.5)`` became 14551 without a word. A
crafted client (a local websocket client with the token) sends such values to the Port box of the live source,
the connection *Send to vehicle* uses; then every number the page offers gets each kind of bad value: each is
refused with a message in the page, the widget keeps the server's value, and nothing reaches the terminal.
"""

from __future__ import annotations

import asyncio
import math
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import page_socket

pytest.importorskip("viser")

PORT_LABEL = "Port (UDP/TCP)"


def _send(wb, uuid, values, wait_for) -> list[str]:
    """Send ``{"value": v}`` for each of ``values`` to the widget ``uuid`` as a browser's websocket does, and return
    the page's message after each (``wait_for(message)`` says the answer came)."""
    import msgspec
    from viser import _messages

    said = []

    async def go():
        async with page_socket(wb.port, token=wb.token) as ws:
            for value in values:
                wb.ctrl.say("-")
                message = _messages.GuiUpdateMessage(uuid, {"value": value})
                await ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))
                end = time.monotonic() + 5
                while not wait_for(wb.ctrl.message) and time.monotonic() < end:
                    await asyncio.sleep(0.02)
                said.append(wb.ctrl.message)

    asyncio.run(asyncio.wait_for(go(), 120))
    return said


BAD_PORTS = [float("nan"), float("inf"), float("-inf"), [14550, 1], 14551.5, "14550", True, 80, 70000]


def test_a_bad_port_from_the_page_is_a_message_not_a_traceback(bench, capfd, caplog):
    import gc

    wb = bench(store=False)
    port = wb.panels.live_port
    said = _send(wb, port._impl.uuid, BAD_PORTS, lambda m: m != "-")
    gc.collect()  # an exception left in a task is reported when the task is collected
    time.sleep(0.3)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Task exception" not in err
    assert not [r for r in caplog.records if r.exc_info or "exception" in r.getMessage()]  # asyncio's log
    for value, message in zip(BAD_PORTS, said):
        assert message.startswith("**Error:**") and PORT_LABEL in message and "refused" in message, (value, message)
    assert "is not a whole number" in said[BAD_PORTS.index(14551.5)]
    assert "is not a finite number" in said[0] and "is not a number" in said[3]
    assert port.value == 14550  # never truncated to 14551, never NaN
    # a good port still goes through
    said = _send(wb, port._impl.uuid, [14560], lambda m: port.value == 14560)
    assert port.value == 14560 and said[0] == "-"


def _numbers(wb):
    """Every number widget the page offers (slider or number box), with its rule: ``(handle, lo, hi, integral)``."""
    from magcal_workbench import viser_adapter

    handles = wb.server.gui._gui_input_handle_from_uuid.values()
    out = []
    for handle in handles:
        if viser_adapter.widget_kind(handle) == "number":
            kind, rule = wb.values._rules[id(handle)]
            assert kind == "number", handle.label  # every number widget is registered with its range
            out.append((handle, *rule))
    return out


def _bad_values(lo, hi, integral) -> list:
    bad = [float("nan"), float("inf"), -float("inf"), [1.0], "1", None, {"a": 1}, False]
    if lo is not None:
        bad.append(lo - 1.0)
    if hi is not None:
        bad.append(hi + 1.0)
    if integral:
        bad.append((lo if lo is not None else 0) + 0.5)
    return bad


def test_every_number_the_page_offers_refuses_each_bad_value_before_viser(bench):
    """The screen on viser's update handler (:meth:`PageValues.screen`) for every number widget: a bad value's
    message is dropped (viser never casts it), the widget keeps its value, and the page says why."""
    from viser import _messages

    wb = bench(store=False)
    numbers = _numbers(wb)
    assert len(numbers) >= 20 and sum(integral for *_, integral in numbers) >= 2  # the Port and the Samples
    for handle, lo, hi, integral in numbers:
        before = handle.value
        for value in _bad_values(lo, hi, integral):
            message = _messages.GuiUpdateMessage(handle._impl.uuid, {"value": value})
            wb.update_screen(None, message)
            assert message.uuid == "", (handle.label, value)  # dropped: viser's handler finds no widget
            assert handle.value == before
        good = before if math.isfinite(before) else lo
        message = _messages.GuiUpdateMessage(handle._impl.uuid, {"value": good})
        wb.update_screen(None, message)
        assert message.uuid == handle._impl.uuid, handle.label  # a good value goes on to viser
    assert wb.ui.wait(10)
    assert "refused" in wb.ctrl.message


@pytest.mark.parametrize(
    "widget, updates, says",
    [
        ("live_port", {"min": 0}, "only a widget's value"),
        ("btn_load_effects", {"disabled": False}, "only a widget's value"),
        ("auto_refit", {"value": "yes"}, "is not a bool"),
        ("live_units", {"value": 3}, "is not a text"),
        ("effects_path", {"value": ["a"]}, "a text of at most"),
    ],
)
def test_other_widgets_and_properties_are_screened_too(bench, widget, updates, says):
    """Only a widget's value may change (not its range, not whether it is enabled), and only to a value of its
    type: a checkbox a bool, a dropdown or a text a text."""
    from viser import _messages

    wb = bench(store=False)
    handle = getattr(wb.panels, widget)
    message = _messages.GuiUpdateMessage(handle._impl.uuid, dict(updates))
    wb.update_screen(None, message)
    assert message.uuid == ""
    assert wb.ui.wait(10)
    assert says in wb.ctrl.message and "refused" in wb.ctrl.message


_VALUES = st.one_of(
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=5),
    st.none(),
    st.lists(st.integers(), max_size=2),
)


@settings(max_examples=300, deadline=None)
@given(value=_VALUES, lo=st.integers(-100, 100), width=st.integers(0, 1000), integral=st.booleans())
def test_a_number_the_check_accepts_is_kept_exactly_by_viser_s_cast(value, lo, width, integral):
    """:func:`number_problem` accepts exactly the values that viser's cast to the widget's type (``int`` for a
    whole-number widget, ``float`` else) keeps unchanged and that lie in the range; the rest get a message."""
    from magcal_workbench.checks import number_problem

    hi = lo + width
    why = number_problem(value, lo, hi, integral)
    kind = int if integral else float
    try:
        kept = kind(value) == value and not isinstance(value, (bool, str, list)) and lo <= value <= hi
    except (TypeError, ValueError, OverflowError):
        kept = False
    assert (why is None) == kept, (value, why)
    if why is not None:
        assert "\n" not in why and len(why) < 200
