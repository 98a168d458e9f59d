"""``bsms``: the package's one command, with a subcommand per job.

Each subcommand runs the same code as the entry point beside it (which keeps working), and
``bsms SUBCOMMAND --help`` shows its options::

    bsms train CONFIG [section.key=value ...] [--resume]     python train.py
    bsms generate DATASET_CONFIG [--out data] [--shard I/N]   python -m datagen
    bsms evaluate RUN [--split test]                          python -m bsms.evaluate
    bsms infer RUN --mesh FILE [--solver]                     python -m bsms.infer
    bsms convert deepmind|authors SRC DST                     python -m bsms.datasets convert
    bsms export RUN OUT [--which best|latest] [--set K=V]     python -m bsms.pretrained

A subcommand's module is imported only when it runs, so ``bsms --help`` answers at once.
"""

from __future__ import annotations

import importlib
import sys
from importlib.metadata import PackageNotFoundError, version

# name -> (module with main(argv, prog), one line of help, the argv its main expects before ours)
COMMANDS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "train": ("bsms.training.train_cli", "train a learned simulator from a config (generates its data if missing)", ()),
    "generate": ("datagen.generate", "generate a dataset with the MPM solver (resumable, --shard I/N)", ()),
    "evaluate": ("bsms.evaluate", "roll a trained run out against the solver: table, chart, report.md", ()),
    "infer": ("bsms.infer", "run a trained model on a mesh of your own (--solver: and the solver beside it)", ()),
    "convert": ("bsms.datasets.__main__", "convert DeepMind's or the authors' datasets into trajectory files",
                ("convert",)),
    "export": ("bsms.infer.pretrained", "export a run's weights as a small pretrained folder", ()),
}


def _version() -> str:
    try:
        return version("bsms")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: bsms SUBCOMMAND [options]   (bsms SUBCOMMAND --help for its options)", "",
             "Generate MPM data, train bi-stride multi-scale graph networks on it, evaluate them against "
             "the solver.", "", "subcommands:"]
    lines += [f"  {name:<{width}}  {help_line}" for name, (_, help_line, _) in COMMANDS.items()]
    lines += ["", "options:", "  -h, --help  show this message", "  --version   show the version"]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    if argv[0] == "--version":
        print(f"bsms {_version()}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"error: bsms has no subcommand {name!r}; choose one of {', '.join(COMMANDS)} "
              "(bsms --help lists them)", file=sys.stderr)
        return 2
    module, _, before = COMMANDS[name]
    entry = importlib.import_module(module).main
    if before:  # a module whose own parser has subcommands: ours is one of them
        return entry([*before, *rest], prog="bsms")
    return entry(rest, prog=f"bsms {name}")


if __name__ == "__main__":
    sys.exit(main())
