"""Driving policies from pixels (behaviour cloning on the shards) and the closed loop inside a world model."""
