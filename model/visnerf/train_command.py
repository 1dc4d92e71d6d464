"""The ``train`` sub-command: options, data, a trainer (fresh, resumed or from a checkpoint), the run and its save."""

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from visnerf.arg_types import add_device_option, positive_float
from visnerf.checkpoint import CheckpointError
from visnerf.cinema_options import add_cinema_options, cinema_camera
from visnerf.config import FieldConfig, RenderConfig, TrainConfig
from visnerf.config_options import add_config_options, given_options
from visnerf.holdout_options import add_holdout_options, holdout_config
from visnerf.runtime import pick_device

if TYPE_CHECKING:
    from visnerf.data.scene import SceneData
    from visnerf.training.trainer import Trainer


def parse_bbox(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``"-0.2,-0.2,-0.2,0.2,0.2,0.2"`` -> ((x0, y0, z0), (x1, y1, z1)), finite with x1 > x0 etc."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"cannot read box {text!r}: use six numbers 'X0,Y0,Z0,X1,Y1,Z1'")
    lo, hi = (v[0], v[1], v[2]), (v[3], v[4], v[5])
    if not all(b > a for a, b in zip(lo, hi, strict=True)):
        raise argparse.ArgumentTypeError(f"box {text!r} is empty: each of X1,Y1,Z1 must exceed X0,Y0,Z0")
    return lo, hi


def with_bbox(scene: "SceneData", box: tuple[tuple[float, ...], tuple[float, ...]] | None) -> "SceneData":
    """``scene`` with its content box replaced by ``box`` (unchanged when None)."""
    if box is None:
        return scene
    return dataclasses.replace(scene, bbox=torch.tensor(box, dtype=torch.float32))


def _train(args: argparse.Namespace) -> int:
    """``visnerf train``: one process, or one of the ranks a launcher started (torchrun, srun),
    which train one model together and leave their process group at the end."""
    from visnerf.training.distributed import run_then_leave

    return run_then_leave(lambda: _train_as_rank(args))


class _Refused(Exception):
    """A bad input to ``visnerf train``: its message is printed as an error, exit status 2, nothing written."""


@dataclass(frozen=True)
class _Options:
    """``visnerf train``'s configurations and which of their fields the user gave."""

    train: TrainConfig
    field: FieldConfig
    render: RenderConfig
    train_given: dict
    field_given: dict
    render_given: dict


def _paths(args: argparse.Namespace) -> tuple[Path, Path, Path | None]:
    """(the checkpoint to write, its run state, the state or checkpoint to resume or None)."""
    from visnerf.training.run_state import run_state_path

    out = Path(args.out)
    if out.suffix != ".safetensors":
        raise _Refused(f"--out must end in .safetensors, got {out}")
    if out.exists() and not args.force and args.resume is None:
        raise _Refused(f"{out} exists; pass --force to overwrite it")
    state_path = run_state_path(out)
    resume = None if args.resume is None else Path(args.resume) if args.resume else state_path
    if resume is None and state_path.exists() and not args.force:
        raise _Refused(f"{state_path} holds the state of an earlier run of {out} that was stopped; pass --resume to "
                       "go on with it, or --force to start afresh (the state is then replaced)")
    if resume is not None and not resume.is_file():
        raise _Refused(f"no run state or checkpoint at {resume} to resume (a run keeps its state in {state_path} "
                       "while it trains and deletes it when it has written its checkpoint)")
    return out, state_path, resume


def _options(args: argparse.Namespace, resume: Path | None) -> _Options:
    """The configurations from the options, judged by their own checks before anything loads."""
    train_given, field_given = given_options(args, TrainConfig), given_options(args, FieldConfig)
    render_given = given_options(args, RenderConfig)
    if args.time_budget is not None:
        train_given = {"time_budget_s": args.time_budget * 60, **train_given}
    try:
        options = _Options(TrainConfig(**{"time_budget_s": None, **train_given}), FieldConfig(**field_given),
                           RenderConfig(**render_given), train_given, field_given, render_given)
    except ValueError as exc:
        raise _Refused(str(exc)) from None
    shape_given = sorted(set(field_given) - {"factor_storage"})
    if resume is not None and shape_given:
        raise _Refused(f"{', '.join('--' + k.replace('_', '-') for k in shape_given)} would change the field of "
                       f"{resume}; a resumed run keeps it")
    return options


def _data(args: argparse.Namespace) -> tuple[Any, "SceneData", "SceneData | None"]:
    """(the parsed training split, its training frames, the held-out frames or None)."""
    from visnerf.data.datasets import DatasetError, has_split, load_dataset, read_split
    from visnerf.data.holdout import split_holdout

    try:
        parsed = read_split(args.data, "train", cinema_camera(args))
        scene = with_bbox(parsed.scene, args.bbox)
        train, val = split_holdout(scene, holdout_config(scene, args))
        if val is None and has_split(args.data, "val"):
            val = load_dataset(args.data, "val")
    except (DatasetError, ValueError) as exc:
        raise _Refused(str(exc)) from None
    return parsed, train, val


def _make_trainer(options: _Options, resume: Path | None, train: "SceneData", val: "SceneData | None",
                  device: torch.device, announce: bool) -> "Trainer":
    """A trainer with the recipe chosen from the data, or going on from a run state or checkpoint."""
    from visnerf.training.run_state import RUN_STATE_SUFFIX, RunStateError
    from visnerf.training.trainer import Trainer

    try:
        if resume is None:
            from visnerf.training.recipe import recipe_trainer

            fixed = set(options.train_given) | set(options.field_given)
            if "density_shift" in options.field_given:
                fixed.add("density_scale")
            trainer = recipe_trainer(train, val, options.train, options.field, device, options.render, frozenset(fixed))
            for choice in trainer.recipe_choices if announce else ():
                print(f"  {choice['name']} = {choice['value']}: {choice['reason']}", file=sys.stderr)
        elif resume.suffix == RUN_STATE_SUFFIX:
            trainer = Trainer.from_run_state(resume, train, val, device, options.train_given, options.render_given)
            if announce:
                print(f"resuming {resume} at iteration {trainer.state.iteration} "
                      f"({trainer.state.train_seconds / 60:.1f} min trained)", file=sys.stderr)
        else:
            trainer = _trainer_from_checkpoint(resume, train, val, device, options.train_given,
                                               options.render_given, options.field_given)
    except (CheckpointError, RunStateError) as exc:
        raise _Refused(str(exc)) from None
    if "factor_storage" in options.field_given:  # storage, not shape: a resumed field may change it
        trainer.field.cfg = dataclasses.replace(trainer.field.cfg, factor_storage=options.field_given["factor_storage"])
    return trainer


def _train_as_rank(args: argparse.Namespace) -> int:
    from visnerf.training.distributed import Launch, Ranks

    try:
        out, state_path, resume = _paths(args)
        options = _options(args, resume)
        try:  # several processes (torchrun, srun): each draws its share of every batch; rank 0 writes
            ranks = Ranks.start(Launch.from_environment(), pick_device(args.device))
        except ValueError as exc:
            raise _Refused(str(exc)) from None
        parsed, train, val = _data(args)
        main = ranks.is_main
        for note in parsed.notes if main else ():
            print(f"  {note}", file=sys.stderr)
        if main:
            print(f"training on {train.n_frames} frames ({val.n_frames if val else 0} held out), "
                  f"K={train.n_params}, {train.intrinsics.width}x{train.intrinsics.height}, device {ranks.device}"
                  + (f", {ranks.world_size} ranks" if ranks.world_size > 1 else ""), file=sys.stderr)
        trainer = _make_trainer(options, resume, train, val, ranks.device, main)
    except _Refused as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    trainer.dataset_notes = list(parsed.notes)  # how the columns were read, into the checkpoint
    trainer.distribute(ranks)
    return _run_and_save(args, trainer, out, state_path)


def _run_and_save(args: argparse.Namespace, trainer: "Trainer", out: Path, state_path: Path) -> int:
    """Train until the budget or a stop; rank 0 writes the checkpoint (or, stopped, the log and the
    run state to resume from) and submits it where asked."""
    from visnerf.training.record import write_log
    from visnerf.training.stop_signals import StopRequested, StopSignals

    main = trainer.ranks.is_main
    with StopSignals() as stop:
        try:
            trainer.run(progress_bar=not args.quiet and main, on_validate=lambda row: print("  " + json.dumps(row),
                                                                                           file=sys.stderr),
                        state_path=state_path if main else None, stop=stop)
            if not main:  # rank 0 writes the checkpoint, its log and the run state
                return stop.exit_status if trainer.stopped else 0
            if not trainer.stopped:
                path = trainer.save(out, dataset=str(args.data))
        except StopRequested:  # in the final steps: the state written when the loop ended is whole
            print(f"stopped by {stop.name} in the final steps; {state_path} holds the run at the end of training: "
                  "the same command with --resume finishes it", file=sys.stderr)
            return stop.exit_status
    if trainer.stopped:
        write_log(trainer.state.log, out.with_suffix(".log.csv"))
        print(f"stopped by {stop.name} at iteration {trainer.state.iteration} "
              f"({trainer.state.train_seconds / 60:.1f} min of training); {state_path} holds the run: "
              "the same command with --resume goes on from there", file=sys.stderr)
        return stop.exit_status
    state_path.unlink(missing_ok=True)  # the checkpoint is written: the run is done
    print(f"saved {path} ({path.stat().st_size / 1e6:.2f} MB) and its log {path.with_suffix('.log.csv')}")
    if args.submit:
        from visnerf.upload import UploadError, upload_checkpoint

        try:
            done = upload_checkpoint(path, args.submit, path.name.removesuffix(".safetensors"), None)
        except UploadError as exc:
            print(f"error: {exc} (the checkpoint is saved at {path})", file=sys.stderr)
            return 1
        print(f"{'created' if done.created else 'replaced'} scene {done.scene_id!r} at {done.url}")
    return 0


def _trainer_from_checkpoint(path: Path, train: "SceneData", val: "SceneData | None", device: torch.device,
                             train_given: dict, render_given: dict, field_given: dict) -> "Trainer":
    """A run that goes on from a finished checkpoint's weights: its recipe (``provenance.recipe``)
    with the given options on top, its schedule position; the optimizer's moments and the weight
    average start afresh (a run state keeps them: ``--resume`` without a value)."""
    from visnerf.checkpoint import load_checkpoint
    from visnerf.training.schedule import TrainState
    from visnerf.training.trainer import Trainer

    init_field, meta = load_checkpoint(path, device)
    prov = meta.provenance
    try:
        cfg = TrainConfig.from_dict({**prov.recipe, **train_given})
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its recorded training configuration cannot be read back: {exc}") from None
    render_cfg = dataclasses.replace(meta.render, **render_given)  # the resumed model's, unless given
    start = TrainState(iteration=prov.iterations, train_seconds=prov.train_seconds, upsamples_done=prov.upsamples_done,
                       occupancy_done=prov.occupancy_done, refines_done=prov.refines_done)
    trainer = Trainer(train, val, cfg, device, render_cfg=render_cfg, init_field=init_field, start=start)
    trainer.recipe_choices = [dataclasses.asdict(c) for c in prov.choices]
    return trainer


def register_train(sub: argparse._SubParsersAction) -> None:
    """The ``train`` sub-command: its options from the typed configuration."""
    p = sub.add_parser("train", help="train a ViSNeRF model on a dataset folder")
    p.add_argument("data",
                   help="dataset folder with transforms_train.json, or a Cinema database (folder with data.csv)")
    p.add_argument("--out", required=True, help="checkpoint to write (.safetensors)")
    p.add_argument("--time-budget", type=positive_float, default=None, metavar="MINUTES",
                   help="wall-clock training budget; the schedule is given as fractions of it")
    add_holdout_options(p, "for validation")
    p.add_argument("--bbox", type=parse_bbox, default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="world box that holds the content (write --bbox=-1,... for negative numbers); "
                        "default: the dataset's bbox, else a box every camera sees, carved from the images")
    add_device_option(p)
    p.add_argument("--resume", nargs="?", const="", default=None, metavar="STATE|CKPT",
                   help="go on with a run. Alone: from the run state beside --out (M.resume, written every "
                        "--checkpoint-every-s seconds and when SIGTERM or Ctrl-C stops the run), exactly where it "
                        "stopped; with a .resume file: from that run state; with a checkpoint: from its weights "
                        "and schedule position, with fresh optimizer moments")
    p.add_argument("--submit", default=None, metavar="URL", help="upload the checkpoint to a server when done")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_options(p)
    add_cinema_options(p)
    p.set_defaults(func=_train, requires=("skimage",))  # SSIM of held-out frames


__all__ = ["register_train", "parse_bbox", "with_bbox"]
