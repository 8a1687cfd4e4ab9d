"""Prefect task wrappers, the only Prefect-aware modules of tasks/: each wraps one topic's science with a cache key."""
