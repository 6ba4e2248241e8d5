"""MkDocs hook: the reference pages made from the code at build time (mkdocs.yml `hooks`).

Nothing here is written to disk: each page's text is made when the site is built, so the
site can never show a stale copy (the stubs committed at these paths say so to a reader of
the Markdown, and are replaced in the build). Pages:

- reference/cli.md      every `arlight` subcommand, from `arlight.cli.build_parser()`
                        (wherever the CLI lives: a module or a package, the parser is
                        imported by that name);
- reference/config.md   every `--set KEY=VALUE` key, from `arlight.pipeline.config`
                        (`FLAT_KEYS`, `FLAT_ALIASES`, the stage dataclasses, the presets'
                        values, each field's own source comment);
- reference/protocol.md `protocols/SPEC.md`, included as it is;
- reference/modules.md  every module of the source tree with the first line of its
                        docstring;
- the decision records: each docs/decisions/NNNN-*.md is put in the nav, and listed in a
                        table on decisions/index.md (where it says <!-- records -->).

Run by itself (`python docs/gen_reference.py OUT_DIR`) it writes the same pages to OUT_DIR.
"""

from __future__ import annotations

import argparse
import ast
import enum
import io
import os
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# source folders -> the package they are installed as (pyproject's package-dir)
PACKAGES = {
    "arlight": "arlight",
    "pipeline": "arlight.pipeline",
    "server": "arlight.server",
    "client": "arlight.client",
    "protocols": "arlight.protocols",
    "sources": "arlight.sources",
}


