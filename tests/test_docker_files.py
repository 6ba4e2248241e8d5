"""docker/ against the CLI: every `arlight` command the container files run is one the CLI
accepts (its own argparse parser, `arlight.cli.build_parser`), every image compose.yaml names
is a target of the Containerfile, and the module the build runs exists.

The images themselves are built and run by docker/smoke-test.sh (podman, minutes), not here.
"""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
from pathlib import Path

import pytest

from arlight.cli import build_parser

DOCKER = Path(__file__).resolve().parent.parent / "docker"
CONTAINERFILE = DOCKER / "Containerfile"
COMPOSE = DOCKER / "compose.yaml"
SMOKE_TEST = DOCKER / "smoke-test.sh"


def _logical_lines(path: Path) -> list[str]:
    """The file's lines without comments, backslash continuations joined."""
    text = "\n".join(
        line for line in path.read_text().splitlines() if not line.lstrip().startswith("#")
    )
    return [line.strip() for line in text.replace("\\\n", " ").splitlines()]


def _until_shell_syntax(words: list[str]) -> list[str]:
    """The command's own words: up to a redirection, pipe or command separator."""
    out = []
    for word in words:
        if word in ("|", "||", "&&", ";", ">", "2>&1", ">/dev/null") or word.startswith(">"):
            break
        out.append(word)
    return out


def _compose_commands() -> list[list[str]]:
    commands = []
    for line in _logical_lines(COMPOSE):
        m = re.search(r"(?:^|\|\||&&|;)\s*(?:exec\s+)?arlight\s+(.*)", line)
        if m:
            commands.append(_until_shell_syntax(shlex.split(m.group(1), comments=True)))
    return commands


def _containerfile_commands() -> list[list[str]]:
    """Each target's CMD (the image's ENTRYPOINT is `arlight`)."""
    lines = _logical_lines(CONTAINERFILE)
    entrypoints = [
        json.loads(line.split(None, 1)[1]) for line in lines if line.startswith("ENTRYPOINT")
    ]
    assert entrypoints == [["arlight"]]
    return [
        json.loads(line.split(None, 1)[1])
        for line in lines
        if line.startswith("CMD") and "--help" not in line
    ]


def _smoke_test_commands() -> list[list[str]]:
    """The `podman run ... IMAGE ARGS` lines of smoke-test.sh whose entrypoint is arlight,
    its variables filled in as the script sets them."""
    values = {
        "$K": "--server-key /keys/server.key --client-key /keys/client.key_secret "
        "--token-file /keys/session.token",
        '"$FRAMES"': "24",
    }
    commands = []
    for line in _logical_lines(SMOKE_TEST):
        m = re.search(r'"\$(?:CLIENT|SERVER)"\s+(.*)', line)
        if not line.startswith("podman run") or not m or "--entrypoint" in line:
            continue
        args = m.group(1)
        for name, value in values.items():
            args = args.replace(name, value)
        words = _until_shell_syntax(shlex.split(args, comments=True))
        if words:
            commands.append(words)
    return commands


COMMANDS = (
    [("compose.yaml", c) for c in _compose_commands()]
    + [("Containerfile", c) for c in _containerfile_commands()]
    + [("smoke-test.sh", c) for c in _smoke_test_commands()]
)


def test_the_files_run_the_commands_they_should():
    subcommands = {(where, c[0]) for where, c in COMMANDS}
    assert {("compose.yaml", s) for s in ("keys", "serve", "display", "stream")} <= subcommands
    assert ("Containerfile", "serve") in subcommands
    assert {("smoke-test.sh", "display"), ("smoke-test.sh", "stream")} <= subcommands


@pytest.mark.parametrize("where,argv", COMMANDS, ids=[f"{w}:{c[0]}" for w, c in COMMANDS])
def test_every_arlight_command_parses(where, argv):
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{where}: `arlight {shlex.join(argv)}` is refused by the CLI ({exc})")
    if args.command == "serve":  # a network bind needs keys (no --insecure in docker/)
        assert args.keys and not args.insecure, (where, argv)
    if args.command in ("stream", "display"):
        assert args.server_key and args.client_key and args.token_file, (where, argv)


def test_compose_images_are_containerfile_targets():
    targets = set(re.findall(r"^FROM\s+\S+\s+AS\s+(\S+)", CONTAINERFILE.read_text(), re.M))
    images = set(re.findall(r"image:\s*localhost/arlight-([\w-]+):", COMPOSE.read_text()))
    assert {"server", "server-cuda", "client"} <= targets
    assert images and images <= targets


def test_the_build_runs_modules_that_exist():
    modules = set(re.findall(r"python -m ([\w.]+)", CONTAINERFILE.read_text()))
    assert "arlight.warmup" in modules
    for module in modules:
        assert importlib.util.find_spec(module) is not None, module
