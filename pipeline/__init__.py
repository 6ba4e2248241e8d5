"""The compute: pure functions and kernels, no sockets (see DESIGN.md)."""
