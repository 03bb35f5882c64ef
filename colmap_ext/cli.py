"""The `colmap-ext` command: one subcommand per pipeline step, COLMAP's flag names.

Each subcommand lives in its own module, which exposes `add_arguments(parser)` and a
`main(**kwargs)` whose keyword arguments are the parser's destinations, so the same
step is one call from Python and one command from the shell.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import tempfile
from typing import NoReturn

from colmap_ext import __version__
from colmap_ext.errors import Interrupted, UserError
from colmap_ext.memory import limit_malloc_arenas

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "mapper": ("colmap_ext.mapper.cli", "Reconstruct poses and points from a COLMAP database "
               "(known intrinsics), like `colmap mapper`."),
    "hierarchical_mapper": ("colmap_ext.hierarchical_mapper.cli", "Map a large database cluster "
                            "by cluster (local processes or Ray tasks) and join the models, "
                            "like `colmap hierarchical_mapper`."),
    "reconstruct": ("colmap_ext.reconstruct", "Images and known intrinsics in, a COLMAP "
                    "workspace out: features, matching, verification and the mapper."),
    "evaluate": ("colmap_ext.evaluate", "Measure a model's poses against ground truth "
                 "(the paper's R_err, T_err, C_err)."),
    "compare": ("colmap_ext.compare", "Run our mapper and COLMAP's on copies of one database "
                "and compare them (with ground truth: their errors)."),
    "rig_config_from_kalibr": ("colmap_ext.rigs", "Write COLMAP's rig configuration JSON "
                               "(for `reconstruct --rig_config`, `colmap rig_configurator`) "
                               "from Kalibr camchain YAML files."),
    "demo": ("colmap_ext.demo", "Render a synthetic ring scene, reconstruct it and "
             "measure the result."),
}


def _raise_interrupted(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def handle_interrupts() -> None:
    """SIGINT and SIGTERM raise `Interrupted`, so every command cleans up and ends the
    same way. pycolmap's glog replaces SIGTERM's handler with a stack dump, so this runs
    once pycolmap is loaded; a SIGINT ignored from the start (a background job) stays
    ignored."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _raise_interrupted)


def silence_colmap_logs() -> None:
    """No more of COLMAP's log lines (glog's level raised to FATAL), where pycolmap is loaded."""
    pycolmap = sys.modules.get("pycolmap")
    if pycolmap is not None:
        pycolmap.logging.minloglevel = int(pycolmap.logging.Level.FATAL)


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser with COLMAP's kind of error: one line and a non-zero exit (2),
    instead of the usage block and then the error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} -h')\n")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the subcommand named in `argv` (all of them when `argv` is None)
    is imported and given its flags, so a command does not pay for the others' imports."""
    named = [a for a in argv if a in COMMANDS][:1] if argv is not None else list(COMMANDS)
    parser = ArgumentParser(
        prog="colmap-ext",
        description="Camera poses for calibrated cameras, as a drop-in for `colmap mapper`.",
    )
    parser.add_argument("--version", action="version", version=f"colmap-ext {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        if name in named:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(_module=module, _parser=sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    limit_malloc_arenas()  # before any thread starts: imports start BLAS's
    # Python finds TMPDIR by writing a probe file with a random name there and removing
    # it: done once here, before any work, so that a kill -9 mid-run never leaves it.
    tempfile.gettempdir()
    argv = sys.argv[1:] if argv is None else argv
    try:
        # pycolmap's glog installs a stack dump for SIGTERM as pycolmap loads: load it
        # before the subcommand, and replace that handler at once (handle_interrupts).
        # Not at the top: after NumPy (colmap_ext/__init__.py), or PNG writes abort.
        import pycolmap

        # COLMAP's log lines go to stderr as before, but not also to files in /tmp (glog's
        # default in pycolmap), which every run would leave behind.
        pycolmap.logging.logtostderr = True
        handle_interrupts()
        parser = build_parser(argv)  # imports the subcommand: Ctrl-C may come that early
        args, unknown = parser.parse_known_args(argv)
        if args.command is None:
            if unknown:
                parser.error(f"unrecognized arguments: {' '.join(unknown)}")
            parser.print_help()
            return 0
        if unknown:  # said by the subcommand, whose -h lists what it takes
            args._parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        kwargs = {k: v for k, v in vars(args).items()
                  if k not in ("command", "_module", "_parser")}
        args._module.main(**kwargs)
    except UserError as exc:
        print(f"colmap-ext: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        silence_colmap_logs()  # COLMAP's threads still winding down: our line is the last
        # On a line of its own: the signal may have cut a progress bar (a child's) mid-line.
        print(f"\ncolmap-ext: interrupted by {signal.Signals(signum).name}; no partial result "
              "was written", file=sys.stderr)
        return 128 + signum
    return 0
