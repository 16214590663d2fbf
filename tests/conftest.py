"""Shared by every test: the tests train as the product's runs do, with the optional speed
layer registered onto the learners where it is installed (``offline_rl_core.runs`` imports
it); tests/test_speed_layer.py trains a copy of the package without it."""

import offline_rl_core.runs  # noqa: F401 - registers offline_rl_core.fast
