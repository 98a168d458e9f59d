"""``python -m bsms.datasets convert deepmind|authors SRC DST [--split S] [--dt DT] [--quiet]``."""

from __future__ import annotations

import argparse
import sys

from bsms.datasets.convert import convert
from bsms.datasets.errors import SourceError
from datagen.config import ConfigError
from datagen.dataset import DatasetError


def main(argv=None, prog: str = "python -m bsms.datasets") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Convert benchmark datasets into "
                                     "the project's trajectory files (resumable, atomic).")
    sub = parser.add_subparsers(dest="command", required=True)
    conv = sub.add_parser("convert", help="convert a source dataset folder")
    conv.add_argument("kind", choices=["deepmind", "authors"], help="DeepMind TFRecords or the authors' h5 files")
    conv.add_argument("src", help="source folder (deepmind: meta.json and {train,valid,test}.tfrecord)")
    conv.add_argument("dst", help="output folder: DST/<split>/<index>.h5")
    conv.add_argument("--split", action="append", choices=["train", "valid", "test"], help="only this split")
    conv.add_argument("--dt", type=float, default=1.0, help="time between frames (default 1: frame units)")
    conv.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        counts = convert(args.kind, args.src, args.dst, splits=args.split or ("train", "valid", "test"),
                         dt=args.dt, progress=not args.quiet)
    except (SourceError, ConfigError, DatasetError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(", ".join(f"{split}: {n} trajectories" for split, n in counts.items()) + f" in {args.dst}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
