"""The compute: pure functions and kernels, no sockets (see docs/architecture.md).

Importing it changes no process-wide setting; entry points call
`arlight.pipeline.runtime.configure_process()` once at start.
"""
