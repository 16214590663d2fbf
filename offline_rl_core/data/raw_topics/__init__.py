"""Datasets from raw robot topics: what a real arm logs, joined into transitions.

A robot logs its joint states, its commands and its goal on separate topics at their own
rates; nobody publishes the transition message. ``transitions_from_topics(bag, task)``
joins them by stamp into Transitions as the task file says (``build``; the topics a task
reads: ``spec``), decoding the messages in numpy passes (``messages``, ``streams``).
``LiveJoin`` (``live``) builds the same transitions from the topics as they arrive, for
the online learner. `offline-rl dataset` and `offline-rl train --from-topics` use the batch join.
"""

from .build import JoinReport, transitions_from_topics
from .live import LiveJoin
from .spec import JoinPlan, plan_for

__all__ = ["JoinPlan", "JoinReport", "LiveJoin", "plan_for", "transitions_from_topics"]
