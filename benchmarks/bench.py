"""The benchmark suite of softbody: the same as ``softbody bench`` (logic in experiments/bench.py).

    python benchmarks/bench.py                 # default configurations (docs/benchmarks.md)
    python benchmarks/bench.py --scaling       # ms per step and memory against nodes, per element type
    python benchmarks/bench.py --tiny          # a few seconds: checks that everything runs

Every figure is measured in a fresh process per configuration, with the thread count pinned; see
``python benchmarks/bench.py --help`` and docs/benchmarks.md for the columns.
"""
from __future__ import annotations

import argparse
import sys

from experiments.bench import add_bench_arguments, bench_command


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_bench_arguments(parser)
    bench_command(parser.parse_args(argv))
    return 0


if __name__ == "__main__":  # the guard matters: measurements run in spawned processes that import this file
    sys.exit(main())
