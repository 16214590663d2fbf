"""Whole runs built from the layers below: one training run from bags to files, the
chapter's experiment, the best prior (``--algo auto``), the chapter's reference loop,
several runs in worker processes, the in-process HIL-SERL loop.

Importing this package registers the optional speed layer (``offline_rl_core.fast``) onto
the learners, where it is installed: every run trains with it, or with autograd without it.
"""

try:
    import offline_rl_core.fast  # noqa: F401 - registers itself onto the learners
except ModuleNotFoundError as exc:
    if exc.name != "offline_rl_core.fast":
        raise
