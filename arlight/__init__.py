"""arlight: probeless light estimation from RGB-D, as a library and a streaming service."""

__version__ = "0.1.0"
