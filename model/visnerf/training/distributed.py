"""Training one model on several processes (``torchrun``, Slurm's ``srun``): torch.distributed.

Every rank holds the whole field and optimizer. A step's global batch of ``batch_rays`` rays is
shared out: each rank draws its share from its own random stream, back-propagates the squared
error of its rays divided by ``batch_rays / world_size``, and the ranks then average their
gradients (one all-reduce of one flat buffer): the average is the gradient of the mean over the
global batch, so every rank takes the same optimizer step, as one process with the whole batch
would. What the schedule reads stays in step too: rank 0's training clock (a time budget's
progress, learning-rate decay, milestones) and any rank's stop request are agreed before each
step, and after a milestone (upsampling, box shrink, occupancy grid) rank 0's field is broadcast,
so the ranks never differ in step count or in the field's shape. Rank 0 alone validates and
writes files.

One process (no ``WORLD_SIZE``, or 1) starts no process group: ``Ranks.solo`` does nothing.
The backend follows the device: gloo on CPU, nccl on CUDA.
"""

import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import timedelta
from typing import TypeVar

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from visnerf.runtime import available_cores, configure

DEFAULT_PORT = 29500
"""``MASTER_PORT`` where the launcher sets none (srun does not): torchrun's default."""
T = TypeVar("T")
BACKENDS = {"cpu": "gloo", "cuda": "nccl"}
"""torch.distributed backend for each device type."""
TIMEOUT = timedelta(minutes=30)
"""How long a rank waits in a collective (rank 0 validates while the others wait)."""


