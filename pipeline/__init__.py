"""Orchestration: the stage graph, the on-disk cache, settings, the CLI, logging and progress."""
