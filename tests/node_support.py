"""Where the optional node / browser tests find their npm packages: $ARLIGHT_NODE_MODULES,
else where scripts/node_test_deps.sh installs them (~/.cache/arlight-node/node_modules).
`node_modules_or_skip(what, *paths)` skips the test, saying what is missing and how to get
it, unless every path (relative to node_modules) exists."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DEFAULT = Path.home() / ".cache" / "arlight-node" / "node_modules"


def node_modules_or_skip(what: str, *paths: str) -> Path:
    modules = Path(os.environ.get("ARLIGHT_NODE_MODULES", DEFAULT)).resolve()
    for path in paths:
        if not (modules / path).exists():
            pytest.skip(
                f"{path} not in {modules} (scripts/node_test_deps.sh installs it, or set "
                f"ARLIGHT_NODE_MODULES): {what}"
            )
    return modules
