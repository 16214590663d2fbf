"""Filtered BC: behaviour cloning on the best episodes only (top 10 % by return).

The cheap baseline the CORL benchmarks found hard to beat. The filtering happens in
the sampler (``data.top_episode_rows``); the update is BC's.
"""

from __future__ import annotations

from .bc import BC


class FilteredBC(BC):
    name = "filtered_bc"
