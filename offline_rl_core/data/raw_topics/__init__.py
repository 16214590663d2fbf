"""Datasets from raw robot topics: what a real arm logs, joined into transitions.

A robot logs its joint states, its commands and its goal on separate topics at their own
rates; nobody publishes the transition message. ``transitions_from_topics(bag, spec)``
joins them by stamp into Transitions (``build``), decoding the messages in numpy passes
(``messages``), as a YAML spec says (``spec``; the shipped example is
``bags/pusher_topics.yaml``). `offline-rl dataset --from-topics` and
`offline-rl train --from-topics` use it.
"""

from .build import JoinReport, source_from_tag, transitions_from_topics
from .spec import TopicSpec, load_spec, spec_from_dict

__all__ = ["JoinReport", "TopicSpec", "load_spec", "source_from_tag", "spec_from_dict", "transitions_from_topics"]
