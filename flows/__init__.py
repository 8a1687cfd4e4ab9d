"""Prefect flows: the jobs a user runs. Each wires tasks and does no maths itself."""
