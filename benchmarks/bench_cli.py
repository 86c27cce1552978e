"""Start-up time of the command lines: how long `shadowcorr --version` etc. take as fresh processes.

    python benchmarks/bench_cli.py [--repeats 7]

Each command runs ``--repeats`` times as a new process (the way a user or a script runs it);
the table shows the median and the fastest wall time, next to a bare ``python -c pass`` for
the interpreter's own start.  Also reports whether torch was imported (``-X importtime``).
Target (issue 12): ``--version`` and ``--help`` in <= 0.3 s.
"""

from __future__ import annotations

import argparse
import os
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


def wall_times(cmd: list[str], repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        times.append(time.perf_counter() - start)
    return times


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
    print(f"{'command':<36}{'median s':>10}{'min s':>9}  torch imported")
    for label, cmd in COMMANDS:
        times = wall_times(cmd, args.repeats)
        print(f"{label:<36}{statistics.median(times):>10.3f}{min(times):>9.3f}  {'yes' if imports_torch(cmd) else 'no'}")


if __name__ == "__main__":
    main()
