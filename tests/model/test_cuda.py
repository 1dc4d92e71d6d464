"""The CUDA path against the CPU, which is the reference: the same field renders the same rays and
frames on both, a tiny scene trains on CUDA, and a checkpoint written from a CUDA field loads and
renders on the CPU. Skipped where no CUDA device is present (CI has none); on a GPU machine:

    pytest tests/model/test_cuda.py
"""

import numpy as np
import pytest
import torch

from visnerf.checkpoint import load_checkpoint
from visnerf.data.cameras import orbit_c2w
from visnerf.evaluation.metrics import psnr
from visnerf.factor_codec import CODE_MAX
from visnerf.inference import load_scene
from visnerf.rendering.training_render import render_rays
from visnerf.testing import make_tiny_checkpoint, make_tiny_field
from visnerf.training.trainer import Trainer

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
CUDA = torch.device("cuda")
CPU = torch.device("cpu")
SURFACE = {"level_set_axis": 0, "facing_vectors": 2}
"""The opaque-scene field: a level axis (isosurface sweeps) and facing cosines in the colour."""
FIELDS = pytest.mark.parametrize("options", [{}, SURFACE], ids=["volume", "surface"])


def _rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 1.5  # [n, 3]
    targets = (torch.rand(n, 3, generator=g) - 0.5) * 0.6
    dirs = torch.nn.functional.normalize(targets - origins, dim=-1)
    params = torch.rand(n, 1, generator=g) * 2 - 1  # [n, 1] normalised
    return origins, dirs, params


@FIELDS
def test_render_rays_on_cuda_matches_the_cpu_and_so_do_its_gradients(options: dict) -> None:
    field_cpu, _ = make_tiny_field([("a", [0.0, 0.5, 1.0])], seed=3, resolution=10, **options)
    field_gpu, _ = make_tiny_field([("a", [0.0, 0.5, 1.0])], seed=3, resolution=10, **options)
    field_gpu = field_gpu.to(CUDA)
    o, d, p = _rays(512, 0)
    bg = torch.ones(512, 3)
    step = field_cpu.voxel_size() * 0.5
    out_cpu = render_rays(field_cpu, o, d, p, bg, step, 4096, None)
    out_gpu = render_rays(field_gpu, o.to(CUDA), d.to(CUDA), p.to(CUDA), bg.to(CUDA), step, 4096, None)
    assert out_cpu["n_samples"] == out_gpu["n_samples"]
    torch.testing.assert_close(out_gpu["rgb"].cpu(), out_cpu["rgb"], atol=2e-5, rtol=0)
    torch.testing.assert_close(out_gpu["opacity"].cpu(), out_cpu["opacity"], atol=2e-5, rtol=0)
    out_cpu["rgb"].square().sum().backward()
    out_gpu["rgb"].square().sum().backward()
    for (name, a), (_, b) in zip(field_cpu.named_parameters(), field_gpu.named_parameters(), strict=True):
        if a.grad is None:
            assert b.grad is None or not b.grad.any(), name
            continue
        scale = float(a.grad.abs().max()) + 1e-12
        assert float((b.grad.cpu() - a.grad).abs().max()) < 1e-3 * scale, name


@FIELDS
def test_a_checkpoint_renders_the_same_frame_on_cuda_and_cpu(tmp_path, options: dict) -> None:
    kind = "ir" if options else "dvr"
    path = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [("a", [0.0, 1.0])], kind=kind, seed=2, **options)
    c2w = orbit_c2w(30.0, 20.0, 2.5)
    frames = {}
    for which, device in (("reference", CPU), ("cuda", CUDA)):
        scene = load_scene(path, device)
        for quality in ("full", "preview"):
            frames[which, quality] = scene.render(c2w, 30.0, 64, 48, {"a": 0.3}, quality)
    for quality in ("full", "preview"):
        cpu, gpu = (frames[k, quality].astype(np.float32) / 255 for k in ("reference", "cuda"))
        assert cpu.shape == gpu.shape == (48, 64, 3)
        assert cpu.std() > 0.02  # something is drawn, so the comparison means something
        # bfloat16 decoders where the device has them: rounding differs, the frame does not.
        assert psnr(gpu, cpu) > 40.0, quality


def test_a_tiny_scene_trains_on_cuda_and_its_checkpoint_loads_on_the_cpu(tmp_path, tiny_plume_run) -> None:
    trainer = Trainer(tiny_plume_run.train, tiny_plume_run.val, tiny_plume_run.cfg, CUDA)
    log = trainer.run(progress_bar=False)
    assert trainer.field.aabb.device.type == CUDA.type
    assert log[-1]["val_psnr"] > tiny_plume_run.min_held_out_psnr, log  # the CPU run's floor
    ckpt = trainer.save(tmp_path / "plume.safetensors")
    field, _ = load_checkpoint(ckpt, CPU)
    for (name, a), (_, b) in zip(trainer.field.state_dict().items(), field.state_dict().items(), strict=True):
        assert b.device.type == "cpu"
        # the planes are stored as int8 codes, a scale per row (``factor_codec``): half a step of the
        # row, at most half of max |a| / 127; float16 rounding of the other tensors is finer
        bound = float(a.float().abs().max()) / (2 * CODE_MAX) + 1e-6
        torch.testing.assert_close(b, a.cpu().to(b.dtype), atol=bound, rtol=0, msg=name)
