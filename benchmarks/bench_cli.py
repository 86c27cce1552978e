"""Start-up time of the command lines: how long `shadowcorr --version` etc. take as fresh processes.

    python benchmarks/bench_cli.py [--repeats 7]

Each command runs ``--repeats`` times as a new process (the way a user or a script runs it);
the table shows the median and the fastest wall time and the median CPU time (user + system,
less sensitive than wall time to other load on the machine), next to a bare
``python -c pass`` for the interpreter's own start.  Also reports whether torch was imported (``-X importtime``).
Target: ``--version`` and ``--help`` in <= 0.3 s.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
COMMANDS = [
    ("python -c pass", [sys.executable, "-c", "pass"]),
    ("shadowcorr --version", [str(BIN / "shadowcorr"), "--version"]),
    ("shadowcorr --help", [str(BIN / "shadowcorr"), "--help"]),
    ("shadowcorr correspond --help", [str(BIN / "shadowcorr"), "correspond", "--help"]),
    ("shadowcorr convert rosbag --help", [str(BIN / "shadowcorr"), "convert", "rosbag", "--help"]),
    ("shadowcorr serve --help", [str(BIN / "shadowcorr"), "serve", "--help"]),
    ("shadowcorr-client --help", [str(BIN / "shadowcorr-client"), "--help"]),
]


def run_times(cmd: list[str], repeats: int) -> tuple[list[float], list[float]]:
    """(wall seconds, CPU seconds) of each run."""
    walls, cpus = [], []
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        walls.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return walls, cpus


def imports_torch(cmd: list[str]) -> bool:
    """Whether the command imports torch (``-X importtime`` lists every module it imports)."""
    if cmd[0] == sys.executable:
        return False
    env = {**os.environ, "PYTHONPROFILEIMPORTTIME": "1"}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    return any(line.rstrip().endswith("| torch") for line in out.stderr.splitlines())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    print(f"{'command':<36}{'wall median s':>14}{'wall min s':>11}{'CPU median s':>13}  torch imported")
    for label, cmd in COMMANDS:
        walls, cpus = run_times(cmd, args.repeats)
        print(f"{label:<36}{statistics.median(walls):>14.3f}{min(walls):>11.3f}{statistics.median(cpus):>13.3f}  "
              f"{'yes' if imports_torch(cmd) else 'no'}")


if __name__ == "__main__":
    main()
