"""bf16 decoder passes run on a few padded row counts: the same values and gradients as unpadded."""

import pytest
import torch

import visnerf.representation.decoders as decoders
from visnerf.representation.decoders import Decoder, padded_rows


def test_padded_row_counts_are_few_and_never_smaller() -> None:
    counts = {padded_rows(m) for m in range(1, 16385)}
    assert len(counts) <= 24
    assert all(padded_rows(m) >= m and padded_rows(m) - m < 1024 for m in range(1, 20000, 7))


@pytest.mark.parametrize("n", [1, 130, 1500])
def test_padded_bf16_pass_gives_the_unpadded_values_and_gradients(n: int, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(0)
    dec = Decoder(10, 16, 3)
    dec.bf16 = True
    x = torch.randn(n, 10)

    def run() -> tuple[torch.Tensor, list[torch.Tensor]]:
        dec.zero_grad()
        xi = x.clone().requires_grad_(True)
        out = dec(xi)
        (out * torch.linspace(-1, 1, 3)).sum().backward()
        return out.detach(), [xi.grad.clone()] + [p.grad.clone() for p in dec.parameters()]

    padded_out, padded_grads = run()
    monkeypatch.setattr(decoders, "padded_rows", lambda m: m)
    exact_out, exact_grads = run()
    assert padded_out.shape == (n, 3)
    assert torch.equal(padded_out, exact_out)
    for a, b in zip(padded_grads, exact_grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-2, atol=1e-3)  # bf16 sums in another order at most
