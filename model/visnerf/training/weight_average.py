"""An exponential moving average of a model's parameters over the last part of a run.

A step of Adam on a batch of a few thousand rays moves every factor it touches by about the
learning rate, in a direction that is partly the batch's noise; the average of the last few
thousand steps keeps their common direction and cancels most of the noise. Training goes on with
the live parameters; the average replaces them once, at the end (``WeightAverage.copy_into``).

The horizon is a span of run progress, not of steps, so a slower machine averages over the same
share of the run: each update keeps ``exp(-progress made since the last update / span)`` of the
average. The average restarts whenever the parameters' shapes change (a grid upsampled or a box
shrunk after it began).
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn


@dataclass
class WeightAverage:
    """Moving average ``average[i]`` of ``live[i]`` (same shapes), as of progress ``progress``."""

    span: float
    """Progress over which the weight of an old value falls by a factor of e (above 0)."""
    live: list[Tensor]
    average: list[Tensor]
    progress: float

    @classmethod
    def start(cls, model: nn.Module, span: float, progress: float) -> "WeightAverage":
        """An average that begins as a copy of ``model``'s parameters at ``progress``."""
        if not (math.isfinite(span) and span > 0.0):
            raise ValueError(f"weight average span must be a finite progress fraction above 0, got {span}")
        live = [p for p in model.parameters()]
        with torch.no_grad():
            average = [p.detach().clone() for p in live]
        return cls(span, live, average, progress)

    def follows(self, model: nn.Module) -> bool:
        """Whether ``model``'s parameters are still the tensors this average follows (an upsample or
        a box shrink replaces them)."""
        now = list(model.parameters())
        return len(now) == len(self.live) and all(a is b for a, b in zip(now, self.live, strict=True))

    def keep_fraction(self, progress: float) -> float:
        """Share of the average kept by an update at ``progress``: ``exp(-(progress - last) / span)``
        (1 if progress has not advanced)."""
        return math.exp(-max(0.0, progress - self.progress) / self.span)

    @torch.no_grad()
    def update(self, progress: float) -> None:
        """``average <- keep * average + (1 - keep) * live`` for the progress made since the last update."""
        keep = self.keep_fraction(progress)
        if keep < 1.0:
            torch._foreach_lerp_(self.average, [p.detach() for p in self.live], 1.0 - keep)
        self.progress = max(self.progress, progress)

    @torch.no_grad()
    def copy_into(self, model: nn.Module) -> None:
        """Replace ``model``'s parameters by the average (they must be the ones it follows)."""
        if not self.follows(model):
            raise ValueError("the model's parameters changed since the average began; it cannot replace them")
        for a in self.average:
            if not bool(torch.isfinite(a).all()):
                raise FloatingPointError("the weight average holds a non-finite value; the live parameters are kept")
        for p, a in zip(self.live, self.average, strict=True):
            p.copy_(a)
