"""The embedded mode, `omnidata generate`: the service's parts (scheduler loop, TaskRunner) on one machine
with SQLite, a local folder and local worker processes. cli (arguments, run), job (the job and its loop), pool
(the worker processes), report (progress bar and final report).

Nothing is imported here: a spawned worker process imports services.embedded.pool before numpy loads.
"""
