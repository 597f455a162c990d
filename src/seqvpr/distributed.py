"""torch.distributed under ``torchrun``: the rank and world size torchrun sets, one process group for a command,
and a gather that fails every rank with the failing rank's error (so no rank waits forever and none writes output).

Run without torchrun, the world is one process and nothing here touches torch.distributed.
"""

from __future__ import annotations

import atexit
import contextlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

from seqvpr.errors import SeqvprError

T = TypeVar("T")


@dataclass(frozen=True)
class World:
    """This process's place among the ranks of a run: rank, how many there are, and its rank on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def is_root(self) -> bool:
        return self.rank == 0


_current = World()


def from_environment() -> World:
    """The world torchrun describes in ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` (one process when unset)."""
    try:
        world = World(int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)),
                      int(os.environ.get("LOCAL_RANK", 0)))
    except ValueError:
        raise SeqvprError("RANK, WORLD_SIZE and LOCAL_RANK must be whole numbers (torchrun sets them)") from None
    if world.size < 1 or not 0 <= world.rank < world.size:
        raise SeqvprError(f"rank {world.rank} is not one of WORLD_SIZE={world.size} ranks")
    return world


def current() -> World:
    """The world of the running command (one process outside ``process_group``)."""
    return _current


@contextlib.contextmanager
def process_group(device: str = "cpu") -> Iterator[World]:
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
        dist.init_process_group("nccl" if str(device).startswith("cuda") else "gloo")
        atexit.register(_leave)
    _current = world
    yield world


def _leave() -> None:
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


def everywhere(work: Callable[[], T], world: World | None = None) -> T:
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
        error = str(failure) if isinstance(failure, SeqvprError) else f"{type(failure).__name__}: {failure}"
    errors: list[str | None] = [None] * world.size
    dist.all_gather_object(errors, error)
    failed = [(rank, text) for rank, text in enumerate(errors) if text is not None]
    if failed:
        rank, text = failed[0]
        raise SeqvprError(f"rank {rank} of {world.size} failed: {text}")
    return value  # type: ignore[return-value]


def gather_to_root(work: Callable[[], T], world: World | None = None) -> list[T] | None:
    """Every rank's ``work()``, gathered on rank 0 in rank order (other ranks get None). A rank whose work raises
    makes every rank raise one line naming it, after all have finished theirs."""
    world = world or current()
    if world.size == 1:
        return [work()]
    import torch.distributed as dist

    value = everywhere(work, world)
    values: list[T] | None = [None] * world.size if world.is_root else None  # type: ignore[list-item]
    dist.gather_object(value, values, dst=0)
    return values


def gather_everywhere(work: Callable[[], T], world: World | None = None) -> list[T]:
    """Every rank's ``work()``, in rank order, on every rank; a rank whose work raises makes every rank raise one
    line naming it."""
    world = world or current()
    if world.size == 1:
        return [work()]
    import torch.distributed as dist

    value = everywhere(work, world)
    values: list = [None] * world.size
    dist.all_gather_object(values, value)
    return values


def broadcast_from_root(work: Callable[[], T], world: World | None = None) -> T:
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
            message = [None, str(failure) if isinstance(failure, SeqvprError) else f"{type(failure).__name__}: {failure}"]
    dist.broadcast_object_list(message, src=0)
    if message[1] is not None:
        raise SeqvprError(f"rank 0 of {world.size} failed: {message[1]}")
    return message[0]


def sum_over_ranks(values: list[float], world: World | None = None) -> list[float]:
    """Each value summed over the ranks (float64)."""
    world = world or current()
    if world.size == 1:
        return list(values)
    import torch
    import torch.distributed as dist

    total = torch.tensor(values, dtype=torch.float64)
    dist.all_reduce(total)
    return total.tolist()


def barrier(world: World | None = None) -> None:
    """Wait until every rank is here."""
    world = world or current()
    if world.size > 1:
        import torch.distributed as dist

        dist.barrier()
