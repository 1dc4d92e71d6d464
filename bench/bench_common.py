"""Helpers shared by the benchmarks (not a benchmark itself).

The hold-out of the Nyx benchmarks, their shared options, alternating step timing, evaluation
frames of a dataset, the machine record, JSON without NaN/inf, and a figure writer.
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import json
import math
import os
import platform
import re
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from visnerf.checkpoint import load_checkpoint
from visnerf.config import HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.data.scene import SceneData
from visnerf.evaluation.plots import save_figure  # noqa: F401 - the benchmarks take it from here
from visnerf.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
HOLDOUT_SETTINGS = ((0.12, 0.0235, 0.625), (0.1375, 0.0215, 0.775), (0.1375, 0.0225, 0.7), (0.155, 0.0225, 0.625))
"""Whole Nyx parameter settings held out from training (interpolation between training settings)."""
HOLDOUT_VIEWS = (5, 17, 29, 40)
"""Views (icosphere order) held out at every other setting."""


HOLDOUT_PROTOCOLS = ("middle", "standard")
"""The hold-outs of bench/nyx_train.py (``--holdout``): ``standard``, views and settings
(``holdout_for``), and ``middle``, those and the middle value of one axis (``middle_holdout``)."""


def holdout_for(scene: SceneData) -> HoldoutConfig:
    """The standard hold-out of bench/nyx_train.py and bench/train_speed.py: views 5, 17, 29 and
    40 at every setting, plus the four whole Nyx parameter settings where the dataset has that many
    parameters (a setting that matches no frame holds nothing out)."""
    settings = tuple(s for s in HOLDOUT_SETTINGS if len(s) == scene.n_params)
    return HoldoutConfig(views=HOLDOUT_VIEWS, settings=settings)


def middle_value(scene: SceneData, axis: str | None = None) -> tuple[int, float]:
    """(axis index, value): the middle sampled value of the parameter named ``axis``, or, without
    a name, of the first axis with an odd count of values (3 or more). ValueError naming the axes
    when the named one does not exist or has no single middle value, or when no axis has one."""
    counts = ", ".join(f"{a.name} ({len(a.values)} values)" for a in scene.param_axes) or "none"
    names = [a.name for a in scene.param_axes]
    if axis is None:
        odd = [k for k, a in enumerate(scene.param_axes) if len(a.values) % 2 == 1 and len(a.values) >= 3]
        if not odd:
            raise ValueError(f"no parameter axis has an odd count of 3 or more values, so none has a middle one: {counts}")
        k = odd[0]
    elif axis not in names:
        raise ValueError(f"no parameter axis {axis!r}; this dataset's: {counts}")
    else:
        k = names.index(axis)
    values = scene.param_axes[k].values
    if len(values) % 2 == 0 or len(values) < 3:
        raise ValueError(f"parameter {names[k]!r} has {len(values)} values, so no single middle one; "
                         f"the axes: {counts}")
    return k, values[len(values) // 2]


def middle_holdout(scene: SceneData, axis: str | None = None) -> HoldoutConfig:
    """The standard hold-out (``holdout_for``) and every frame at the middle value of one axis
    (``middle_value``): training keeps only the values on either side of it, and the held-out
    frames at it measure the model between sampled values, where the test path goes."""
    return replace(holdout_for(scene), axis_values=(middle_value(scene, axis),))


def nyx_split(data: str | Path) -> tuple[SceneData, SceneData]:
    """(training, held-out) frames of the Nyx dataset at ``data``, split as bench/nyx_train.py
    --holdout standard does (its held-out frames are held out by ``--holdout middle`` too)."""
    scene = load_dataset(Path(data))
    train, val = split_holdout(scene, holdout_for(scene))
    if val is None:
        raise ValueError(f"{data}: the Nyx hold-out leaves no frames out")
    return train, val


def add_trained_model_args(ap: argparse.ArgumentParser, checkpoint: str) -> None:
    """``--checkpoint`` (default ``runs/<checkpoint>``), ``--data`` (shared/data/nyx) and
    ``--results`` of the benchmarks that measure a trained Nyx model."""
    ap.add_argument("--checkpoint", default=str(ROOT / "runs" / checkpoint))
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "nyx"))
    ap.add_argument("--results", default=str(RESULTS))


def require_checkpoint(ap: argparse.ArgumentParser, path: str | Path) -> None:
    """Stop with a usage error, before any data loads, when the ``--checkpoint`` file is missing."""
    if not Path(path).is_file():
        ap.error(f"{path} does not exist: train one with bench/nyx_train.py, or pass --checkpoint")


def add_step_timing_args(ap: argparse.ArgumentParser, steps: int, per: str) -> None:
    """``--rounds``, ``--steps`` and ``--micro-batch-samples`` of the benchmarks that time
    training steps of several configurations in turn."""
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=steps, help=f"steps per {per} and round")
    ap.add_argument("--micro-batch-samples", type=int, default=65536)


def alternate_steps(
    trainers: dict[Any, Any],
    rounds: int,
    steps: int,
    after_step: Callable[[Any], None] | None = None,
    before_step: Callable[[Any], None] | None = None,
    warm_up: bool = False,
) -> tuple[dict[Any, list[float]], dict[Any, list[dict[str, float]]]]:
    """``steps`` training steps of each trainer in turn, ``rounds`` times, so that all share the
    machine's noise: per key, the milliseconds of each step and what each ``train_step`` returned.
    ``before_step(key)`` and ``after_step(key)`` run before and after each step, outside its time
    (the way to give trainers that share a field or a trainer their own setting). With ``warm_up``,
    each trainer first takes one untimed step, after its ``before_step`` (oneDNN builds its kernels
    on first use), so that the warm-up runs each trainer's own setting."""
    times: dict[Any, list[float]] = {k: [] for k in trainers}
    outputs: dict[Any, list[dict[str, float]]] = {k: [] for k in trainers}
    if warm_up:
        for key, trainer in trainers.items():
            if before_step is not None:
                before_step(key)
            trainer.train_step()
    for _ in range(rounds):
        for key, trainer in trainers.items():
            for _ in range(steps):
                if before_step is not None:
                    before_step(key)
                t0 = time.perf_counter()
                outputs[key].append(trainer.train_step())
                times[key].append(1000 * (time.perf_counter() - t0))
                if after_step is not None:
                    after_step(key)
    return times, outputs


