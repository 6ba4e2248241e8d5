"""arlight.protocols."""
