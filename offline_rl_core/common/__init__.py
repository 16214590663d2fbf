"""The bottom layer: what every other layer may use and that knows nothing of robots or
learning: atomic writes, user errors, output paths, seed ranges, rejection counts, and
facts about this machine (CPU flags, the per-machine measurement cache)."""
