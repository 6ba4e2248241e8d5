"""arlight.client."""
