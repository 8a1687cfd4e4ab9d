"""Foundations every topic shares: rigid-body algebra on SE(3), units, the code version."""
