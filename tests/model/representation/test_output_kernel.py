"""The compiled output layer on bfloat16 activations (``output_kernel``) against a float64 product."""

import pytest
import torch

from visnerf.representation import output_kernel
from visnerf.representation.frame_field import FrameField
from visnerf.testing import make_tiny_field

pytestmark = pytest.mark.skipif(not output_kernel.available(torch.device("cpu")), reason="numba is not installed")


def _layer(outputs: int, width: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(outputs, width, generator=g), torch.randn(outputs, generator=g)


@pytest.mark.parametrize("outputs", [1, 3])
@pytest.mark.parametrize("width", [64, 128, 37])
def test_output_equals_the_float64_product_of_the_bf16_activations(outputs, width) -> None:
    weight, bias = _layer(outputs, width, outputs * width)
    hidden = (torch.randn(1000, width, generator=torch.Generator().manual_seed(1)) * 3).relu().to(torch.bfloat16)
    got = output_kernel.OutputLayer(weight, bias)(hidden)
    expected = hidden.double() @ weight.double().t() + bias.double()  # [m, o]
    assert got.dtype == torch.float32 and got.shape == (1000, outputs)
    # float32 sums of exact products (a bfloat16 times a float32 is exact in float64)
    scale = (hidden.double().abs() @ weight.double().abs().t() + bias.double().abs()).max()
    assert float((got.double() - expected).abs().max()) < 1e-6 * float(scale)
    # far closer than the bfloat16 product, whose output is rounded to 8 significant bits
    rounded = torch.nn.functional.linear(hidden, weight.bfloat16(), bias.bfloat16()).double()
    assert float((got.double() - expected).abs().max()) < 0.05 * float((rounded - expected).abs().max())


def test_a_row_with_nan_or_infinity_gives_nan_or_infinity_in_that_row_only() -> None:
    weight, bias = torch.ones(1, 8), torch.zeros(1)
    hidden = torch.ones(4, 8, dtype=torch.bfloat16)
    hidden[1, 3] = float("nan")
    hidden[2, 5] = float("inf")
    got = output_kernel.OutputLayer(weight, bias)(hidden)[:, 0]
    assert float(got[0]) == 8.0 and float(got[3]) == 8.0
    assert torch.isnan(got[1]) and got[2] == float("inf")


def test_no_rows_and_rows_that_are_a_view() -> None:
    weight, bias = _layer(3, 16, 0)
    layer = output_kernel.OutputLayer(weight, bias)
    assert layer(torch.empty(0, 16, dtype=torch.bfloat16)).shape == (0, 3)
    wide = torch.randn(50, 32).to(torch.bfloat16)
    view = wide[:, 8:24]  # rows 32 apart
    assert torch.equal(layer(view), layer(view.contiguous()))


@pytest.mark.parametrize("hidden", [torch.zeros(5, 16), torch.zeros(5, 15, dtype=torch.bfloat16)],
                         ids=["float32", "width"])
def test_activations_of_another_type_or_width_are_refused(hidden) -> None:
    with pytest.raises(ValueError, match="hidden must be bfloat16"):
        output_kernel.OutputLayer(*_layer(1, 16, 0))(hidden)


def test_bf16_frame_fields_on_the_cpu_write_float32_outputs() -> None:
    """The compiled bf16 path's raw densities are not rounded to bfloat16 (the oneDNN product's are)."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=1, resolution=10)
    q_d, q_a = field.eval().param_features(torch.tensor([[0.3]]))
    points = torch.rand(3000, 3, generator=torch.Generator().manual_seed(0)) - 0.5
    with torch.no_grad():
        for compiled, rounded in ((True, False), (False, True)):
            frame = FrameField(field, q_d, q_a, torch.bfloat16, compiled=compiled)
            raw = frame._raw_density(field.to_grid(points), None if compiled else frame.lookup(points).taps)
            assert torch.equal(raw, raw.bfloat16().float()) == rounded
