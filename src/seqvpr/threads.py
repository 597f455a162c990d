"""One thread policy for the whole program: how many threads torch, numba and faiss each use.

A robot's computer is shared. Each of the three libraries starts a pool that wants every core, and on a busy
machine those pools wait on each other and on the other processes (one frame through the encoder: 66 ms with one
thread, 2.4 s with two, measured under load). So seqvpr chooses one count at start-up and gives it to all three:
``--threads`` or ``$SEQVPR_THREADS`` when given, else ``$OMP_NUM_THREADS`` (what torchrun sets for its ranks), else
the cores no other process is using right now (all of them on an idle machine, one on a busy one). The CLI applies
it before any library starts its pool; the public Python entry points (``build_map``, ``Localizer.open``,
``run_demo``, ...) apply it once if nothing has, and re-assert it after building what resets it (numba's OpenMP
launch sets the OpenMP count torch reads).

Nothing here imports torch, numba or faiss: a library not imported yet takes the count from the environment.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from seqvpr.errors import SeqvprError

ENV = "SEQVPR_THREADS"
#: environment variables the thread pools read when they start (numba's only before numba is imported)
POOL_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
LOAD_SAMPLES, LOAD_INTERVAL = 9, 0.005  # /proc/stat read 9 times 5 ms apart: about 40 ms at start-up


@dataclass(frozen=True)
class ThreadPolicy:
    """The thread count every pool uses, where it came from (``--threads``, ``SEQVPR_THREADS``, ``OMP_NUM_THREADS``
    or ``free cores``), and the cores this process may run on with how many other processes kept busy."""

    threads: int
    source: str
    cores: int
    busy: float | None = None

    def describe(self) -> str:
        """One line for ``seqvpr doctor`` and logs."""
        load = "" if self.busy is None else f"; {self.busy:g} of them busy with other work at start"
        return f"{self.threads} thread{'s' * (self.threads != 1)} (from {self.source}; {self.cores} cores usable{load})"


_applied: ThreadPolicy | None = None
_exported: str | None = None  # the count this process wrote to OMP_NUM_THREADS (not a user's choice to read back)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def busy_cores(samples: int = LOAD_SAMPLES, interval: float = LOAD_INTERVAL, stat: Path = Path("/proc/stat"),
               own: Path = Path("/proc/self/task")) -> float | None:
    """How many other processes' threads are running right now: the median over a few reads of the kernel's count
    of runnable tasks, less this process's own running threads (numpy's BLAS pool spins for a while after
    import); None where the system does not say (not Linux)."""
    counts = []
    for i in range(samples):
        running = _procs_running(stat)
        if running is None:
            return None
        counts.append(max(0, running - max(1, _own_running(own))))
        if i + 1 < samples:
            time.sleep(interval)
    return float(statistics.median(counts))


def _own_running(tasks: Path) -> int:
    """This process's threads in the running state (R), from ``/proc/self/task/*/stat``; 0 if unreadable."""
    count = 0
    try:
        for task in tasks.iterdir():
            try:
                if (task / "stat").read_text().rsplit(")", 1)[1].split()[0] == "R":
                    count += 1
            except (OSError, IndexError):
                continue
    except OSError:
        return 0
    return count


def _procs_running(stat: Path) -> int | None:
    try:
        for line in stat.read_text().splitlines():
            if line.startswith("procs_running"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def free_cores(cores: int, busy: float | None) -> int:
    """Threads that do not compete with the rest of the machine: the usable cores no other process is running on,
    at least one (an unknown load counts as none)."""
    return max(1, cores - int(round(busy or 0.0)))


def parse_threads(text: str, where: str, cores: int) -> int:
    """A thread count from an option or variable; anything but a whole number from 1 to 4x the usable cores (more
    only waits on itself) is one line naming ``where``."""
    try:
        value = int(str(text).strip())
    except ValueError:
        value = 0
    if not 1 <= value <= 4 * cores:
        raise SeqvprError(f"{where} must be a whole number of threads from 1 to {4 * cores} (4 x the {cores} usable "
                          f"cores), got {text!r}")
    return value


def choose_policy(requested: int | None = None) -> ThreadPolicy:
    """The policy in force for this run: ``requested`` (``--threads``), else ``$SEQVPR_THREADS``, else
    ``$OMP_NUM_THREADS``, else the free cores measured now."""
    cores = usable_cores()
    if requested is not None:
        return ThreadPolicy(parse_threads(str(requested), "--threads", cores), "--threads", cores)
    for variable in (ENV, "OMP_NUM_THREADS"):
        value = os.environ.get(variable, "").strip()
        if value and not (variable == "OMP_NUM_THREADS" and value == _exported):
            return ThreadPolicy(parse_threads(value, variable, cores), variable, cores)
    busy = busy_cores()
    return ThreadPolicy(free_cores(cores, busy), "free cores", cores, busy)


def apply_policy(policy: ThreadPolicy) -> ThreadPolicy:
    """Give every pool ``policy.threads``: the libraries already imported directly, the others through the
    environment they read when they start (so child processes inherit it too). Returns the policy."""
    global _applied, _exported
    count = _exported = str(policy.threads)
    for variable in POOL_VARIABLES:
        os.environ[variable] = count
    if "numba" not in sys.modules:  # numba fixes its pool size at import; changing it later is an error there
        os.environ["NUMBA_NUM_THREADS"] = count
    _applied = policy
    reassert()
    return policy


def reassert() -> None:
    """Set the applied count again in every imported pool: after numba's first OpenMP launch, which sets the
    OpenMP thread count torch also reads, or after code that changed a count."""
    if _applied is None:
        return
    n = _applied.threads
    if "numba" in sys.modules:  # first: setting numba's count launches its pool, which may reset OpenMP's
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    if "faiss" in sys.modules:
        import faiss

        faiss.omp_set_num_threads(n)
    if "torch" in sys.modules:
        import torch

        if torch.get_num_threads() != n:
            torch.set_num_threads(n)


def ensure_policy() -> ThreadPolicy:
    """The policy in force, choosing and applying the default once if nothing has (the Python entry points call
    this; a later call re-asserts the counts without measuring again)."""
    if _applied is None:
        return apply_policy(choose_policy())
    reassert()
    return _applied


def use_threads(threads: int | None) -> ThreadPolicy:
    """Choose the policy (``threads``, else the environment or the free cores) and apply it: the CLI's
    ``--threads`` and a Python user's one call."""
    return apply_policy(choose_policy(threads))


def current_policy() -> ThreadPolicy | None:
    """The policy applied in this process, if any."""
    return _applied


def pool_counts() -> dict[str, int]:
    """The thread counts the imported pools report now (for ``seqvpr doctor`` and tests)."""
    counts = {}
    if "torch" in sys.modules:
        counts["torch"] = sys.modules["torch"].get_num_threads()
    if "numba" in sys.modules:
        counts["numba"] = sys.modules["numba"].get_num_threads()
    if "faiss" in sys.modules:
        counts["faiss"] = sys.modules["faiss"].omp_get_max_threads()
    return counts
