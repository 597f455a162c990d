"""CPU time of ``seqvpr --help``, each command's ``--help`` and an option error, against two yardsticks measured in
the same run: a bare interpreter (``python -c pass``) and one that imports torch (what a command that loaded its
libraries at start-up would pay). Target: under 0.5 s of CPU each, far below the torch yardstick.

    .venv/bin/python bench/bench_cli_startup.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys

CASES = {
    "seqvpr --help": ["--help"],
    "seqvpr match --help": ["match", "--help"],
    "seqvpr train jist --help": ["train", "jist", "--help"],
    "seqvpr train seqmatchnet --help": ["train", "seqmatchnet", "--help"],
    "seqvpr benchmark --help": ["benchmark", "--help"],
    "seqvpr demo --help": ["demo", "--help"],
    "seqvpr match --k x (option error)": ["match", "-r", "a", "-q", "b", "--k", "x"],
}
YARDSTICKS = {"python -c pass": ["-c", "pass"], "python -c 'import torch'": ["-c", "import torch"]}


def cpu_seconds(argv: list[str]) -> float:
    """User + system CPU seconds of one child process (which must exit 0, or 2 for an option error)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 2) or "Traceback" in done.stderr:
        raise SystemExit(f"{' '.join(argv)} failed: {done.stderr.strip()[-300:]}")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def median_cpu(argv: list[str], repeat: int) -> float:
    return statistics.median(cpu_seconds(argv) for _ in range(repeat))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per case (the median is printed)")
    repeat = parser.parse_args().repeat
    command = [sys.executable, "-m", "seqvpr.cli"]
    torch = median_cpu([sys.executable, *YARDSTICKS["python -c 'import torch'"]], repeat)
    print(f"{'case':<36}{'CPU s':>8}{'vs torch import':>18}")
    for name, argv in YARDSTICKS.items():
        seconds = median_cpu([sys.executable, *argv], repeat)
        print(f"{name:<36}{seconds:>8.3f}{seconds / torch:>17.2f}x")
    for name, argv in CASES.items():
        seconds = median_cpu([*command, *argv], repeat)
        print(f"{name:<36}{seconds:>8.3f}{seconds / torch:>17.2f}x")


if __name__ == "__main__":
    main()
