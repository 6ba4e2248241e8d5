"""arlight: probeless light estimation from RGB-D, as a library and a streaming service.

Importing it changes no process-wide setting (environment, threads, warnings): the entry
points do that (`arlight.cli`, `arlight.pipeline.runtime.configure_process`).
"""

from importlib.metadata import PackageNotFoundError, version

try:  # the version is written once, in pyproject.toml; the installed metadata carries it
    __version__ = version("arlight")
except PackageNotFoundError:  # a source tree used without installing it
    __version__ = "0+unknown"
