"""Ctrl-C that surfaces through a C extension is still recognised as Ctrl-C."""

import pytest

from offline_rl_core.common.errors import caused_by_interrupt


def test_an_exception_caused_by_keyboard_interrupt_counts_as_interrupt():
    def convert():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise TypeError("Unable to convert function return value") from inner

    with pytest.raises(TypeError) as raised:
        convert()
    assert caused_by_interrupt(raised.value)


def test_an_ordinary_error_is_not_an_interrupt():
    def fail():
        try:
            raise ValueError("bad")
        except ValueError:
            raise RuntimeError("worse")  # noqa: B904 - implicit context on purpose

    with pytest.raises(RuntimeError) as raised:
        fail()
    assert not caused_by_interrupt(raised.value)
