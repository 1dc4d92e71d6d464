"""Occupancy grids for single parameter settings, cached by the parameter tuple (inference).

A checkpoint's occupancy grid is the union over its parameter space: a cell counts when it holds
content at any setting. At one setting, part of that union is empty (on ``tangle_iso``, the
surfaces of the other isovalues), and a frame still walks it. ``SettingOccupancy`` narrows the
union to the cells visible at one setting, ``build_occupancy`` evaluated only on the union's
cells and intersected with it, so it never holds a cell the union lacks, and keeps the grids of
the last ``FramesConfig.setting_grids`` tuples.

A grid is built only for a tuple that asks ``FramesConfig.setting_grid_after`` times: a parameter path (a slider
being dragged, a test path) asks once per tuple and never pays for a build it cannot amortise;
orbiting at one setting builds once, after a few frames. One build runs at a time, and the
frames go on with the union grid until it is stored, so no frame waits for it. The key is the
exact tuple of normalised values (Python floats): two tuples that differ at all never share a grid.

``lookup`` answers the grid to march now and, when one is due, a ``GridBuild`` that its caller
runs where it bounds its work (the render server's background lane), or hands to ``run_own``: on
this cache's worker thread or at once.
"""

import logging
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from visnerf.config import FramesConfig
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import build_occupancy
from visnerf.representation.field import VisNerfField

ParamKey = tuple[float, ...]
log = logging.getLogger(__name__)


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


@dataclass(eq=False)
class GridBuild:
    """The build of one tuple's grid that a lookup found due: ``run`` it (any thread; it stores the
    grid), or ``drop`` it where nothing will run it (the tuple is asked for again by a later frame).
    A failed build is logged and dropped: the union grid keeps serving that tuple."""

    cache: "SettingOccupancy"
    key: ParamKey
    params: Tensor
    step: float

    def run(self) -> None:
        try:
            space = self.cache.build(self.params, self.step)
        except Exception:  # the union grid is always a correct fallback
            log.exception("building the occupancy grid of parameters %s failed", self.key)
            space = None
        self.cache._finish(self, space)

    def drop(self) -> None:
        """Nothing will run it (a queue that takes no work now): the tuple's next frame asks again."""
        self.cache._finish(self, None, ask_again=True)


class SettingOccupancy:
    """LRU of ``EmptySpace`` per parameter tuple for one field; thread safe (a build only reads the
    field). ``cfg``: how many grids, after how many asks, sampled how finely (``FramesConfig``);
    ``threshold``: the alpha over one marching step above which a cell counts as occupied (the
    checkpoint's ``RenderConfig.occupancy_threshold``); ``background``: ``run_own`` builds on a
    worker thread and the frame marches the union meanwhile (False: at once)."""

    def __init__(self, field: VisNerfField, cfg: FramesConfig, threshold: float, background: bool = True) -> None:
        self.field, self.cfg, self.threshold, self.background = field, cfg, threshold, background
        self._grids: OrderedDict[ParamKey, EmptySpace] = OrderedDict()
        self._asked: OrderedDict[ParamKey, int] = OrderedDict()
        self._pending: GridBuild | None = None
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._pool: ThreadPoolExecutor | None = None
        self.builds = 0

    def __len__(self) -> int:
        return len(self._grids)

    def build(self, params: Tensor, step: float) -> EmptySpace:
        """The empty space of ``params`` as the cache builds it, not stored (benchmarks time it)."""
        with torch.inference_mode():
            grid = build_setting_grid(self.field, params, step, self.threshold, self.cfg.setting_grid_samples)
            return EmptySpace.of(grid, self.field.aabb)

    def _finish(self, build: GridBuild, space: EmptySpace | None, ask_again: bool = False) -> None:
        """End ``build``: store its grid (None: nothing to store) and free the one build slot;
        ``ask_again``: the tuple's next ask hands out a new build."""
        with self._lock:
            if self._pending is not build:
                return
            self._pending = None
            if ask_again and self.cfg.setting_grid_after > 1:
                self._asked[build.key] = self.cfg.setting_grid_after - 1
            if space is not None:
                self.builds += 1
                self._grids[build.key] = space
                while len(self._grids) > self.cfg.setting_grids:
                    self._grids.popitem(last=False)
            self._idle.notify_all()

    def wait(self) -> None:
        """Block until no build is running (tests, benchmarks)."""
        with self._lock:
            self._idle.wait_for(lambda: self._pending is None)

    def lookup(self, params: Float[Tensor, " k"], step: float) -> tuple[EmptySpace | None, GridBuild | None]:
        """(the grid of ``params`` or None: march the union, the build now due or None). No grid
        while the tuple has asked fewer than ``setting_grid_after`` times or its grid is being built, when
        the cache is off, or when the field has no grid; no build while another one runs."""
        if self.cfg.setting_grids == 0 or self.field.occupancy is None:
            return None, None
        key = param_key(params)
        with self._lock:
            hit = self._grids.get(key)
            if hit is not None:
                self._grids.move_to_end(key)
                return hit, None
            if self._pending is not None and self._pending.key == key:
                return None, None
            asked = self._asked.pop(key, 0) + 1
            if asked < self.cfg.setting_grid_after or self._pending is not None:
                self._asked[key] = asked
                while len(self._asked) > 4 * self.cfg.setting_grids:
                    self._asked.popitem(last=False)
                return None, None
            self._pending = GridBuild(self, key, params.detach().clone(), step)
            return None, self._pending

    def run_own(self, build: GridBuild) -> EmptySpace | None:
        """Run a due build here: on this cache's worker thread (``background``; None: the frame
        marches the union meanwhile), or at once, returning the grid it stored."""
        if self.background:
            self._own_pool().submit(build.run)
            return None
        build.run()
        with self._lock:
            return self._grids.get(build.key)

    def _own_pool(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="occupancy")
        return self._pool
