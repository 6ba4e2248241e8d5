"""The compute: pure functions and kernels, no sockets (see DESIGN.md)."""

import warnings

# numba probes an old system TBB and warns before falling back to OpenMP/workqueue;
# the fallback is fine and the warning only confuses users
warnings.filterwarnings("ignore", message=".*TBB threading layer.*")
