"""arlight: probeless light estimation from RGB-D, as a library and a streaming service."""

import os

# numpy's BLAS (OpenBLAS) starts a thread per core for LightEst's small (50000 x 16) products;
# beside numba's and Open3D's pools those threads spin against each other: on 2 busy cores
# LightEst took up to 16 s a frame, against about 0.11 s with one BLAS thread. Takes effect
# only when arlight is imported before numpy (the `arlight` command); a user's own
# OPENBLAS_NUM_THREADS wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
