"""mkdocs hook: the command-line reference page (cli.md), generated from the argparse parsers at each build."""

from __future__ import annotations

import argparse

from mkdocs.structure.files import File


def cli_reference() -> str:
    """cli.md's Markdown: ``jaxcga --help``, then each subcommand's ``--help`` (options, example), in order."""
    from jaxcga_cli.main import parser

    top = parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    lines = [
        "# Command-line reference",
        "",
        "Generated from the command line's parsers when the site is built: each section is what",
        "`jaxcga COMMAND --help` prints. [Usage](command-line.md) describes the outputs, the status lines and the",
        "errors.",
        "",
        "## jaxcga",
        "",
        "```text",
        top.format_help().rstrip(),
        "```",
        "",
    ]
    for name, command in sub.choices.items():
        lines += [f"## jaxcga {name}", "", "```text", command.format_help().rstrip(), "```", ""]
    return "\n".join(lines)


def on_files(files, config):
    """Adds the generated cli.md to the site's files."""
    files.append(File.generated(config, "cli.md", content=cli_reference()))
    return files
