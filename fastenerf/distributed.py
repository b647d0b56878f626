"""Several processes, one per GPU (or CPU rank), through torch.distributed: who am I, my share.

The engine is `torchrun` (torch.distributed's launcher): it starts one process per rank and
sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; this module reads them. There
is no scheduler of ours: ranks meet at torch.distributed's rendezvous, each takes its share of
a job list (`my_share`), and they meet again at a barrier, after which rank 0 collects.

    torchrun --standalone --nproc-per-node 4 -m fastenerf.cli train-many A B C --out runs

A fan-out of independent jobs (a study's runs, a dataset's scenes) looks like:

    with process_group(backend="gloo") as world:
        for job in my_share(jobs, world, cost=lambda j: j.seconds):
            results.append(train(job, device=world.device))
        everyone = gather(results, world)       # rank 0: every rank's list; others: None
    if everyone is not None: write_summary(everyone)

Without torchrun (no WORLD_SIZE in the environment) the world is one rank: `my_share` returns
every job and `gather`/`barrier` are no-ops, so the same code runs in one plain process.
Only this module and `fastenerf.data_parallel` talk to torch.distributed.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
import torch.distributed as dist

from .errors import InputError

T = TypeVar("T")

# A fan-out's barrier waits for the slowest rank's whole share (hours for a long study);
# torch's default of 30 minutes would end it with a timeout error, not a result.
FAN_OUT_TIMEOUT_S = 7 * 24 * 3600.0


@dataclass(frozen=True)
class World:
    """This process's place among the ranks.

    rank: 0..size-1 over all hosts; size: number of ranks; local_rank: index on this host
    (which GPU it uses); distributed: whether a process group is (or will be) up.
    """

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    distributed: bool = False

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that writes shared outputs and prints."""
        return self.rank == 0

    @property
    def device(self) -> torch.device:
        """`cuda:LOCAL_RANK` when CUDA is there, else the CPU."""
        if not torch.cuda.is_available():
            return torch.device("cpu")
        if self.local_rank >= torch.cuda.device_count():
            raise InputError(
                f"LOCAL_RANK {self.local_rank}: this host has {torch.cuda.device_count()} GPU(s); "
                "start at most that many ranks per host (torchrun --nproc-per-node)"
            )
        return torch.device("cuda", self.local_rank)


