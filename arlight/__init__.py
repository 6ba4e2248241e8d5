"""arlight: probeless light estimation and coherent AR rendering from live RGB-D."""

__version__ = "0.1.0"
