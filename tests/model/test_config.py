"""``TrainConfig`` refuses sizes and budgets a run cannot use, naming the field."""

import math

import pytest

from visnerf.config import TrainConfig


@pytest.mark.parametrize(("field", "value"), [
    ("iterations", 0),
    ("batch_rays", 0),
    ("batch_rays", -2048),
    ("micro_batch_rays", 0),
    ("micro_batch_samples", 0),
    ("time_budget_s", 0.0),
    ("time_budget_s", -60.0),
    ("time_budget_s", math.nan),
    ("time_budget_s", math.inf),
])
def test_unusable_sizes_and_budgets_are_refused(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_the_smallest_usable_values_are_accepted() -> None:
    cfg = TrainConfig(iterations=1, batch_rays=1, micro_batch_rays=1, micro_batch_samples=1, time_budget_s=0.5)
    assert (cfg.batch_rays, cfg.time_budget_s) == (1, 0.5)
