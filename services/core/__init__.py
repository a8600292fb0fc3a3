"""Shared domain package: cue catalog, JobSpec, keys, camera conventions, settings, DB models, storage."""
