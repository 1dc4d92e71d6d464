"""What the decoders' bfloat16 matrix products buy on this CPU: Nyx training steps and frames.

Training (``TrainConfig.mixed_precision``) and full-quality frames (``RenderConfig.bf16``) run the
decoders' matrix products in bfloat16 wherever ``runtime.bf16_native`` says the CPU has bf16
instructions: AMX on the Xeons, AVX512-BF16 alone on the AMD EPYCs some sessions run on. This
measures both paths each way on the machine it runs on, from a trained checkpoint:

- training steps: two trainers step the same trained field as the late phase of a run does
  (``nyx_train.late_phase_trainer``), one with the decoders in bfloat16, one in float32,
  alternating over ``--rounds``, so both share the machine's noise;
- frames: ``--frames`` held-out 256x256 frames rendered through the inference API with ``bf16`` on
  and off in turn, ``--frame-repeats`` times each, the order flipping: seconds per frame (median),
  PSNR against the ground truth, and PSNR of the bf16 frame against the float32 one.

    python bench/mixed_precision_speed.py --checkpoint runs/nyx.safetensors

Writes bench/results/mixed_precision_speed.{json,md}.
"""

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from bench_common import (
    add_step_timing_args,
    add_trained_model_args,
    alternate_steps,
    evenly_spaced,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    render_frame,
    require_checkpoint,
    step_time_summary,
    write_results,
)
from nyx_train import NYX_BATCH_RAYS, late_phase_trainer

from visnerf.checkpoint import CheckpointMeta, load_checkpoint
from visnerf.evaluation.metrics import psnr
from visnerf.inference import SceneRenderer
from visnerf.rendering.setting_occupancy import SettingOccupancyConfig
from visnerf.representation.field import VisNerfField
from visnerf.runtime import bf16_native
from visnerf.training.trainer import set_mixed_precision


def time_steps(args: argparse.Namespace, train: Any) -> tuple[list[dict[str, Any]], int]:  # noqa: ANN401
    """Median step times each way, and the rays per step. Both trainers step the same field; the
    bfloat16 flag lives on that field's decoders, so it is set before each step, outside its time."""
    field, _ = load_checkpoint(args.checkpoint, torch.device("cpu"))
    trainers = {bf16: late_phase_trainer(train, field, args.micro_batch_samples, batch_rays=NYX_BATCH_RAYS)
                for bf16 in (True, False)}

    def set_precision(bf16: bool) -> None:
        set_mixed_precision(field, bf16)

    times, _ = alternate_steps(trainers, args.rounds, args.steps, before_step=set_precision, warm_up=True)
    return [{"bf16": bf16, **step_time_summary(times[bf16])} for bf16 in trainers], trainers[True].cfg.batch_rays