def _cell(text: object) -> str:
    """Text made safe for one Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


# ------------------------------------------------------------------ the CLI
def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    return None


def _option_row(action: argparse.Action) -> str:
    if action.option_strings:
        names = ", ".join(f"`{o}`" for o in action.option_strings)
        if action.nargs != 0:
            metavar = action.metavar or (
                "{" + ",".join(map(str, action.choices)) + "}"
                if action.choices
                else action.dest.upper()
            )
            names += f" `{metavar}`"
    else:
        names = f"`{action.metavar or action.dest}`"
    default = action.default
    if default in (None, argparse.SUPPRESS, False) or action.nargs == 0:
        shown = ""
    else:
        shown = f"`{default}`"
    return f"| {_cell(names)} | {_cell(shown)} | {_cell(action.help or '')} |"


def _command_page(
    parser: argparse.ArgumentParser, name: str, summary: str, level: int
) -> list[str]:
    lines = [f"{'#' * level} `{name}`", ""]
    if summary:
        lines += [f"*{summary}*", ""]
    if parser.description:
        lines += [parser.description.strip(), ""]
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    rows = [
        _option_row(a)
        for a in parser._actions
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
        and a.help != argparse.SUPPRESS
    ]
    if rows:
        lines += ["| argument | default | what it does |", "|---|---|---|", *rows, ""]
    if parser.epilog:
        lines += ["```text", parser.epilog.strip(), "```", ""]
    sub = _subparsers(parser)
    if sub is not None:
        helps = {a.dest: a.help or "" for a in sub._choices_actions}
        for child_name, child in sub.choices.items():
            lines += _command_page(
                child, f"{name} {child_name}", helps.get(child_name, ""), min(level + 1, 4)
            )
    return lines


def cli_page() -> str:
    import arlight.cli  # a module or a package: build_parser is its public entry point

    os.environ["COLUMNS"] = "100"  # argparse wraps usage lines to the terminal's width
    parser = arlight.cli.build_parser()
    parser.prog = "arlight"
    sub = _subparsers(parser)
    names = list(sub.choices) if sub is not None else []
    lines = [
        "# Command line: `arlight`",
        "",
        "Generated at build time from `arlight.cli.build_parser()`, so it lists exactly the "
        "arguments the installed command accepts (`arlight COMMAND --help` prints the same). "
        "How `arlight` gets on your PATH: [Getting started](../getting-started.md).",
        "",
        "Commands: " + ", ".join(f"[`{n}`](#arlight-{n.replace(' ', '-')})" for n in names),
        "",
    ]
    lines += _command_page(parser, "arlight", "", 2)
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ the --set keys
def _field_comments(cls: type) -> dict[str, str]:
    """Each dataclass field's comments in its class's source: the comment lines right above
    it and the comment at the end of its line, joined."""
    import inspect

    comments: dict[str, str] = {}
    block: list[str] = []  # comment lines since the last line of code
    line: list[tokenize.TokenInfo] = []
    source = io.StringIO(inspect.getsource(cls)).readline
    for tok in tokenize.generate_tokens(source):
        if tok.type not in (tokenize.NEWLINE, tokenize.NL):
            line.append(tok)
            continue
        code = [t for t in line if t.type in (tokenize.NAME, tokenize.OP)]
        said = [t.string.lstrip("#").strip() for t in line if t.type == tokenize.COMMENT]
        if not code:
            block += said
        else:
            # a field: `name: type [= default]` at the class body's indentation
            if (
                len(code) > 1
                and code[0].type == tokenize.NAME
                and code[1].string == ":"
                and code[0].start[1] == 4
            ):
                comments[code[0].string] = " ".join(block + said)
            block = []
        line = []
    return comments


def _value(value: object) -> str:
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def config_page() -> str:
    from arlight.pipeline import config as cfg

    presets = list(cfg.PRESETS)
    flat = {name: cfg.Config.from_preset(name).flat() for name in presets}
    types = cfg.Config.flat_key_types()
    lines = [
        "# Pipeline parameters: `--set KEY=VALUE`",
        "",
        "Generated at build time from `arlight.pipeline.config` (`FLAT_KEYS`, the stage "
        "dataclasses and the presets), so every key the code accepts is here with its "
        "default. The same keys work everywhere: `arlight estimate|stream|batch|bench --set "
        'KEY=VALUE`, `Config.from_preset("fast", KEY=VALUE)`, `config.replace(KEY=VALUE)` '
        "and a streamed session's overrides. An unknown key is refused with the list of "
        "valid ones; a value out of range is refused naming the key.",
        "",
        "Presets: `full` is the paper's *Ours* (every pixel), `fast` its *OursFast* "
        "(radiance transfer and differential buffers on a 4x4 sub-sampled grid, interpolated "
        "back), `mobile` a 64^3 volume without D''' and fewer samples. What each costs and "
        "how accurate it is: [Results: accuracy](../results/accuracy.md) and "
        "[speed](../results/speed.md). Columns `fast` and `mobile` show a value only where "
        "the preset changes it. Comments are the code's own; the evidence behind a choice "
        "is in the [decision records](../decisions/index.md).",
        "",
    ]
    top = [(k, s, n) for k, (s, n) in cfg.FLAT_KEYS.items() if s is None]
    groups: list[tuple[str, str, list[str]]] = [
        ("Config", (cfg.Config.__doc__ or "").strip().splitlines()[0], [k for k, _, _ in top])
    ]
    comments: dict[str, str] = {}
    for stage, cls in cfg.STAGE_TYPES.items():
        keys = [k for k, (s, _) in cfg.FLAT_KEYS.items() if s == stage]
        doc = " ".join((cls.__doc__ or "").split())
        groups.append((f"{cls.__name__} (`config.{stage}`)", doc, keys))
        for name, text in _field_comments(cls).items():
            comments[name] = text
    for name, text in _field_comments(cfg.Config).items():
        comments.setdefault(name, text)
    for title, doc, keys in groups:
        lines += [
            f"## {title}",
            "",
            doc,
            "",
            "| key | type | full | fast | mobile | notes (from the code) |",
            "|---|---|---|---|---|---|",
        ]
        for key in keys:
            base = _value(flat["full"][key])
            cols = [
                _value(flat[p][key]) if flat[p][key] != flat["full"][key] else ""
                for p in ("fast", "mobile")
                if p in flat
            ]
            kind = types.get(key, type(flat["full"][key])).__name__
            field_name = cfg.FLAT_KEYS[key][1]
            lines.append(
                f"| `{key}` | {kind} | `{base}` | "
                + " | ".join(f"`{c}`" if c else "" for c in cols)
                + f" | {_cell(comments.get(field_name, ''))} |"
            )
        lines.append("")
    if cfg.FLAT_ALIASES:
        lines += [
            "## Aliases",
            "",
            "Keys in another unit, converted to the canonical key "
            "(give one or the other, not both):",
            "",
            "| alias | sets | accepted range |",
            "|---|---|---|",
        ]
        for alias, (canonical, _convert, (low, high)) in cfg.FLAT_ALIASES.items():
            lines.append(f"| `{alias}` | `{canonical}` | ({low:g}, {high:g}] |")
        lines.append("")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ the protocol spec
def protocol_page() -> str:
    spec = (ROOT / "protocols" / "SPEC.md").read_text(encoding="utf-8")
    note = (
        '!!! note "Source"\n    This page is `protocols/SPEC.md`, included as it is at '
        "build time.\n\n"
    )
    head, _, rest = spec.partition("\n")
    return head + "\n\n" + note + rest


# ------------------------------------------------------------------ the module map
def _first_doc_line(path: Path) -> str:
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"))
    except (SyntaxError, UnicodeDecodeError):
        return ""
    doc = ast.get_docstring(tree) or ""
    first = doc.strip().split("\n\n")[0]
    return " ".join(first.split())


def modules_page() -> str:
    lines = [
        "# Module map",
        "",
        "Generated at build time: every module of the source tree with the first paragraph "
        "of its docstring, so a module added, moved or split shows here on the next build. "
        "Who may import whom: [Architecture](../architecture.md).",
        "",
    ]
    for folder, package in PACKAGES.items():
        base = ROOT / folder
        if not base.is_dir():
            continue
        lines += [f"## `{package}` (`{folder}/`)", "", "| module | what it is |", "|---|---|"]
        for path in sorted(base.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            rel = path.relative_to(ROOT).as_posix()
            lines.append(f"| `{rel}` | {_cell(_first_doc_line(path))} |")
        lines.append("")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ decision records
def _decision_records() -> list[tuple[str, str, str, str]]:
    """(path under docs/, title, decision, date) of every docs/decisions/NNNN-*.md."""
    records = []
    for path in sorted((ROOT / "docs" / "decisions").glob("[0-9][0-9][0-9][0-9]-*.md")):
        text = path.read_text(encoding="utf-8")
        title = text.splitlines()[0].lstrip("# ").strip()
        fields = {}
        for line in text.splitlines():
            if line.startswith("- **") and "**:" in line:
                key, _, value = line[4:].partition("**:")
                fields[key.strip().lower()] = value.strip()
        records.append(
            (f"decisions/{path.name}", title, fields.get("decision", ""), fields.get("date", ""))
        )
    return records


def decisions_table() -> str:
    rows = ["| record | decision | date |", "|---|---|---|"]
    for uri, title, decision, date in _decision_records():
        rows.append(
            f"| [{_cell(title)}]({uri.split('/', 1)[1]}) | {_cell(decision)} | {_cell(date)} |"
        )
    return "\n".join(rows) + "\n"


PAGES = {
    "reference/cli.md": cli_page,
    "reference/config.md": config_page,
    "reference/protocol.md": protocol_page,
    "reference/modules.md": modules_page,
}


# ------------------------------------------------------------------ the MkDocs hook
def _installed_layout() -> Path:
    """A folder of symbolic links laid out as the installed package (pipeline/ as
    arlight/pipeline, ...), for mkdocstrings to read the sources statically: the package-dir
    mapping of pyproject is what an import sees, not what a source reader finds."""
    import atexit
    import shutil
    import tempfile

    top = Path(tempfile.mkdtemp(prefix="arlight-api-"))
    atexit.register(shutil.rmtree, top, ignore_errors=True)
    package = top / "arlight"
    package.mkdir()
    for entry in (ROOT / "arlight").iterdir():
        if entry.name != "__pycache__":
            (package / entry.name).symlink_to(entry)
    for folder, name in PACKAGES.items():
        if name != "arlight" and (ROOT / folder).is_dir():
            (package / name.split(".", 1)[1]).symlink_to(ROOT / folder)
    return top


def _first(function):  # before mkdocstrings' own on_config makes its handlers
    from mkdocs.plugins import event_priority

    return event_priority(100)(function)


@_first
def on_config(config):  # noqa: ANN001 (MkDocs' own types)
    for item in config.nav or []:  # every decision record under "Decisions", in order
        if isinstance(item, dict) and isinstance(item.get("Decisions"), list):
            item["Decisions"] += [{title: uri} for uri, title, _, _ in _decision_records()]
    plugin = config.plugins.get("mkdocstrings")
    if plugin is not None:
        python = plugin.config.handlers.setdefault("python", {})
        python["paths"] = [str(_installed_layout())]
    return config


def on_files(files, config):  # noqa: ANN001 (MkDocs' own types)
    from mkdocs.structure.files import File

    for uri in PAGES:  # a committed stub (for readers of the Markdown) is filled in below
        if files.get_file_from_path(uri) is None:
            files.append(File.generated(config, uri, content=""))
    return files


def on_page_markdown(markdown, page, config, files):  # noqa: ANN001
    uri = page.file.src_uri
    if uri in PAGES:
        return PAGES[uri]()
    if uri == "decisions/index.md":
        return markdown.replace("<!-- records -->", decisions_table())
    return markdown


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "generated-reference")
    for uri, make in PAGES.items():
        target = out / uri
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(make(), encoding="utf-8")
        print(target)
