"""User-facing errors: one clear line, exit code 2, never a bare traceback."""


class UserError(Exception):
    """A mistake in the user's input (a path, a bag, a flag, a checkpoint).

    The message is one line naming the file, topic or field and what was expected.
    The CLI prints it as ``offline-rl: error: <message>`` and exits with status 2.
    """

    exit_code = 2


class RunFailed(Exception):
    """A run stopped by something outside the user's input, e.g. a training worker killed
    by the OOM killer. Printed like a UserError, as one line; exit status 1."""

    exit_code = 1


def caused_by_interrupt(exc: BaseException) -> bool:
    """True when ``exc`` comes from Ctrl-C: a KeyboardInterrupt raised inside a C
    extension (e.g. rclpy deserialising a message) can surface as another exception
    whose cause is the interrupt. Nodes treat that as the user's Ctrl-C, not a crash."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