def step_time_summary(ms: list[float]) -> dict[str, float]:
    """Median, fastest and slowest of a list of step times (ms)."""
    return {"median_ms": statistics.median(ms), "min_ms": min(ms), "max_ms": max(ms)}


def held_out_frames(folder: Path) -> tuple[SceneData, str]:
    """Frames the models were not trained on, and where they came from.

    ``transforms_test.json`` if the dataset has one, else ``transforms_val.json``, else the
    training split's hold-out (``holdout_for``).
    """
    for split in ("test", "val"):
        if (folder / f"transforms_{split}.json").is_file():
            return load_dataset(folder, split), f"transforms_{split}.json"
    scene = load_dataset(folder, "train")
    holdout = holdout_for(scene)
    _, val = split_holdout(scene, holdout)
    if val is None:
        raise ValueError(f"{folder}: the hold-out {holdout} matches no training frame")
    return val, f"transforms_train.json held out (views {holdout.views}, {len(holdout.settings)} settings)"


def evenly_spaced(n_frames: int, count: int) -> list[int]:
    """``count`` frame indices spread evenly over ``n_frames`` (fewer if there are fewer frames)."""
    return np.unique(np.linspace(0, n_frames - 1, min(count, n_frames)).round().astype(int)).tolist()


def render_frame(scene: Any, frames: SceneData, i: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``i`` of ``frames`` rendered by ``scene`` (``inference.load_scene``) at its camera
    and parameters, and its ground truth: float32 ``[height, width, 3]`` in [0, 1] each."""
    names = [a.name for a in scene.info.params]
    params = dict(zip(names, frames.params[i].tolist(), strict=True))
    k = frames.intrinsics
    lens = (None, k.view_height) if k.orthographic else (k.fov_x_deg, None)
    img = scene.render(frames.c2w[i].double().numpy(), lens[0], width, height, params, view_height=lens[1])
    return img.astype(np.float32) / 255.0, frames.images[i].numpy().astype(np.float32) / 255.0


def load_average() -> float:
    return round(os.getloadavg()[0], 2)


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU's model name, family and model numbers and its bfloat16 units, from /proc/cpuinfo
    (or ``cpuinfo``): the machines behind these benchmarks have differed between sessions (an Intel
    Xeon with AMX, AMD EPYCs without), and a figure from one is not comparable with a figure from
    another. A virtual machine may name only the vendor's line ("AMD EPYC"); the family and model
    still tell its generations apart (on AMD, family 25 is Zen 3 and 4, family 26 Zen 5)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() not in fields:
            fields[key.strip()] = value.strip()
    name = fields.get("model name") or platform.processor() or platform.machine()
    flags = set(fields.get("flags", "").split())
    if not flags:
        return name
    units = ["AMX bf16" if "amx_bf16" in flags else "no AMX"]
    if "avx512_bf16" in flags:
        units.append("AVX-512 bf16")
    family, model = fields.get("cpu family"), fields.get("model")
    if family and model:
        units.insert(0, f"family {family} model {model}")
    return f"{name} ({', '.join(units)})"


def machine_record() -> dict[str, Any]:
    return {
        "machine": f"{cpu_description()}, {os.cpu_count()} CPU cores, "
                   f"{'CUDA' if torch.cuda.is_available() else 'no GPU'}",
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }


def finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, recursively (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_none(v) for v in value]
    return value


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(finite_or_none(data), indent=1, allow_nan=False) + "\n")


def write_results(out_dir: Path, stem: str, record: dict[str, Any],
                  write_markdown: Callable[[Path, dict[str, Any]], None]) -> None:
    """``out_dir/stem.json`` (non-finite numbers as null) and ``out_dir/stem.md``, and say where."""
    write_json(out_dir / f"{stem}.json", record)
    write_markdown(out_dir / f"{stem}.md", record)
    print(f"results -> {out_dir / stem}.json and .md", file=sys.stderr)


def fmt(value: float | None, digits: int = 1) -> str:
    """A number for a Markdown table; a dash for a missing one."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if math.isinf(value):
        return "identical" if value > 0 else "-inf"
    return f"{value:.{digits}f}"


def table_cell(value: object, digits: int) -> str:
    """A Markdown table cell: a float to ``digits`` decimals, ``n/a`` for a missing value, anything
    else as it prints (a count, a name)."""
    return f"{value:.{digits}f}" if isinstance(value, float) else ("n/a" if value is None else str(value))


def replace_marked_section(text: str, begin: str, end: str, body: str) -> str | None:
    """``text`` with its section from the marker line ``begin`` to ``end`` (both kept) holding
    ``body`` instead; None where ``text`` has no such section."""
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        return None
    return pattern.sub(lambda _: f"{begin}\n{body}\n{end}", text, count=1)


def markdown_header(title: str, record: dict[str, Any]) -> list[str]:
    """Title, command and machine lines of a benchmark's Markdown report, from a record holding
    ``machine_record()``, ``command`` and ``load_average_1min`` (``before``, optional ``between``,
    ``after``)."""
    load = record["load_average_1min"]
    between = f"{load['between']} between the runs, " if "between" in load else ""
    return [
        f"# {title}",
        "",
        f"Command: `{record['command']}`  ",
        f"Machine: {record['machine']}, torch {record['torch']}, {record['torch_threads']} torch thread(s), "
        f"{record['date']}; 1-min load average {load['before']} before, {between}{load['after']} after.",
    ]


def late_trainer(ckpt: Path, scene: SceneData, batch_rays: int, fused: bool | None = None,
                 device: torch.device | None = None) -> Trainer:
    """A trainer that steps the trained field of ``ckpt`` on ``scene`` as the late phase of its run:
    the recipe the checkpoint records (its priors and step), no milestones left. ``fused``: the
    trainer's step (None: the device's own)."""
    device = device or torch.device("cpu")
    field, meta = load_checkpoint(ckpt, device)
    res = max(field.resolution)
    recipe = dict(meta.provenance.recipe)
    late = dict(iterations=10**9, time_budget_s=None, resolution_init=res, resolution_final=res, upsample_at=(),
                occupancy_at=(), occupancy_refine_at=(), trim_every=10**9, batch_rays=batch_rays,
                l1_switch_iteration=0, weight_average_span=0.0)
    cfg = TrainConfig.from_dict({**recipe, **late})
    return Trainer(scene, None, cfg, device, render_cfg=dataclasses.replace(meta.render), init_field=field,
                   fused=fused)
