"""Reset-seed ranges: which episodes train, which are held out, which choose settings.

Every evaluation in the project draws its reset seeds from ``HELD_OUT`` (the chapter's:
``HELD_OUT + seed + suite * episodes + e``), so no episode it scores was ever trained on
or tuned against. Correction and online runs reset from ``ONLINE`` on (far from both);
choices made by measuring (``--algo auto``) score on ``VALIDATION``, never on ``HELD_OUT``.
"""

HELD_OUT = 500_000  # the chapter's held-out reset seeds: 500000 .. 500099 for seed 0
ONLINE = 100_000  # correction and online runs: ONLINE + 10000 * seed + episode
VALIDATION = 600_000  # settings chosen by measuring are scored here

MAX_SEED = 2**32 - 1  # numpy's, torch's and the env's seeds all take 0 .. 2**32 - 1


def seed_arg(text: str) -> int:
    """argparse ``type`` of every seed flag: argparse names the flag in the error."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number from 0 to {MAX_SEED}, got '{text}'") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a whole number from 0 to {MAX_SEED}, got {value}")
    return value


def eval_reset_seeds(seed: int, n_seeds: int, eval_episodes: int) -> list[int]:
    """The held-out reset seeds of one experiment seed, suite by suite (the chapter's rule)."""
    return [HELD_OUT + seed + s * eval_episodes + e for s in range(n_seeds) for e in range(eval_episodes)]
