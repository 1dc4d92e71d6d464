"""Training on several processes (``training.distributed``): real ``torchrun`` runs of two ranks on
gloo, and the launch environments read without one."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from visnerf.checkpoint import read_checkpoint
from visnerf.config import FieldConfig, TrainConfig
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import load_scene
from visnerf.testing import make_noise_scene
from visnerf.training.distributed import Launch, Ranks
from visnerf.training.trainer import Trainer

STEPS_SCRIPT = Path(__file__).with_name("distributed_steps.py")


def torchrun(tmp: Path, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node 2``: its rendezvous on a free port of localhost that
    it binds itself (no race with other jobs for a port chosen beforehand); one thread per rank.
    Its temporary files go under ``tmp`` (torchrun leaves a ``torchelastic_*`` folder behind)."""
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "TMPDIR": str(tmp)})


@pytest.mark.slow
@pytest.mark.parametrize("step", ["torch", "fused"])
def test_two_ranks_with_half_the_batch_each_step_as_one_process_with_the_whole_batch(tmp_path, step: str) -> None:
    run = torchrun(tmp_path, str(STEPS_SCRIPT), str(tmp_path), step)
    assert run.returncode == 0, run.stderr[-3000:]
    ranks = [load_file(tmp_path / f"rank{r}.safetensors") for r in (0, 1)]
    # A stop asked of rank 1 alone before step 2 stops both ranks there (rank 0 learns it in step).
    assert [r.pop("stopped_at").tolist() for r in ranks] == [[2, 1], [2, 1]]
    solo, init = load_file(tmp_path / "solo.safetensors"), load_file(tmp_path / "init.safetensors")
    assert ranks[0].keys() == ranks[1].keys() == solo.keys()
    assert any(name.startswith("grad") for name in solo) == (step == "torch")
    for name in solo:
        # The ranks took the same steps from the same averaged gradients: bit for bit the same field.
        assert torch.equal(ranks[0][name], ranks[1][name]), name
        # The average of the two half-batch gradients is the whole batch's (float32 rounding apart:
        # 2e-7 of the largest entry seen), and so are the parameters after four Adam steps and an
        # upsampling (4e-8 apart seen, the steps moved them by 4e-3 to 4e-2).
        if name.startswith("grad"):
            scale = float(solo[name].abs().max())
            torch.testing.assert_close(ranks[0][name], solo[name], rtol=1e-5, atol=1e-5 * scale, msg=name)
        else:
            torch.testing.assert_close(ranks[0][name], solo[name], rtol=1e-5, atol=1e-6, msg=name)
    moved = [float((solo[k] - init[k]).abs().max()) for k in init if not k.startswith("grad") and
             solo[k].shape == init[k].shape]
    assert min(moved) > 1e-3  # the steps changed every tensor that kept its shape
    assert solo["density_grid.plane_table"].shape != init["density_grid.plane_table"].shape  # upsampled


@pytest.mark.slow
def test_torchrun_train_writes_one_checkpoint_from_rank_0(tmp_path) -> None:
    data = tmp_path / "plume"
    made = subprocess.run([sys.executable, "-m", "visnerf", "make-scene", "plume_time", "--out", str(data),
                           "--res", "16", "--views", "12", "--test-views", "2", "--quiet"],
                          capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    out = tmp_path / "runs"
    out.mkdir()
    # A time budget: rank 0's clock decides every rank's progress, milestones and last step.
    run = torchrun(tmp_path, "-m", "visnerf", "train", str(data), "--out", str(out / "m.safetensors"), "--time-budget", "0.05",
                   "--resolution", "16", "--batch-rays", "512", "--holdout-views", "3", "--validate-every-s", "1000",
                   "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr[-3000:]
    log = run.stdout + run.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == ["m.log.csv", "m.log.json", "m.safetensors"], log
    assert run.stdout.count("saved ") == 1 and run.stderr.count("training on ") == 1, log  # rank 0 alone
    meta, _ = read_checkpoint(out / "m.safetensors")
    prov = meta.provenance
    assert prov.ranks == 2 and prov.backend == "gloo" and prov.recipe["batch_rays"] == 512
    assert prov.iterations > 0 and prov.train_seconds >= 3.0 and prov.val_psnr is not None, prov
    scene = load_scene(out / "m.safetensors", torch.device("cpu"))
    image = scene.render(orbit_c2w(30.0, 20.0, scene.info.camera.get("distance", 2.0)), 30.0, 24, 24)
    assert image.shape == (24, 24, 3) and image.dtype == np.uint8 and image.std() > 0, image


def test_the_launch_is_read_from_torchrun_srun_or_nothing() -> None:
    torchrun_env = {"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2",
                    "MASTER_ADDR": "node0", "MASTER_PORT": "1234"}
    assert Launch.from_environment(torchrun_env) == Launch(3, 4, 1, 2, "node0", 1234, "torchrun")
    srun_env = {"SLURM_PROCID": "5", "SLURM_STEP_NUM_TASKS": "8", "SLURM_LOCALID": "1", "SLURM_NTASKS": "8",
                "MASTER_ADDR": "node7"}
    assert Launch.from_environment(srun_env) == Launch(5, 8, 1, 1, "node7", 29500, "srun")
    # A batch script's own process (no job step) and a one-process torchrun train alone.
    assert Launch.from_environment({"SLURM_PROCID": "0", "SLURM_NTASKS": "8"}).world_size == 1
    assert Launch.from_environment({"RANK": "0", "WORLD_SIZE": "1"}) == Launch()
    assert Launch.from_environment({}) == Launch()
    with pytest.raises(ValueError, match="MASTER_ADDR"):
        Launch.from_environment({k: v for k, v in srun_env.items() if k != "MASTER_ADDR"})
    with pytest.raises(ValueError, match="rank 4"):
        Launch(4, 4)
    assert Launch(0, 2, 1).device_for(torch.device("cpu")) == torch.device("cpu")


def test_batch_shares_add_up_and_each_rank_draws_its_own_stream() -> None:
    device = torch.device("cpu")
    shares = [Ranks(Launch(r, 3), device).batch_share(2048) for r in range(3)]
    assert [s[0] for s in shares] == [683, 683, 682] and all(s[1] == 2048 / 3 for s in shares)
    seeds = {Ranks(Launch(r, 3), device).stream_seed(0, i) for r in range(3) for i in (0, 100)}
    assert len(seeds) == 6


def test_one_process_starts_no_group_and_changes_nothing() -> None:
    solo = Ranks.start(Launch(), torch.device("cpu"))
    assert solo.is_main and solo.world_size == 1 and solo.provenance() == {}
    assert solo.batch_share(2048) == (2048, 2048.0)
    assert solo.agree(12.5, True) == (12.5, True)
    p = torch.nn.Parameter(torch.ones(3))
    p.grad = torch.full((3,), 2.0)
    assert solo.average_gradients([p], 0.25) == (0.25,) and torch.equal(p.grad, torch.full((3,), 2.0))
    assert not torch.distributed.is_initialized()


def test_a_trainer_of_one_process_goes_on_as_it_was() -> None:
    """``distribute`` with one process keeps the random stream (a resumed run's) and validation."""
    scene = make_noise_scene(n_views=4, size=8)
    cfg = TrainConfig(iterations=1, resolution_init=8, resolution_final=8, carve=False)
    trainer = Trainer(scene, scene, cfg, torch.device("cpu"), field_cfg=FieldConfig(hidden_width=16))
    stream = trainer.generator.get_state()
    trainer.distribute(Ranks.solo(torch.device("cpu")))
    assert torch.equal(trainer.generator.get_state(), stream) and trainer.val_scene is scene
