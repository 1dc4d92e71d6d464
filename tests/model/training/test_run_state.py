"""Killed and stopped training runs: the run state, SIGTERM / Ctrl-C, ``--resume``, SIGKILL."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from visnerf.checkpoint import read_checkpoint
from visnerf.config import HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.training.record import validate
from visnerf.training.run_state import RunStateError, read_run_state, run_state_path, write_run_state
from visnerf.training.trainer import Trainer


class StopAt:
    """Stands in for ``StopSignals``: asks the loop to stop once ``trainer`` reaches ``iteration``."""

    def __init__(self, iteration: int) -> None:
        self.iteration = iteration
        self.trainer: Trainer | None = None

    def requested(self) -> bool:
        assert self.trainer is not None
        return self.trainer.state.iteration >= self.iteration

    def loop_ended(self) -> None:
        pass


# Milestones on both sides of the stop at 27 of 48: an upsample and the first occupancy grid
# before it, the weight average begun; the second upsample, an occupancy update and a
# refinement after it.
SCHEDULE = TrainConfig(iterations=48, batch_rays=256, resolution_init=12, resolution_final=20,
                       upsample_at=(0.3, 0.7), occupancy_at=(0.25, 0.65), occupancy_min_iterations=5,
                       occupancy_refine_at=(0.8,), l1_switch_iteration=20, weight_average_from=0.4,
                       weight_average_span=0.2, weight_average_every=2, validate_every_s=1e9,
                       validate_max_images=2, choose_full_spacing=False)


@pytest.fixture(scope="module")
def scene_split(synthetic_scene):
    data = synthetic_scene("plume_time", 16)
    train, val = split_holdout(load_dataset(data), HoldoutConfig(views=(2, 9)))
    return data, train, val


@pytest.mark.slow
def test_a_stopped_run_resumed_from_its_state_is_the_uninterrupted_run(scene_split, tmp_path) -> None:
    _, train, val = scene_split
    cpu = torch.device("cpu")
    whole = Trainer(train, val, SCHEDULE, cpu)
    whole.run(progress_bar=False)

    first = Trainer(train, val, SCHEDULE, cpu)
    stop = StopAt(27)
    stop.trainer = first
    state = tmp_path / "m.resume"
    first.run(progress_bar=False, state_path=state, stop=stop)
    assert first.stopped and first.state.iteration == 27 and state.exists()
    document, tensors = read_run_state(state)
    assert document["state"]["iteration"] == 27 and document["weight_average"] is not None
    assert any(name.startswith("optimizer.") and name.endswith("exp_avg_sq") for name in tensors)

    second = Trainer.from_run_state(state, train, val, cpu)
    assert second.state.upsamples_done == first.state.upsamples_done == 1
    second.run(progress_bar=False)
    assert second.state.iteration == whole.state.iteration == SCHEDULE.iterations
    assert second.field.resolution == whole.field.resolution
    for (name, a), b in zip(whole.field.state_dict().items(), second.field.state_dict().values(), strict=True):
        assert torch.equal(a, b), f"{name} differs after the resumed run"
    psnr_whole = validate(whole.field, val, whole.render_cfg, 2)["val_psnr"]
    psnr_resumed = validate(second.field, val, second.render_cfg, 2)["val_psnr"]
    assert abs(psnr_whole - psnr_resumed) < 1e-6


def _stopped_after_three_steps(train, val, tmp_path: Path) -> tuple[Trainer, Path]:
    """A run stopped after three steps, its run state written to ``tmp_path / "m.resume"``."""
    first = Trainer(train, val, SCHEDULE, torch.device("cpu"))
    stop = StopAt(3)
    stop.trainer = first
    state = tmp_path / "m.resume"
    first.run(progress_bar=False, state_path=state, stop=stop)
    return first, state


def test_a_run_state_refuses_other_frames_and_damage(scene_split, tmp_path) -> None:
    _, train, val = scene_split
    cpu = torch.device("cpu")
    first, state = _stopped_after_three_steps(train, val, tmp_path)
    with pytest.raises(RunStateError, match="other training frames"):
        Trainer.from_run_state(state, val, None, cpu)  # the held-out frames are not the training frames
    document, tensors = read_run_state(state)
    tensors["field.density_grid.planes.0"][0, 0, 0] = float("nan")
    write_run_state(tmp_path / "nan.resume", tensors, document)
    with pytest.raises(RunStateError, match="non-finite"):
        read_run_state(tmp_path / "nan.resume")
    blob = state.read_bytes()
    (tmp_path / "cut.resume").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(RunStateError, match="corrupt or truncated"):
        read_run_state(tmp_path / "cut.resume")
    (tmp_path / "other.resume").write_bytes(b"\x80\x04not a run state")
    with pytest.raises(RunStateError, match="not a run state"):
        read_run_state(tmp_path / "other.resume")


def test_a_version_1_run_state_goes_on(scene_split, tmp_path) -> None:
    """A run state written before a setting was retired (version 1, ``random_background`` in its
    training configuration) is read as version 2 and the run goes on from it."""
    _, train, val = scene_split
    cpu = torch.device("cpu")
    first, state = _stopped_after_three_steps(train, val, tmp_path)
    document, tensors = read_run_state(state)
    assert document["format_version"] == 2
    old = {**document, "format_version": 1, "train": {**document["train"], "random_background": False}}
    write_run_state(tmp_path / "v1.resume", tensors, old)
    migrated, _ = read_run_state(tmp_path / "v1.resume")
    assert migrated == document
    resumed = Trainer.from_run_state(tmp_path / "v1.resume", train, val, cpu)
    assert resumed.state.iteration == first.state.iteration


def _train_command(data: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "visnerf.cli", "train", str(data), "--out", str(out), "--iterations", "240",
            "--resolution", "16", "--batch-rays", "256", "--holdout-views", "2,9", "--validate-every", "0.5",
            "--device", "cpu", "--quiet", *extra]


def _has_validated(state: Path) -> bool:
    """Whether the run state at ``state`` exists and its log has a validation row."""
    if not state.exists():
        return False
    return bool(read_run_state(state)[0]["state"]["log"])


def _psnr_of(checkpoint: Path) -> float:
    meta, _ = read_checkpoint(checkpoint)
    return float(meta.provenance.val_psnr)


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_visnerf_train_stopped_by_a_signal_saves_and_resumes(scene_split, tmp_path, signum) -> None:
    data = scene_split[0]
    out = tmp_path / "m.safetensors"
    state = run_state_path(out)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    job = subprocess.Popen(_train_command(data, out, "--checkpoint-every-s", "0.2"), stderr=subprocess.PIPE,
                           text=True, env=env)
    deadline = time.monotonic() + 240
    while not _has_validated(state) and time.monotonic() < deadline and job.poll() is None:
        time.sleep(0.1)  # a periodic state after the first validation: the loop is running
    assert state.exists(), job.communicate()[1]
    job.send_signal(signum)
    _, err = job.communicate(timeout=120)
    assert job.returncode == 128 + signum, err
    name = signal.Signals(signum).name
    assert f"stopped by {name} at iteration" in err and "--resume" in err
    assert not out.exists() and out.with_suffix(".log.csv").exists()
    stopped_at = read_run_state(state)[0]["state"]["iteration"]
    assert 0 < stopped_at < 240

    again = subprocess.run(_train_command(data, out), capture_output=True, text=True, env=env)
    assert again.returncode == 2 and "pass --resume to go on with it" in again.stderr and state.exists()

    resumed = subprocess.run(_train_command(data, out, "--resume"), capture_output=True, text=True, env=env)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming {state} at iteration {stopped_at}" in resumed.stderr
    assert not state.exists()  # the run is done: its state is gone, its checkpoint written
    meta, _ = read_checkpoint(out)
    assert meta.provenance.iterations == 240 and meta.provenance.run_states.written >= 2
    log = json.loads(out.with_suffix(".log.json").read_text())
    assert any(row["iteration"] <= stopped_at for row in log) and log[-1]["iteration"] == 240  # one log

    if signum != signal.SIGTERM:
        return  # one comparison with an uninterrupted run is enough
    whole = tmp_path / "whole.safetensors"
    uninterrupted = subprocess.run(_train_command(data, whole, "--checkpoint-every-s", "0"), capture_output=True,
                                   text=True, env=env)
    assert uninterrupted.returncode == 0, uninterrupted.stderr
    assert read_checkpoint(whole)[0].provenance.iterations == 240
    assert abs(_psnr_of(out) - _psnr_of(whole)) < 0.1


@pytest.mark.slow
def test_a_job_killed_outright_goes_on_from_its_last_periodic_state(scene_split, tmp_path) -> None:
    data = scene_split[0]
    out = tmp_path / "m.safetensors"
    state = run_state_path(out)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    job = subprocess.Popen(_train_command(data, out, "--checkpoint-every-s", "0.2"), stderr=subprocess.DEVNULL,
                           env=env)
    deadline = time.monotonic() + 240
    while not _has_validated(state) and time.monotonic() < deadline and job.poll() is None:
        time.sleep(0.1)
    while (job.poll() is None and time.monotonic() < deadline
           and read_run_state(state)[0]["state"]["states_written"] < 3):
        time.sleep(0.1)  # a few more periodic states
    job.kill()
    job.wait()
    document = read_run_state(state)[0]  # the last whole state: the kill cannot have torn it
    kept = document["state"]["iteration"]
    assert kept > 0 and document["state"]["states_written"] >= 2
    resumed = subprocess.run(_train_command(data, out, "--resume"), capture_output=True, text=True, env=env)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming {state} at iteration {kept}" in resumed.stderr
    assert read_checkpoint(out)[0].provenance.iterations == 240 and not state.exists()


@pytest.mark.slow
def test_resume_without_a_state_names_what_is_missing(scene_split, tmp_path) -> None:
    data = scene_split[0]
    run = subprocess.run(_train_command(data, tmp_path / "m.safetensors", "--resume"), capture_output=True, text=True)
    assert run.returncode == 2 and f"no run state or checkpoint at {tmp_path / 'm.resume'}" in run.stderr


WRITER = """
import sys, torch
from visnerf.training.run_state import write_run_state
path = sys.argv[1]
i = 0
while True:
    i += 1
    write_run_state(path, {"big": torch.full((4_000_000,), float(i))}, {"state": {"iteration": i}})
"""


@pytest.mark.slow
def test_sigkill_during_writes_never_leaves_a_file_that_fails_to_load(tmp_path) -> None:
    path = tmp_path / "k.resume"
    seen = []
    for delay in (0.0, 0.13, 0.37, 0.61, 0.85):  # killed at different points of a 16 MB write
        writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path)])
        deadline = time.monotonic() + 120
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.02)  # the first write is done: the writer is past its imports
        time.sleep(delay)
        writer.kill()
        writer.wait()
        if path.exists():
            document, tensors = read_run_state(path)  # whole, or the error would name the damage
            i = document["state"]["iteration"]
            assert bool((tensors["big"] == float(i)).all())
            seen.append(i)
    assert seen, "no write finished before the kills: lengthen the delays"
    print(json.dumps({"iterations_seen": seen}))
