"""Executing a contact plan (ROS-free): configuration paths between stances
(interpolation) and their time scaling (timing)."""
