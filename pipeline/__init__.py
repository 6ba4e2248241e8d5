"""The compute: pure functions and kernels, no sockets (see docs/architecture.md)."""
