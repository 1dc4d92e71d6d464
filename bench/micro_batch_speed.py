"""What a step's micro-batches cost: late-phase Nyx steps with the batch split in several chunks or
rendered in one.

``Trainer.train_step`` renders and back-propagates a step's rays in micro-batches of at most
``micro_batch_rays`` rays and ``micro_batch_samples`` samples (those the rays evaluate, in
occupied cells, ``trainer.micro_batches``); the gradient is the same for any split. Each micro-batch has
fixed costs besides its samples: a pass of Python over the renderer, the decoders' weight
gradients, and per factor table a sort of its taps and a sparse product into the whole table's
gradient. From a trained checkpoint, one trainer per setting steps the field as the late phase of
a run does (``nyx_train.late_phase_trainer``, the recipe's 2048 rays), alternating over
``--rounds``, so that all share the machine's noise.

    python bench/micro_batch_speed.py --checkpoint runs/nyx_hour_r200.safetensors

Writes bench/results/micro_batch_speed.{json,md}.
"""

import argparse
import statistics
import sys
from pathlib import Path

import torch
from bench_common import (
    add_trained_model_args,
    alternate_steps,
    fmt,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    require_checkpoint,
    step_time_summary,
    write_results,
)
from nyx_train import NYX_BATCH_RAYS, NYX_LATE_PHASE_STEP, late_phase_trainer

from visnerf.inference import load_scene
from visnerf.rendering.renderer import empty_space_of, place_samples
from visnerf.training.trainer import Trainer, micro_batches, occupied_windows


def parse_settings(text: str) -> list[tuple[int, int]]:
    """``"1024x32768,2048x131072"`` -> [(rays, samples), ...]."""
    out = []
    for item in text.split(","):
        rays, _, samples = item.strip().partition("x")
        try:
            pair = (int(rays), int(samples))
        except ValueError:
            pair = (0, 0)
        if min(pair) < 1:
            raise argparse.ArgumentTypeError(f"expected RAYSxSAMPLES with both above 0, got {item!r}")
        out.append(pair)
    return out


def chunks_of(trainer: Trainer, batches: int) -> dict[str, float]:
    """Median micro-batches per step, and samples in the rays' occupied windows, over ``batches``
    fresh batches of the trainer's sampler, placed as ``Trainer.train_step`` places them."""
    chunks, window = [], []
    cfg = trainer.cfg
    step = trainer.step_size()
    for _ in range(batches):
        b = trainer.sampler.sample(cfg.batch_rays)
        w = occupied_windows(trainer.field, b.rays_o, b.rays_d, step, empty_space_of(trainer.field))
        window.append(int((w[1] - w[0] + 1).clamp_min(0).sum()))
        placed = place_samples(trainer.field, b.rays_o, b.rays_d, b.params, step, trainer.render_cfg.max_samples,
                               trainer.field.occupancy, trainer.generator, 0, w)
        chunks.append(len(micro_batches(placed.per_ray(), cfg.micro_batch_rays, cfg.micro_batch_samples)))
    return {"micro_batches": statistics.median(chunks), "window_samples": statistics.median(window)}


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("Late-phase Nyx steps against their micro-batching", record) + [
        "",
        f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}); steps of {record['batch_rays']} rays, "
        f"{record['rounds']} rounds of {record['steps']} steps per setting, alternating. Samples are those the step "
        "evaluated (in occupied cells), which the micro-batching counts; window samples those in the rays' occupied "
        "windows, which it counted before.",
        "",
        "| rays per micro-batch | samples per micro-batch | micro-batches per step | window samples per step | samples evaluated | s per step (median) | against the first |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    first = record["settings"][0]["median_ms"]
    for s in record["settings"]:
        lines.append(f"| {s['rays']} | {s['samples']} | {fmt(s['micro_batches'], 0)} | {fmt(s['window_samples'], 0)} | "
                     f"{fmt(s['samples_evaluated'], 0)} | {s['median_ms'] / 1000:.4f} | {first / s['median_ms']:.2f}x |")
    lines.append("")
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_hour_r200.safetensors")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=25, help="steps per setting and round")
    ap.add_argument("--settings", type=parse_settings, default=parse_settings("1024x32768,1024x65536,2048x65536,2048x131072"),
                    metavar="RAYSxSAMPLES,...", help="micro-batch limits to compare (default %(default)s)")
    args = ap.parse_args()
    require_checkpoint(ap, args.checkpoint)
    load_before = load_average()
    train, _ = nyx_split(args.data)
    field = load_scene(Path(args.checkpoint), torch.device("cpu")).field
    trainers = {
        (rays, samples): late_phase_trainer(
            train, field, samples, micro_batch_rays=rays, lr_factors=0.0, lr_networks=0.0, **NYX_LATE_PHASE_STEP)
        for rays, samples in args.settings}
    # Rates of 0: the field stays as trained, so every setting steps the same field.
    times, outputs = alternate_steps(trainers, args.rounds, args.steps, warm_up=True)
    settings = []
    for (rays, samples), trainer in trainers.items():
        settings.append({"rays": rays, "samples": samples, **chunks_of(trainer, 20),
                         "samples_evaluated": statistics.median(o["samples"] for o in outputs[(rays, samples)]),
                         **step_time_summary(times[(rays, samples)])})
    record = {
        **machine_record(),
        "command": "python bench/micro_batch_speed.py " + " ".join(sys.argv[1:]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution), "batch_rays": NYX_BATCH_RAYS,
        "rounds": args.rounds, "steps": args.steps, "settings": settings,
    }
    write_results(Path(args.results), "micro_batch_speed", record, write_markdown)
    for s in settings:
        print(f"{s['rays']} rays / {s['samples']} samples: {s['micro_batches']:.0f} micro-batches, {s['median_ms']:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
