"""The parameters' moving average (training/weight_average.py) against its closed form, and the
trainer's use of it: kept from its start fraction, restarted by an upsample, swapped in at the end."""

import math

import pytest
import torch
from torch import nn

from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.trainer import Trainer
from visnerf.training.weight_average import WeightAverage


def _model(value: float) -> nn.Module:
    model = nn.Linear(3, 2)
    with torch.no_grad():
        for p in model.parameters():
            p.fill_(value)
    return model


def test_updates_follow_the_closed_form_of_an_exponential_average() -> None:
    # Live values x_k at progress p_k; the average after the updates is
    # x_0 * prod(keep) + sum_k (1 - keep_k) x_k * prod(keep of later updates), keep_k = exp(-(p_k - p_{k-1}) / span).
    model, span = _model(1.0), 0.1
    avg = WeightAverage.start(model, span, progress=0.5)
    values, progresses = [2.0, -3.0, 5.0], [0.52, 0.53, 0.6]
    for v, p in zip(values, progresses, strict=True):
        with torch.no_grad():
            for t in model.parameters():
                t.fill_(v)
        avg.update(p)
    expected, last = 1.0, 0.5
    for v, p in zip(values, progresses, strict=True):
        keep = math.exp(-(p - last) / span)
        expected, last = keep * expected + (1 - keep) * v, p
    for a in avg.average:
        torch.testing.assert_close(a, torch.full_like(a, expected), rtol=1e-6, atol=1e-6)
    assert avg.progress == 0.6


def test_no_progress_keeps_the_average_and_progress_never_goes_back() -> None:
    model = _model(1.0)
    avg = WeightAverage.start(model, 0.05, progress=0.5)
    with torch.no_grad():
        model.weight.fill_(9.0)
    avg.update(0.5)
    avg.update(0.4)
    assert avg.keep_fraction(0.4) == 1.0
    torch.testing.assert_close(avg.average[0], torch.ones_like(model.weight))
    assert avg.progress == 0.5


def test_copy_into_replaces_the_parameters_and_refuses_other_ones() -> None:
    model = _model(1.0)
    avg = WeightAverage.start(model, 0.1, progress=0.0)
    with torch.no_grad():
        model.weight.fill_(3.0)
    avg.copy_into(model)
    torch.testing.assert_close(model.weight, torch.ones_like(model.weight))
    other = _model(1.0)
    assert not avg.follows(other)
    with pytest.raises(ValueError, match="changed since the average began"):
        avg.copy_into(other)


def test_a_non_finite_average_leaves_the_parameters_unchanged() -> None:
    model = _model(1.0)
    avg = WeightAverage.start(model, 0.1, progress=0.0)
    avg.average[0][0, 0] = float("nan")
    with torch.no_grad():
        model.weight.fill_(4.0)
    with pytest.raises(FloatingPointError, match="non-finite"):
        avg.copy_into(model)
    assert bool((model.weight == 4.0).all())


@pytest.mark.parametrize("span", [0.0, -0.1, float("inf"), float("nan")])
def test_a_span_that_is_not_a_positive_fraction_is_refused(span: float) -> None:
    with pytest.raises(ValueError, match="span"):
        WeightAverage.start(_model(1.0), span, 0.0)


@pytest.mark.parametrize(("name", "value"), [("weight_average_span", -1.0), ("weight_average_span", float("nan")),
                                             ("weight_average_from", 1.5), ("weight_average_every", 0)])
def test_config_refuses_bad_values(name: str, value: float) -> None:
    with pytest.raises(ValueError, match=name):
        TrainConfig(**{name: value})


def _trainer(span: float, iterations: int = 30) -> Trainer:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=8)
    cfg = TrainConfig(iterations=iterations, resolution_init=8, resolution_final=10, upsample_at=(0.6,),
                      occupancy_at=(), carve=False, weight_average_span=span, weight_average_from=0.5,
                      weight_average_every=2, choose_full_spacing=False)
    return Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)


def test_trainer_keeps_the_average_from_its_start_restarts_it_at_an_upsample_and_ends_with_it() -> None:
    trainer = _trainer(span=0.05)
    seen: list[tuple[int, float | None]] = []
    original = trainer._average_weights

    def spy() -> None:
        original()
        avg = trainer.weight_average
        seen.append((trainer.state.iteration, None if avg is None else avg.progress))

    trainer._average_weights = spy  # type: ignore[method-assign]
    averaged: list[list[torch.Tensor]] = []
    original_use = trainer._use_weight_average

    def use() -> dict[str, float]:
        avg = trainer.weight_average
        assert avg is not None and avg.follows(trainer.field)
        avg.update(trainer.progress())
        averaged.append([a.clone() for a in avg.average])
        return original_use()

    trainer._use_weight_average = use  # type: ignore[method-assign]
    trainer.run(progress_bar=False)
    assert all(p is None for it, p in seen if it < 15)  # progress below 0.5: no average yet
    assert seen[14][1] == 0.5  # started at iteration 15 (progress 0.5)
    assert trainer.state.upsamples_done == 1
    # The upsample at iteration 18 (progress 0.6) replaced the grids: the average restarted there.
    assert seen[18][1] == pytest.approx(19 / 30)
    assert [it for it, p in seen[19:] if p is not None and p == pytest.approx(it / 30)] == [20, 22, 24, 26, 28, 30]
    for p, a in zip(trainer.field.parameters(), averaged[0], strict=True):
        torch.testing.assert_close(p.detach(), a)


def test_trainer_without_a_span_keeps_no_average() -> None:
    trainer = _trainer(span=0.0, iterations=6)
    trainer.run(progress_bar=False)
    assert trainer.weight_average is None


def test_a_non_finite_average_at_the_end_keeps_the_last_parameters_with_a_warning() -> None:
    trainer = _trainer(span=0.05, iterations=20)
    trainer.run(progress_bar=False)  # ends with the average swapped in
    avg = trainer.weight_average
    assert avg is not None
    avg.average[0].view(-1)[0] = float("nan")
    before = [p.detach().clone() for p in trainer.field.parameters()]
    with pytest.warns(RuntimeWarning, match="holds the last parameters"):
        assert trainer._use_weight_average() == {}
    for p, b in zip(trainer.field.parameters(), before, strict=True):
        assert torch.equal(p.detach(), b)
