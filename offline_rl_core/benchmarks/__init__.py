"""Benchmarks of the learning core against its references (`offline-rl bench`).

Each figure group is one module (``train``, ``decode``, ``eval_rollouts``, ``serve``,
``record``) with a ``run(settings) -> list[Figure]``; ``harness`` times, tabulates and
writes the JSON. The references live here too: ``reference_chapter`` (the chapter's
plain training loop) and ``d3rlpy_ref`` (d3rlpy, an optional extra: never imported by
the runtime package).
"""
