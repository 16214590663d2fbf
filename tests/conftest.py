"""Shared by every test: the tests train as the product's runs do, with the optional speed
layer registered onto the learners where it is installed (``offline_rl_core.runs`` imports
it); tests/test_speed_layer.py trains a copy of the package without it."""

import offline_rl_core.runs  # noqa: F401 - registers offline_rl_core.fast

import os

from hypothesis import settings

# The property tests draw the same examples on every run, so CI passes or fails on the code,
# not on the draw; what a draw once found stays as an explicit test (test_bag_layouts has
# one). HYPOTHESIS_PROFILE=explore draws new examples, to look for more.
settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
