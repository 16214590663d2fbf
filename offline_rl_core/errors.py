"""User-facing errors: one clear line, exit code 2, never a bare traceback."""


class UserError(Exception):
    """A mistake in the user's input (a path, a bag, a flag, a checkpoint).

    The message is one line naming the file, topic or field and what was expected.
    The CLI prints it as ``offline-rl: error: <message>`` and exits with status 2.
    """

    exit_code = 2
