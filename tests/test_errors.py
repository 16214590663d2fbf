"""Ctrl-C that surfaces through a C extension is still recognised as Ctrl-C."""

from offline_rl_core.common.errors import caused_by_interrupt


def test_an_exception_caused_by_keyboard_interrupt_counts_as_interrupt():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise TypeError("Unable to convert function return value") from inner
    except TypeError as exc:
        assert caused_by_interrupt(exc)


def test_an_ordinary_error_is_not_an_interrupt():
    try:
        try:
            raise ValueError("bad")
        except ValueError:
            raise RuntimeError("worse")  # noqa: B904 - implicit context on purpose
    except RuntimeError as exc:
        assert not caused_by_interrupt(exc)