def world_from_env(env: dict[str, str] | None = None) -> World:
    """The World torchrun describes in RANK / WORLD_SIZE / LOCAL_RANK; one rank without them.

    Raises InputError (one line) for values that are not integers or out of range.
    """
    env = os.environ if env is None else env
    if "WORLD_SIZE" not in env and "RANK" not in env:
        return World()
    try:
        size = int(env.get("WORLD_SIZE", "1"))
        rank = int(env.get("RANK", "0"))
        local = int(env.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise InputError(
            "RANK / WORLD_SIZE / LOCAL_RANK must be integers (start the ranks with torchrun)"
        ) from None
    if size < 1 or not 0 <= rank < size or local < 0:
        raise InputError(f"RANK {rank} / WORLD_SIZE {size}: rank must be in [0, world size)")
    return World(rank, size, local, distributed=size > 1)


_joined: World | None = None  # the World `init` joined the group as
_left = False  # this process destroyed a process group (`left_a_group`)


def current_world() -> World:
    """The World of the process group that is up, else the environment's."""
    if dist.is_available() and dist.is_initialized():
        if _joined is not None:
            return _joined
        return World(dist.get_rank(), dist.get_world_size(), world_from_env().local_rank, True)
    return world_from_env()


def default_backend() -> str:
    """nccl when this process has a GPU, else gloo (CPU tensors)."""
    return "nccl" if torch.cuda.is_available() and dist.is_nccl_available() else "gloo"


def init(
    backend: str | None = None,
    *,
    rank: int | None = None,
    world_size: int | None = None,
    init_method: str | None = None,
    timeout_s: float | None = None,
) -> World:
    """Join the process group (torch.distributed's rendezvous) and return this rank's World.

    backend: "gloo" or "nccl" (None: `default_backend()`); rank, world_size, init_method: for
    processes not started by torchrun (tests: init_method="file:///tmp/x"); by default all
    come from the environment (env://). A world of one rank starts no group. With CUDA the
    process's current device becomes cuda:LOCAL_RANK (NCCL's collectives run there).
    timeout_s: how long a collective may wait for the other ranks (None: torch's default).
    """
    env = world_from_env()
    explicit = rank is not None and world_size is not None
    world = World(rank, world_size, rank, world_size > 1) if explicit else env
    if not world.distributed:
        return world
    if dist.is_initialized():
        return current_world()
    backend = backend or default_backend()
    if backend == "nccl" and torch.cuda.is_available():
        torch.cuda.set_device(world.device)
    kw: dict[str, Any] = {"backend": backend}
    if timeout_s is not None:
        kw["timeout"] = datetime.timedelta(seconds=timeout_s)
    if init_method is not None:
        kw.update(init_method=init_method, rank=world.rank, world_size=world.size)
    dist.init_process_group(**kw)
    global _joined
    _joined = world
    return world


def destroy() -> None:
    """Leave the process group (a no-op when none is up)."""
    global _joined, _left
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
        _left = True
    _joined = None


def left_a_group() -> bool:
    """Whether this process has been in a process group and left it (`destroy`)."""
    return _left


@contextmanager
def process_group(backend: str | None = None, **kw: Any) -> Iterator[World]:
    """`init(...)` for the block, `destroy()` after it (also on an error). After a block that
    ended normally the ranks meet at a barrier first, so no rank tears its group down while
    another still has a message in flight to it (a rank of a CI run once aborted in C++ at
    exit, "terminate called without an active exception", after such a gather)."""
    world = init(backend, **kw)
    try:
        yield world
        barrier()
    finally:
        destroy()


def my_share(
    jobs: Sequence[T],
    world: World | None = None,
    cost: Callable[[T], float] | None = None,
) -> list[T]:
    """The jobs this rank runs, in their order in `jobs`; every job goes to exactly one rank.

    jobs: the same sequence, in the same order, on every rank; world: default the current
    one. Without `cost`: round-robin (job i to rank i mod size). With `cost` (a job's expected
    seconds, any consistent unit): longest job first to the least-loaded rank (ties to the
    lower rank), which keeps the slowest rank within one job of the mean load. Deterministic,
    so every rank computes the same split without talking to the others.
    """
    world = world or current_world()
    costs = None if cost is None else [cost(j) for j in jobs]
    return [jobs[i] for i in share_indices(len(jobs), world.size, costs)[world.rank]]


def share_indices(n: int, size: int, costs: Sequence[float] | None = None) -> list[list[int]]:
    """Job indices (ascending) of each of `size` ranks for `n` jobs (see `my_share`)."""
    if size < 1:
        raise ValueError(f"world size must be >= 1 (got {size})")
    shares: list[list[int]] = [[] for _ in range(size)]
    if costs is None:
        for i in range(n):
            shares[i % size].append(i)
        return shares
    if len(costs) != n:
        raise ValueError(f"{len(costs)} costs for {n} jobs")
    load = [0.0] * size
    for i in sorted(range(n), key=lambda i: (-float(costs[i]), i)):
        r = min(range(size), key=lambda r: (load[r], r))
        shares[r].append(i)
        load[r] += float(costs[i])
    return [sorted(s) for s in shares]


def barrier() -> None:
    """Wait until every rank gets here (a no-op without a process group)."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def gather(obj: Any, world: World | None = None) -> list[Any] | None:
    """Every rank's `obj` (picklable) in rank order on rank 0, None on the others.

    Also a barrier: it returns when every rank has handed its object in. One rank: [obj].
    """
    world = world or current_world()
    if not (dist.is_available() and dist.is_initialized()):
        return [obj]
    out: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out if world.is_main else None
