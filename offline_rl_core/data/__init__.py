"""Datasets: transitions as arrays, collecting them from a task, and rosbag2 bags
(``bag/``: reading, writing, repairing; ``raw_topics/``: transitions built from a plain
recording of a robot's topics)."""
