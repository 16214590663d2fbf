"""Multi-process runs over ROS 2: ``make demo``, ``offline-rl hil`` (offline rounds and the
online stage). Nodes are started as processes from the launch files, on a private DDS
domain, and stopped by pid (``processes``)."""
