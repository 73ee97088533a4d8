"""Orchestration above the stages: the CLI and its commands, the stage graph and runner, the on-disk cache, settings
and presets, reports and progress, batches, and the viewer's server. Nothing in stages/ or plenoxels/ imports it."""
