"""Shared ROS-side helpers of the fluxdrive nodes (CDR codec, QoS, parameters, runner)."""
