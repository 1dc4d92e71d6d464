"""Occupancy grids for single parameter settings, cached by the parameter tuple (inference).

A checkpoint's occupancy grid is the union over its parameter space: a cell counts when it holds
content at any setting. At one setting, part of that union is empty (on ``tangle_iso``, the
surfaces of the other isovalues), and a frame still walks it. ``SettingOccupancy`` narrows the
union to the cells visible at one setting, ``build_occupancy`` evaluated only on the union's
cells and intersected with it, so it never holds a cell the union lacks, and keeps the grids of
the last ``capacity`` tuples.

A grid is built only for a tuple that asks ``build_after`` times: a parameter path (a slider
being dragged, a test path) asks once per tuple and never pays for a build it cannot amortise;
orbiting at one setting builds once, from the second frame on. With ``background`` the build runs
on a worker thread (one at a time) and the frames go on with the union grid until it is ready, so
no frame waits for it. The key is the exact tuple of normalised values (Python floats): two
tuples that differ at all never share a grid. A caller that bounds the work running at once (the
render server's queue) hands ``lookup`` a ``BackgroundRunner`` and the build runs there instead.
"""

import contextlib
import logging
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial

import torch
from jaxtyping import Float
from torch import Tensor

from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import build_occupancy
from visnerf.representation.field import VisNerfField

ParamKey = tuple[float, ...]
BackgroundRunner = Callable[[Callable[[], EmptySpace]], "Future[EmptySpace]"]
"""Runs a grid build off the frame's thread and returns its future; raises RuntimeError when it
takes no work now (full or stopping), and the build is asked for again by a later frame."""
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SettingOccupancyConfig:
    capacity: int = 8
    """Grids kept (least recently used dropped first); 0 turns the cache off."""
    build_after: int = 2
    """Requests of one tuple before its grid is built (1: at once)."""
    threshold: float = 1e-4
    """Alpha over one marching step above which a cell counts as occupied."""
    samples_per_axis: int = 2
    """Density samples per cell and axis (as the union grid is built: structure thinner than a
    cell between two cell centres is still seen)."""
    background: bool = True
    """Build on a worker thread and use the grid once it is ready (False: build in ``lookup``)."""

    def __post_init__(self) -> None:
        if self.capacity < 0 or self.build_after < 1 or self.samples_per_axis < 1:
            raise ValueError(f"capacity must be >= 0, build_after and samples_per_axis >= 1, got "
                             f"{self.capacity}, {self.build_after}, {self.samples_per_axis}")


def param_key(params: Float[Tensor, " k"]) -> ParamKey:
    """The exact cache key of normalised parameters."""
    return tuple(float(v) for v in params.detach().cpu().double().tolist())


@torch.no_grad()
def build_setting_grid(
    field: VisNerfField, params: Float[Tensor, " k"], step: float, threshold: float, samples_per_axis: int = 2
) -> Tensor:
    """The field's union grid narrowed to the cells whose alpha over ``step`` exceeds
    ``threshold`` at ``params`` (dilated by one cell, then intersected with the union)."""
    union = field.occupancy
    if union is None:
        raise ValueError("the field has no occupancy grid to narrow")
    own = build_occupancy(field, tuple(union.shape), params[None].to(field.aabb), step, threshold,  # type: ignore[arg-type]
                          candidates=union, samples_per_axis=samples_per_axis)
    return own & union


class SettingOccupancy:
    """LRU of ``EmptySpace`` per parameter tuple for one field. ``lookup`` is not thread safe:
    call it under the scene's render lock (a background build only reads the field)."""

    def __init__(self, field: VisNerfField, cfg: SettingOccupancyConfig) -> None:
        self.field, self.cfg = field, cfg
        self._grids: OrderedDict[ParamKey, EmptySpace] = OrderedDict()
        self._asked: OrderedDict[ParamKey, int] = OrderedDict()
        self._pending: tuple[ParamKey, Future[EmptySpace]] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self.builds = 0

    def __len__(self) -> int:
        return len(self._grids)

    def build(self, params: Tensor, step: float) -> EmptySpace:
        """The empty space of ``params`` as the cache builds it, not stored (benchmarks time it)."""
        with torch.inference_mode():
            grid = build_setting_grid(self.field, params, step, self.cfg.threshold, self.cfg.samples_per_axis)
            return EmptySpace.of(grid, self.field.aabb)

    def _store(self, key: ParamKey, space: EmptySpace) -> EmptySpace:
        self.builds += 1
        self._grids[key] = space
        while len(self._grids) > self.cfg.capacity:
            self._grids.popitem(last=False)
        return space

    def _collect(self) -> None:
        """Store the background build if it has finished (a failed build is logged and dropped:
        the union grid keeps serving that tuple)."""
        if self._pending is None or not self._pending[1].done():
            return
        key, future = self._pending
        self._pending = None
        if future.cancelled():  # dropped by its runner (a server stopping): the union serves
            return
        try:
            self._store(key, future.result())
        except Exception:  # noqa: BLE001 - the union grid is always a correct fallback
            log.exception("building the occupancy grid of parameters %s failed", key)

    def wait(self) -> None:
        """Block until a background build has finished and is stored (tests, benchmarks)."""
        if self._pending is not None:
            with contextlib.suppress(CancelledError):  # dropped by its runner: nothing to wait for
                self._pending[1].exception()
            self._collect()

    def lookup(
        self, params: Float[Tensor, " k"], step: float, background: BackgroundRunner | None = None
    ) -> EmptySpace | None:
        """The empty space of ``params``, or None (use the union) while the tuple has asked fewer
        than ``build_after`` times or its grid is being built, when the cache is off, or when the
        field has no grid. A background build runs on ``background`` when given, else on this
        cache's own worker thread."""
        if self.cfg.capacity == 0 or self.field.occupancy is None:
            return None
        self._collect()
        key = param_key(params)
        hit = self._grids.get(key)
        if hit is not None:
            self._grids.move_to_end(key)
            return hit
        if self._pending is not None and self._pending[0] == key:
            return None
        asked = self._asked.pop(key, 0) + 1
        if asked < self.cfg.build_after:
            self._asked[key] = asked
            while len(self._asked) > 4 * self.cfg.capacity:
                self._asked.popitem(last=False)
            return None
        if not self.cfg.background:
            return self._store(key, self.build(params, step))
        if self._pending is None:  # one build at a time; a busy worker leaves this tuple for later
            build = partial(self.build, params.detach().clone(), step)
            try:
                self._pending = (key, background(build) if background is not None else self._own_pool().submit(build))
            except RuntimeError:  # the runner takes no work now: a later frame asks again
                self._asked[key] = asked
        else:
            self._asked[key] = asked
        return None

    def _own_pool(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="occupancy")
        return self._pool