def time_frames(args: argparse.Namespace, val: Any, field: VisNerfField, meta: CheckpointMeta) -> list[dict[str, Any]]:  # noqa: ANN401
    """Each frame rendered ``--frame-repeats`` times each way, the order flipping at each repeat;
    the per-setting occupancy cache is off, so every render marches the same union grid (with it
    on, the second request of a setting starts a background build that would run beside one of
    the two timed renders). ``field`` is the checkpoint as loaded, not stepped by ``time_steps``."""
    scene = SceneRenderer(field, meta, torch.device("cpu"), SettingOccupancyConfig(capacity=0))
    metas = {bf16: dataclasses.replace(meta, render=dataclasses.replace(meta.render, bf16=bf16))
             for bf16 in (True, False)}  # the frame settings come from the scene's meta at each render
    for m in metas.values():  # warm-up: oneDNN builds its kernels on first use
        scene.meta = m
        render_frame(scene, val, 0, 256, 256)
    rows = []
    for i in evenly_spaced(val.n_frames, args.frames):
        row: dict[str, Any] = {"frame": int(i)}
        seconds: dict[bool, list[float]] = {True: [], False: []}
        images = {}
        for repeat in range(args.frame_repeats):
            for bf16 in ((True, False) if repeat % 2 == 0 else (False, True)):
                scene.meta = metas[bf16]
                t0 = time.perf_counter()
                images[bf16], gt = render_frame(scene, val, i, 256, 256)
                seconds[bf16].append(time.perf_counter() - t0)
        for bf16, name in ((True, "bf16"), (False, "fp32")):
            row[f"seconds_{name}"] = statistics.median(seconds[bf16])
            row[f"psnr_{name}"] = psnr(images[bf16], gt)
        row["psnr_bf16_from_fp32"] = psnr(images[True], images[False])
        rows.append(row)
    return rows


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    steps = {row["bf16"]: row for row in record["steps"]}
    frames = record["frames"]

    def median(key: str) -> float:
        return statistics.median(r[key] for r in frames)

    lines = [
        *markdown_header("Decoders in bfloat16 or float32: Nyx training steps and frames", record),
        f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}); bf16 instructions "
        f"(`runtime.bf16_native`): {record['bf16_native']}.",
        "",
        f"Training steps of {record['batch_rays']} rays ({record['rounds']} rounds of "
        f"{record['steps_per_round']} steps each way, alternating):",
        "",
        "| decoders | median ms per step | min | max |",
        "| --- | --- | --- | --- |",
        *(f"| {'bfloat16' if bf16 else 'float32'} | {row['median_ms']:.1f} | {row['min_ms']:.1f} | {row['max_ms']:.1f} |"
          for bf16, row in steps.items()),
        "",
        f"float32 / bfloat16 step time (medians): {steps[False]['median_ms'] / steps[True]['median_ms']:.2f}x.",
        "",
        f"Frames ({len(frames)} held-out 256x256 frames, full quality, {record['frame_repeats']} renders each way "
        "in turn, the order flipping; the union occupancy grid, no per-setting cache):",
        "",
        "| decoders | median s per frame | mean PSNR to ground truth |",
        "| --- | --- | --- |",
        f"| bfloat16 | {median('seconds_bf16'):.3f} | {np.mean([r['psnr_bf16'] for r in frames]):.3f} dB |",
        f"| float32 | {median('seconds_fp32'):.3f} | {np.mean([r['psnr_fp32'] for r in frames]):.3f} dB |",
        "",
        f"float32 / bfloat16 frame time (medians): {median('seconds_fp32') / median('seconds_bf16'):.2f}x; "
        f"bfloat16 frames from float32 frames: {min(r['psnr_bf16_from_fp32'] for r in frames):.1f} dB at the least.",
        "",
    ]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx.safetensors")
    add_step_timing_args(ap, steps=5, per="precision")
    ap.add_argument("--frames", type=int, default=6, help="held-out frames rendered each way")
    ap.add_argument("--frame-repeats", type=int, default=3, help="renders of each frame each way (median)")
    args = ap.parse_args()
    if min(args.rounds, args.steps, args.frames, args.frame_repeats) < 1:
        ap.error("--rounds, --steps, --frames and --frame-repeats must be at least 1")
    require_checkpoint(ap, args.checkpoint)
    load_before = load_average()
    train, val = nyx_split(args.data)
    steps, batch_rays = time_steps(args, train)
    load_between = load_average()
    field, meta = load_checkpoint(args.checkpoint, torch.device("cpu"))
    frames = time_frames(args, val, field, meta)
    record = {
        **machine_record(),
        "command": " ".join(["python bench/mixed_precision_speed.py", *sys.argv[1:]]),
        "load_average_1min": {"before": load_before, "between": load_between, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution),
        "bf16_native": bf16_native(torch.device("cpu")),
        "batch_rays": batch_rays, "rounds": args.rounds, "steps_per_round": args.steps, "steps": steps,
        "frame_repeats": args.frame_repeats, "frames": frames,
    }
    write_results(Path(args.results), "mixed_precision_speed", record, write_markdown)
    for row in steps:
        print(f"steps, {'bf16' if row['bf16'] else 'fp32'}: {row['median_ms']:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
