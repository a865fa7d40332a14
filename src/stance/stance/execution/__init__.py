"""Executing a contact plan (ROS-free): configuration paths between stances
(interpolation), their time scaling (timing), the stabilizer gate's rule (stabilizer) and
the execution's task stacks and arrival gate (tracking)."""