@dataclass(frozen=True)
class Launch:
    """Where this process stands among the processes a launcher started."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    """Rank among the processes on this node (the CUDA device index)."""
    local_world_size: int = 1
    """Processes on this node that share its CPU cores (1 where the launcher binds each its own)."""
    master_addr: str = "127.0.0.1"
    master_port: int = DEFAULT_PORT
    launcher: str = "none"
    """``torchrun`` (or any launcher that sets ``RANK`` and ``WORLD_SIZE``), ``srun``, ``none``."""

    def __post_init__(self) -> None:
        if not 0 <= self.rank < self.world_size:
            raise ValueError(f"rank {self.rank} is not among {self.world_size} processes")

    @classmethod
    def from_environment(cls, env: Mapping[str, str] | None = None) -> "Launch":
        """The launch that ``env`` (default: this process's environment) describes.

        torchrun sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``, ``MASTER_ADDR``
        and ``MASTER_PORT``. srun sets ``SLURM_PROCID``, ``SLURM_STEP_NUM_TASKS`` and
        ``SLURM_LOCALID`` (only inside a job step: a batch script's own process, which has
        ``SLURM_NTASKS`` too, trains alone); the job script exports ``MASTER_ADDR`` (the first
        node's name) and may set ``MASTER_PORT``. Slurm binds each task to its own cores, so
        ``local_world_size`` is 1 there.
        """
        env = os.environ if env is None else env
        master = {"master_addr": env.get("MASTER_ADDR", "127.0.0.1"),
                  "master_port": int(env.get("MASTER_PORT", DEFAULT_PORT))}
        if "WORLD_SIZE" in env and int(env["WORLD_SIZE"]) > 1:
            return cls(int(env.get("RANK", 0)), int(env["WORLD_SIZE"]), int(env.get("LOCAL_RANK", 0)),
                       int(env.get("LOCAL_WORLD_SIZE", 1)), launcher="torchrun", **master)  # type: ignore[arg-type]
        if "SLURM_STEP_NUM_TASKS" in env and int(env["SLURM_STEP_NUM_TASKS"]) > 1:
            if "MASTER_ADDR" not in env:
                raise ValueError("srun started several tasks but MASTER_ADDR is not set: export the first node's "
                                 "name in the job script, e.g. MASTER_ADDR=$(scontrol show hostnames "
                                 "\"$SLURM_JOB_NODELIST\" | head -n 1)")
            return cls(int(env["SLURM_PROCID"]), int(env["SLURM_STEP_NUM_TASKS"]), int(env.get("SLURM_LOCALID", 0)),
                       1, launcher="srun", **master)  # type: ignore[arg-type]
        return cls()

    def device_for(self, device: torch.device) -> torch.device:
        """``device`` for this rank: a CUDA device without an index becomes this node's
        ``local_rank``-th visible one (modulo the count, for launchers that show each task one)."""
        if device.type == "cuda" and device.index is None and self.world_size > 1:
            return torch.device("cuda", self.local_rank % max(1, torch.cuda.device_count()))
        return device


class Ranks:
    """The processes training one model together, as this rank sees them (``Ranks.start``)."""

    def __init__(self, launch: Launch, device: torch.device) -> None:
        self.launch, self.device = launch, device

    @classmethod
    def solo(cls, device: torch.device) -> "Ranks":
        """One process alone: every method does nothing (or the one-process thing)."""
        return cls(Launch(), device)

    @classmethod
    def start(cls, launch: Launch, device: torch.device) -> "Ranks":
        """Join the process group ``launch`` describes on ``device`` (see ``Launch.device_for``);
        a one-process launch starts none. On CPU, ranks that share a node's cores get an equal
        share of them unless ``VISNERF_THREADS`` says otherwise (torchrun's own ``OMP_NUM_THREADS=1``
        for each of several ranks would leave most cores of a larger node idle)."""
        device = launch.device_for(device)
        if launch.world_size == 1:
            return cls(launch, device)
        if device.type not in BACKENDS:
            raise ValueError(f"no torch.distributed backend for device {device} (one of {sorted(BACKENDS)})")
        if device.type == "cuda":
            torch.cuda.set_device(device)
        elif "VISNERF_THREADS" not in os.environ and launch.local_world_size > 1:
            configure(max(1, available_cores() // launch.local_world_size))
        os.environ.setdefault("MASTER_ADDR", launch.master_addr)
        os.environ.setdefault("MASTER_PORT", str(launch.master_port))
        dist.init_process_group(BACKENDS[device.type], init_method="env://", rank=launch.rank,
                                world_size=launch.world_size, timeout=TIMEOUT)
        return cls(launch, device)

    @property
    def rank(self) -> int:
        return self.launch.rank

    @property
    def world_size(self) -> int:
        return self.launch.world_size

    @property
    def is_main(self) -> bool:
        """Rank 0: validates, writes the checkpoint, run state and log, and submits."""
        return self.launch.rank == 0

    def provenance(self) -> dict[str, object]:
        """What a checkpoint records of the ranks (nothing for one process)."""
        if self.world_size == 1:
            return {}
        return {"ranks": self.world_size, "backend": BACKENDS[self.device.type], "launcher": self.launch.launcher}

    def batch_share(self, batch_rays: int) -> tuple[int, float]:
        """(rays this rank draws, the divisor of their squared-error sum) for a global batch of
        ``batch_rays``: shares differ by at most one ray and add up to ``batch_rays``; the divisor
        ``batch_rays / world_size`` makes the ranks' averaged gradient that of the global mean."""
        base, extra = divmod(batch_rays, self.world_size)
        return base + int(self.rank < extra), batch_rays / self.world_size

    def stream_seed(self, seed: int, iteration: int) -> int:
        """The seed of this rank's random stream (rays, backgrounds, jitter) from ``iteration`` on:
        one per (seed, rank, iteration), so ranks draw different rays and a resumed run new ones."""
        return int(np.random.SeedSequence((seed, self.rank, iteration)).generate_state(1, np.uint64)[0])

    def agree(self, train_seconds: float, stop_requested: bool) -> tuple[float, bool]:
        """(rank 0's training seconds, whether any rank was asked to stop), the same on every rank."""
        if self.world_size == 1:
            return train_seconds, stop_requested
        values = torch.tensor([train_seconds if self.is_main else 0.0, float(stop_requested)],
                              dtype=torch.float64, device=self.device)
        dist.all_reduce(values)
        return float(values[0]), bool(values[1] > 0)

    @torch.no_grad()
    def merge_row_marks(self, marks: list[np.ndarray]) -> None:
        """Set each row mark (``vm_rows.RowGradients``) that any rank set, on every rank: a row one
        rank's samples touched holds the averaged gradient on all of them. One all-reduce."""
        if self.world_size == 1 or not marks:
            return
        flat = torch.from_numpy(np.concatenate(marks)).to(device=self.device, dtype=torch.float32)
        dist.all_reduce(flat)
        merged = (flat > 0).to(torch.uint8).cpu().numpy()
        start = 0
        for m in marks:
            m[:] = merged[start:start + m.shape[0]]
            start += m.shape[0]

    @torch.no_grad()
    def average_gradients(self, params: Iterable[nn.Parameter], *values: float) -> tuple[float, ...]:
        """Replace each parameter's gradient by its mean over the ranks, and return the means of
        ``values`` (a batch statistic, say). A gradient that no rank has stays None; one that
        only some ranks have counts as zero on the others. One all-reduce of one float32 buffer."""
        if self.world_size == 1:
            return values
        params = list(params)
        parts = [p.grad.reshape(-1).float() if p.grad is not None else torch.zeros(p.numel(), device=self.device)
                 for p in params]
        present = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=self.device)
        extra = torch.tensor(values, dtype=torch.float32, device=self.device)
        flat = torch.cat([*parts, present, extra])  # [gradient entries + n_params + len(values)]
        dist.all_reduce(flat)
        flat /= self.world_size
        sizes = [p.numel() for p in params]
        grads = flat[: sum(sizes)].split(sizes)
        anyone = flat[sum(sizes) : sum(sizes) + len(params)] > 0
        for p, g, has in zip(params, grads, anyone.tolist(), strict=True):
            if not has:
                p.grad = None
            elif p.grad is None:
                p.grad = g.view_as(p).to(p.dtype).clone()
            else:
                p.grad.copy_(g.view_as(p))
        return tuple(float(v) for v in flat[sum(sizes) + len(params) :])

    @torch.no_grad()
    def broadcast_field(self, field: nn.Module) -> None:
        """Overwrite ``field``'s parameters and buffers (occupancy grid included) in place with rank
        0's. Ranks whose fields differ in a tensor's name or shape (a resolution, an occupancy
        grid) have gone apart: a RuntimeError rather than a broadcast of tensors that do not match."""
        if self.world_size == 1:
            return
        state = field.state_dict()
        describe = tuple((name, tuple(t.shape)) for name, t in state.items())
        theirs: list[object] = [describe]
        dist.broadcast_object_list(theirs, src=0, device=self.device if self.device.type == "cuda" else None)
        if theirs[0] != describe:
            raise RuntimeError(f"rank {self.rank}'s field ({describe}) is not rank 0's ({theirs[0]}): "
                               "the ranks' schedules went apart")
        for tensor in state.values():
            if tensor.dtype == torch.bool:  # not every backend broadcasts bool
                carrier = tensor.to(torch.uint8)
                dist.broadcast(carrier, src=0)
                tensor.copy_(carrier.bool())
            else:
                dist.broadcast(tensor, src=0)


def run_then_leave(run: "Callable[[], T]") -> "T":
    """``run()``, then leave the process group (``leave_process_group``): together when it returned,
    alone when it raised."""
    try:
        result = run()
    except BaseException:
        leave_process_group()
        raise
    leave_process_group(together=True)
    return result


def leave_process_group(together: bool = False) -> None:
    """Leave this process's process group, if it joined one (``Ranks.start``). ``together``: wait at
    a barrier first, so that every rank leaves at once. A rank that left while rank 0 still wrote
    its checkpoint aborted now and then in gloo's teardown ("terminate called without an active
    exception", 1 of 12 two-rank runs on a loaded machine), and torchrun then stopped rank 0. A
    rank that fails leaves alone: the others may never reach the barrier."""
    if not (dist.is_available() and dist.is_initialized()):
        return
    if together:
        dist.barrier()
    dist.destroy_process_group()
