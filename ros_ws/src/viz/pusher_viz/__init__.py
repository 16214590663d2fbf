"""The arm in RViz and Foxglove (``ros2 run viz markers``)."""
