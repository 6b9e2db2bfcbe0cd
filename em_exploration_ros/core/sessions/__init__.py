"""The team protocol as ROS-free sessions that take inputs and return effects, and em-sim's
in-process team that drives them; the ROS nodes drive the same sessions."""
