"""The ROS-free core of each ROS node (``ros_ws/src/*``): the sim's loop, the recorder's
collection driver, the mux's arbiter, the online learner's service, and the checks of
the messages they take. A node only moves messages between DDS and one of these."""
