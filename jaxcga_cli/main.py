"""The ``jaxcga`` command: parses the command line and runs one subcommand (one module each, in this package)."""

from __future__ import annotations

import argparse
import importlib
import math
import re
import sys
import textwrap

# subcommand -> its module in this package; each has HELP (one plain line), EXAMPLE, add_arguments(parser),
# check_paths(args) (every path checked before anything is loaded or computed) and run(args) (what the summary line
# names and the summary {name: value}, or None for a command that prints its own report)
COMMANDS = {
    "demo": "demo",
    "skin": "skin",
    "animate": "animate",
    "animate-batch": "animate_batch",
    "fit": "fit",
    "cut": "cut",
    "tear": "tear",
    "drill": "drill",
    "deform": "deform",
    "arap": "arap",
    "fem": "fem",
    "xfem": "xfem",
    "physics": "physics",
    "view": "view",
}
DESCRIPTION = (
    "jaxcga: differentiable geometry and simulation in JAX on a conformal geometric algebra kernel: pose, "
    "cut, tear, drill, deform and simulate meshes from the command line. Run 'jaxcga COMMAND --help' for "
    "a command's options and an example."
)

NO_CACHE_HELP = "compile afresh: neither read nor write the compilation cache (as JAXCGA_NO_CACHE=1)"


def version() -> str:
    """The installed distribution's version (its metadata), or a note that it is not installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("jaxcga")
    except PackageNotFoundError:
        return "unknown (not installed; run 'pip install -e .')"


def _finite_float(value: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {value!r}")
    return number


class _Parser(argparse.ArgumentParser):
    """argparse with every ``type=float`` option finite, negative numbers in any notation read as values
    (argparse's own test, ``-1`` or ``-.5``, takes ``-1e0`` for an option) and errors on one line."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register("type", float, _finite_float)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE
        )

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def command_module(name: str):
    """The module of subcommand ``name``."""
    return importlib.import_module(f"jaxcga_cli.{COMMANDS[name]}")


def parser() -> argparse.ArgumentParser:
    """The parser of the whole command line (no JAX imported: ``--help`` and ``--version`` answer at once)."""
    from jaxcga_cli import cache

    said = cache.help_text()
    top = _Parser(
        prog="jaxcga",
        description=textwrap.fill(DESCRIPTION, 100, break_on_hyphens=False),
        # raw: the cache's path stays whole on its line, to be copied
        epilog=textwrap.fill(said[0].upper() + said[1:] + ".", 100, break_on_hyphens=False, break_long_words=False),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    top.add_argument("--version", action="version", version=f"jaxcga {version()}")
    top.add_argument("--no-cache", action="store_true", help=NO_CACHE_HELP)
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        module = command_module(name)
        description = textwrap.fill(module.HELP[0].upper() + module.HELP[1:] + ".", 100, break_on_hyphens=False)
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=description,
            epilog=f"example:\n  {module.EXAMPLE}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        # also after the command's name; SUPPRESS keeps a --no-cache given before it
        p.add_argument("--no-cache", action="store_true", default=argparse.SUPPRESS, help=NO_CACHE_HELP)
    return top


def main(argv: list[str] | None = None) -> int:
    from jaxcga_cli.report import error_message, one_line_reports

    top = parser()
    args = top.parse_args(argv)
    module = command_module(args.command)
    try:
        with one_line_reports(args.command):
            module.check_paths(args)
            import jax

            from jaxcga_cli import cache

            # the command line computes in double precision and caches what it compiles (the library leaves both
            # choices to its caller)
            jax.config.update("jax_enable_x64", True)
            cache.enable(args.command, args.no_cache)
            summary = module.run(args)
    except (ValueError, OSError, RuntimeError) as error:
        top.exit(2, f"jaxcga {args.command}: error: {error_message(error)}\n")
    except KeyboardInterrupt:
        # one line, not a traceback through JAX: a command writes its outputs whole at its end (beside, then moved)
        top.exit(130, f"jaxcga {args.command}: interrupted; its outputs were left as they were\n")
    if summary is not None:
        subject, shown = summary
        print(f"jaxcga {args.command} {subject}: " + ", ".join(f"{k} {v}" for k, v in shown.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
