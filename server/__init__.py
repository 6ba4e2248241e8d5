"""arlight.server."""
