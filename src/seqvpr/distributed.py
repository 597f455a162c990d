"""torch.distributed under ``torchrun``: the rank and world size torchrun sets, one process group for a command,
and a gather that fails every rank with the failing rank's error (so no rank waits forever and none writes output).

Run without torchrun, the world is one process and nothing here touches torch.distributed.

A rank waits at most ``$SEQVPR_RANK_TIMEOUT`` seconds (default 300) for the others, to join the group and at each
collective: a rank started alone, or left alone, ends with one line. SIGTERM ends a rank waiting on the others at
once (a wait inside torch.distributed does not return to Python, where the CLI's handler would run).
"""

from __future__ import annotations

import atexit
import contextlib
import datetime
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

from seqvpr.errors import SeqvprError, SettingError

T = TypeVar("T")

TIMEOUT_VARIABLE = "SEQVPR_RANK_TIMEOUT"
DEFAULT_TIMEOUT_S = 300.0
MAX_TIMEOUT_S = 86_400.0  # a day: past that a wait is a hang


@dataclass(frozen=True)
class Ranks:
    """This process's place among the ranks of a run: rank, how many there are, and its rank on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def is_root(self) -> bool:
        return self.rank == 0


_current = Ranks()


def from_environment() -> Ranks:
    """The world torchrun describes in ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` (one process when unset)."""
    try:
        world = Ranks(int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)),
                      int(os.environ.get("LOCAL_RANK", 0)))
    except ValueError:
        raise SeqvprError("RANK, WORLD_SIZE and LOCAL_RANK must be whole numbers (torchrun sets them)") from None
    if world.size < 1 or not 0 <= world.rank < world.size:
        raise SeqvprError(f"rank {world.rank} is not one of WORLD_SIZE={world.size} ranks")
    return world


def current() -> Ranks:
    """The world of the running command (one process outside ``process_group``)."""
    return _current


@contextlib.contextmanager
def process_group(device: str = "cpu") -> Iterator[Ranks]:
    """Be in torchrun's process group for the duration (gloo on CPU, NCCL on CUDA). The group is joined once per
    process and left when the process exits: a second command or training run in the same process reuses it, as a
    group torn down and joined again on the same port can wait forever for its rendezvous."""
    global _current
    world = from_environment()
    if world.size == 1:
        yield world
        return
    import torch.distributed as dist

    if not dist.is_initialized():
        if str(device).startswith("cuda"):
            import torch

            torch.cuda.set_device(world.local_rank)
        timeout = rank_timeout()
        end_waits_on_sigterm()
        try:
            dist.init_process_group("nccl" if str(device).startswith("cuda") else "gloo",
                                    timeout=datetime.timedelta(seconds=timeout))
        except RuntimeError as error:  # torch's store and network errors: the other ranks never came
            raise SeqvprError(f"rank {world.rank} of {world.size}: the other ranks did not join within {timeout:g} s "
                              f"(${TIMEOUT_VARIABLE}; {str(error).splitlines()[0][:120]})") from None
        atexit.register(_leave)
    _current = world
    yield world


def rank_timeout() -> float:
    """Seconds a rank waits for the others (``$SEQVPR_RANK_TIMEOUT``, default 300); a bad value is one line."""
    text = os.environ.get(TIMEOUT_VARIABLE, "").strip()
    if not text:
        return DEFAULT_TIMEOUT_S
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not 0 < seconds <= MAX_TIMEOUT_S:  # False for NaN
        raise SeqvprError(f"${TIMEOUT_VARIABLE}={text!r}: expected seconds in (0, {MAX_TIMEOUT_S:g}]")
    return seconds


_sigterm_watch: threading.Thread | None = None
#: set by whoever reports a SIGTERM itself (the CLI), so the watch adds no second line
sigterm_reported = threading.Event()
SIGTERM_GRACE_S = 2.0


def end_waits_on_sigterm() -> None:
    """Watch for SIGTERM beside the main thread (through Python's signal wake-up fd): where the main thread has not
    ended the process ``SIGTERM_GRACE_S`` after it (stuck in a wait on other ranks), one line and exit 143. Only
    where a Python handler takes SIGTERM (the CLI's); without one SIGTERM ends the process anyway."""
    global _sigterm_watch
    if _sigterm_watch is not None or threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, signal.SIG_IGN, None):
        return
    reader, writer = socket.socketpair()
    writer.setblocking(False)
    try:
        signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    except ValueError:  # not the main thread of the main interpreter
        return
    _sigterm_watch = threading.Thread(target=_watch_sigterm, args=(reader, writer), daemon=True,
                                      name="seqvpr-sigterm")
    _sigterm_watch.start()


def _watch_sigterm(reader: socket.socket, writer: socket.socket) -> None:
    """Wait for SIGTERM's byte on the wake-up fd; then, unless the process ends or reports it first, end it."""
    while reader.recv(1) != bytes([signal.SIGTERM]):
        pass
    if not sigterm_reported.wait(SIGTERM_GRACE_S):
        os.write(2, b"seqvpr: terminated (SIGTERM) while waiting for the other ranks\n")
        os._exit(143)


def _leave() -> None:
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


def everywhere(work: Callable[[], T], world: Ranks | None = None) -> T:
    """Every rank's own ``work()``; if it raises on any rank, every rank raises one line naming the first that
    failed, once all have finished theirs (a sync point: no rank goes on before all have done this)."""
    world = world or current()
    if world.size == 1:
        return work()
    import torch.distributed as dist

    value, error = None, None
    try:
        value = work()
    except Exception as failure:  # reported to every rank below, then raised on each
        error = failure_text(failure)
    errors: list[str | None] = [None] * world.size
    _wait(dist.all_gather_object, world, errors, error)
    failed = [(rank, text) for rank, text in enumerate(errors) if text is not None]
    if failed:
        rank, text = failed[0]
        raise SettingError(f"rank {rank} of {world.size} failed: {text}")
    return value  # type: ignore[return-value]


def failure_text(failure: BaseException) -> str:
    """What a rank's failure sends the others: a SettingError's template (so each rank's message names settings as
    its caller does), another error's message, or an unexpected one's type and message."""
    if isinstance(failure, SettingError):
        return failure.template
    return str(failure) if isinstance(failure, SeqvprError) else f"{type(failure).__name__}: {failure}"


def gather_to_root(work: Callable[[], T], world: Ranks | None = None) -> list[T] | None:
    """Every rank's ``work()``, gathered on rank 0 in rank order (other ranks get None). A rank whose work raises
    makes every rank raise one line naming it, after all have finished theirs."""
    world = world or current()
    if world.size == 1:
        return [work()]
    import torch.distributed as dist

    value = everywhere(work, world)
    values: list[T] | None = [None] * world.size if world.is_root else None  # type: ignore[list-item]
    _wait(dist.gather_object, world, value, values, dst=0)
    return values


def gather_everywhere(work: Callable[[], T], world: Ranks | None = None) -> list[T]:
    """Every rank's ``work()``, in rank order, on every rank; a rank whose work raises makes every rank raise one
    line naming it."""
    world = world or current()
    if world.size == 1:
        return [work()]
    import torch.distributed as dist

    value = everywhere(work, world)
    values: list = [None] * world.size
    _wait(dist.all_gather_object, world, values, value)
    return values


def broadcast_from_root(work: Callable[[], T], world: Ranks | None = None) -> T:
    """Rank 0's ``work()`` on every rank (the others do not run it); if it raises, every rank raises one line."""
    world = world or current()
    if world.size == 1:
        return work()
    import torch.distributed as dist

    message: list = [None, None]
    if world.is_root:
        try:
            message = [work(), None]
        except Exception as failure:  # sent to every rank below, then raised on each
            message = [None, failure_text(failure)]
    _wait(dist.broadcast_object_list, world, message, src=0)
    if message[1] is not None:
        raise SettingError(f"rank 0 of {world.size} failed: {message[1]}")
    return message[0]


def sum_over_ranks(values: list[float], world: Ranks | None = None) -> list[float]:
    """Each value summed over the ranks (float64)."""
    world = world or current()
    if world.size == 1:
        return list(values)
    import torch
    import torch.distributed as dist

    total = torch.tensor(values, dtype=torch.float64)
    _wait(dist.all_reduce, world, total)
    return total.tolist()


def barrier(world: Ranks | None = None) -> None:
    """Wait until every rank is here."""
    world = world or current()
    if world.size > 1:
        import torch.distributed as dist

        _wait(dist.barrier, world)


def _wait(collective: Callable, world: Ranks, *args, **kwargs) -> None:
    """Run a collective; a rank that times out waiting (``$SEQVPR_RANK_TIMEOUT``) or loses the others is one line."""
    try:
        collective(*args, **kwargs)
    except RuntimeError as error:
        raise SeqvprError(f"rank {world.rank} of {world.size}: waiting for the other ranks failed (a rank stopped, or "
                          f"none answered within ${TIMEOUT_VARIABLE} s: {str(error).splitlines()[0][:120]})") from None
