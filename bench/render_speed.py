"""Render speed and quality: the plain exhaustive renderer against the fast one, and the preview.

For each checkpoint (default: checkpoints/*.safetensors, each with its dataset data/<name>_<size>/ as
made by scripts/train_bundled.sh, and runs/nyx.safetensors with ../shared/data/nyx) the same held-out
views (transforms_test.json where the dataset has one, else the hold-out of bench/nyx_train.py),
with the camera and parameters of those frames, are rendered at each size with three settings:

- plain: quality ``exhaustive``: the training sample spacing (half a voxel) within the model's
  occupancy grid (part of the model: outside it the density was never fitted), no early ray
  termination, every sample's colour decoded and float32 decoders: the exhaustive renderer;
- fast: the checkpoint's full settings (``RenderSettings.from_meta``), as the server renders (the
  checkpoint's full-quality spacing, chosen by ``evaluation.spacing`` on held-out frames, or on
  training frames when none were held out; empty-space skipping, early termination, colour decoded
  only above a weight threshold, bf16 lookups and decoders where the CPU has bf16 instructions);
- every pixel: the fast settings with every pixel marched (``refine_spacing`` 1), the fast frame
  before ``rendering.refine``; at a size where a voxel spans two pixels or more the fast frame
  marches a lattice and the cells that differ;
- preview: quality ``preview`` (half resolution, larger steps), bilinearly upsampled to the size.

Per view the three run back to back (fast, plain, preview, then the next view), so machine noise
hits all of them; one untimed render per setting and size comes first. The time is that of
``render_image`` (and the upsampling of the preview). Records ms per frame (median, p95), the PSNR
of fast and preview frames against the plain frames (from the squared error pooled over all views)
and the mean PSNR of each against ground truth, at the dataset's native image size only: frames
of another size are not resampled for it. A checkpoint or dataset that is missing or unreadable is
skipped with the reason printed and recorded.

    .venv/bin/python bench/render_speed.py
    .venv/bin/python bench/render_speed.py --threads 1 --views 20 --sizes 128,256 \\
        --checkpoints checkpoints/vortex_tf1.safetensors runs/nyx.safetensors=../shared/data/nyx

A checkpoint is given as PATH (dataset data/<file stem>/, or the one data/<file stem>_<size>/ there
is) or PATH=DATASET_FOLDER.
Writes render_speed.json, render_speed.md and render_speed.png to --out-dir (bench/results).
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    RESULTS,
    ROOT,
    evenly_spaced,
    fmt,
    held_out_frames,
    load_average,
    machine_record,
    markdown_header,
    save_figure,
    write_json,
)
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from visnerf.data.cameras import Intrinsics
from visnerf.evaluation.metrics import mse_to_psnr, psnr
from visnerf.inference import SceneRenderer, load_scene
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image_scaled
from visnerf.runtime import configure

MODES = ("fast", "fast_own", "every", "plain", "preview")
"""Render order within each view. ``fast`` marches the checkpoint's occupancy grid, the union over
its parameter space: a frame at a setting seen for the first time (a slider being dragged).
``fast_own`` is the same frame marching the grid of the view's own setting
(``rendering.setting_occupancy``, built beforehand and timed apart): what the server serves from
a setting asked for a few times (orbiting). ``every``: the fast frame with every pixel marched."""
TARGET_FULL_256_MS = 100.0
"""Full-quality 256x256 median on two threads: the target of the learning-speed issue (0.1 s; the
Nyx issue's 0.2 s before it)."""
TARGET_FULL_800_MS = 1000.0
"""Full-quality 800x800 median on two threads (the learning-speed issue)."""
TARGET_PREVIEW_128_MS = 80.0
TARGET_PSNR_DROP_DB = 0.1


@dataclass(frozen=True)
class Case:
    """One checkpoint and the dataset holding its ground truth."""

    name: str
    checkpoint: Path
    data: Path


@dataclass(frozen=True)
class Options:
    cases: tuple[Case, ...]
    views: int
    """Held-out views rendered per checkpoint and size."""
    sizes: tuple[int, ...]
    """Square image sizes (pixels per side)."""
    threads: int | None
    """Torch threads (None: visnerf's default, the usable cores or VISNERF_THREADS)."""
    out_dir: Path


@dataclass(frozen=True)
class Views:
    """The frames rendered for one checkpoint, with their ground truth."""

    c2w: torch.Tensor
    """[n, 4, 4] camera-to-world, OpenGL axes."""
    params: torch.Tensor
    """[n, k] parameters normalised by the checkpoint's axes."""
    images: torch.Tensor
    """[n, h, w, 3] uint8 ground truth at the dataset's native size."""
    intrinsics: Intrinsics
    """Camera of the dataset at its native size."""
    frame_indices: tuple[int, ...]
    split: str


@dataclass(frozen=True)
class ModeResult:
    """One setting at one size, over all views."""

    mode: str
    size: int
    render_size: int
    """Pixels per side actually marched (the preview renders smaller and upsamples)."""
    ms_median: float
    ms_p95: float
    ms: tuple[float, ...]
    psnr_vs_plain: float | None
    """From the squared error against the plain frames pooled over all views (inf: identical)."""
    max_abs_diff_vs_plain: float | None
    psnr_vs_gt: float | None
    """Mean over views; None where the size is not the dataset's native size."""


@dataclass(frozen=True)
class CaseResult:
    name: str
    checkpoint: str
    data: str
    skipped: str | None = None
    split: str = ""
    frame_indices: tuple[int, ...] = ()
    native_size: tuple[int, int] | None = None
    """(width, height) of the ground truth."""
    settings: dict[str, dict] = dataclasses.field(default_factory=dict)
    results: tuple[ModeResult, ...] = ()
    own_grid_build_ms: tuple[float, ...] = ()
    """Build time of each view's own occupancy grid (what ``SettingOccupancy`` builds)."""

    def result(self, mode: str, size: int) -> ModeResult | None:
        return next((r for r in self.results if r.mode == mode and r.size == size), None)


def default_dataset(stem: str) -> Path:
    """``data/<stem>``, or where that is missing the one ``data/<stem>_<size>`` folder there is (the
    name bench/eval_scenes.py and so scripts/train_bundled.sh give a dataset); ``data/<stem>`` when
    there are none or several, so that the skip names it."""
    plain = ROOT / "data" / stem
    sized = [p for p in (ROOT / "data").glob(f"{stem}_*") if p.is_dir() and p.name[len(stem) + 1:].isdigit()]
    return sized[0] if not plain.is_dir() and len(sized) == 1 else plain


def parse_case(spec: str) -> Case:
    """``PATH`` (dataset ``default_dataset(stem)``) or ``PATH=DATASET``."""
    path, _, data = spec.partition("=")
    checkpoint = Path(path)
    return Case(checkpoint.stem, checkpoint, Path(data) if data else default_dataset(checkpoint.stem))


def default_cases() -> tuple[Case, ...]:
    bundled = [parse_case(str(p)) for p in sorted((ROOT / "checkpoints").glob("*.safetensors"))]
    nyx = Case("nyx", ROOT / "runs" / "nyx.safetensors", ROOT.parent / "shared" / "data" / "nyx")
    return (*bundled, nyx)


def render_settings(scene: SceneRenderer) -> dict[str, RenderSettings]:
    full = RenderSettings.from_meta(scene.meta, "full")
    plain = RenderSettings.from_meta(scene.meta, "exhaustive")
    return {"fast": full, "fast_own": full, "every": dataclasses.replace(full, refine_spacing=1), "plain": plain,
            "preview": RenderSettings.from_meta(scene.meta, "preview")}


def load_views(scene: SceneRenderer, folder: Path, count: int) -> Views:
    """``count`` evenly spaced held-out frames; their parameters checked against the checkpoint's ranges."""
    frames, split = held_out_frames(folder)
    idx = evenly_spaced(frames.n_frames, count)
    columns = {a.name: k for k, a in enumerate(frames.param_axes)}
    missing = [a.name for a in scene.info.params if a.name not in columns]
    if missing:
        raise ValueError(f"{folder} ({split}) does not vary parameter(s) {missing} of the checkpoint")
    rows = []
    for i in idx:
        raw = {a.name: float(frames.params[i, columns[a.name]]) for a in scene.info.params}
        values = scene.resolve_params(raw)  # raises naming a value outside the trained range
        rows.append([axis.normalize(v) for axis, v in zip(scene.meta.param_axes, values, strict=True)])
    params = torch.tensor(rows, dtype=torch.float32).reshape(len(idx), len(scene.info.params))
    sel = torch.tensor(idx)
    return Views(frames.c2w[sel].clone(), params, frames.images[sel].clone(), frames.intrinsics, tuple(idx), split)


def render_frame(
    scene: SceneRenderer, c2w: torch.Tensor, intrinsics: Intrinsics, params: torch.Tensor,
    settings: RenderSettings, size: int, empty_space: EmptySpace | None = None,
) -> tuple[np.ndarray, float]:
    """One ``size`` x ``size`` frame (float [0, 1]) and the seconds it took; ``empty_space``
    replaces the checkpoint's union grid."""
    cam = intrinsics.scaled(size, size)
    t0 = time.perf_counter()
    with torch.inference_mode():
        rgb = render_image_scaled(scene.field, c2w.to(scene.device), cam, params.to(scene.device), settings,
                                  empty_space)
    seconds = time.perf_counter() - t0
    return rgb.clamp(0, 1).cpu().numpy().astype(np.float32), seconds


def own_grids(
    scene: SceneRenderer, views: Views, settings: RenderSettings
) -> tuple[list[EmptySpace | None], list[float]]:
    """Each view's own occupancy grid (None where the checkpoint has no grid) and ms to build it."""
    if scene.field.occupancy is None:
        return [None] * views.c2w.shape[0], []
    grids, ms = [], []
    step = scene.field.voxel_size() * settings.step_ratio
    for v in range(views.c2w.shape[0]):
        t0 = time.perf_counter()
        grids.append(scene.setting_occupancy.build(views.params[v].to(scene.device), step))
        ms.append(1000.0 * (time.perf_counter() - t0))
    return grids, ms


def time_size(
    scene: SceneRenderer, views: Views, settings: dict[str, RenderSettings], size: int,
    own: list[EmptySpace | None],
) -> tuple[dict[str, list[float]], dict[str, list[np.ndarray]]]:
    """ms and frames of every mode at ``size``, interleaved per view (``own``: each view's grid)."""
    for mode in MODES:  # warm-up: allocator and caches, not timed
        render_frame(scene, views.c2w[0], views.intrinsics, views.params[0], settings[mode], size,
                     own[0] if mode == "fast_own" else None)
    ms: dict[str, list[float]] = {m: [] for m in MODES}
    frames: dict[str, list[np.ndarray]] = {m: [] for m in MODES}
    for v in range(views.c2w.shape[0]):
        for mode in MODES:
            img, seconds = render_frame(scene, views.c2w[v], views.intrinsics, views.params[v], settings[mode], size,
                                        own[v] if mode == "fast_own" else None)
            ms[mode].append(1000.0 * seconds)
            frames[mode].append(img)
    return ms, frames


def summarize(
    mode: str, size: int, settings: RenderSettings, ms: list[float], frames: list[np.ndarray],
    plain: list[np.ndarray], truth: list[np.ndarray] | None,
) -> ModeResult:
    vs_plain = max_diff = None
    if mode != "plain":
        sq = [np.mean((a.astype(np.float64) - b) ** 2) for a, b in zip(frames, plain, strict=True)]
        vs_plain = mse_to_psnr(float(np.mean(sq)))
        max_diff = float(max(np.abs(a - b).max() for a, b in zip(frames, plain, strict=True)))
    vs_gt = None
    if truth is not None:
        vs_gt = float(np.mean([psnr(a, b) for a, b in zip(frames, truth, strict=True)]))
    return ModeResult(
        mode=mode, size=size, render_size=max(1, round(size * settings.resolution_scale)),
        ms_median=float(np.median(ms)), ms_p95=float(np.percentile(ms, 95)), ms=tuple(round(t, 2) for t in ms),
        psnr_vs_plain=vs_plain, max_abs_diff_vs_plain=max_diff, psnr_vs_gt=vs_gt,
    )


def measure_case(case: Case, opts: Options) -> CaseResult:
    scene = load_scene(case.checkpoint, torch.device("cpu"))
    views = load_views(scene, case.data, opts.views)
    settings = render_settings(scene)
    native = (views.intrinsics.width, views.intrinsics.height)
    truth_all = [im.numpy().astype(np.float32) / 255.0 for im in views.images]
    results: list[ModeResult] = []
    own, build_ms = own_grids(scene, views, settings["fast"])
    for size in opts.sizes:
        t0 = time.perf_counter()
        ms, frames = time_size(scene, views, settings, size, own)
        truth = truth_all if (size, size) == native else None
        results += [summarize(m, size, settings[m], ms[m], frames[m], frames["plain"], truth) for m in MODES]
        line = ", ".join(f"{m} {np.median(ms[m]):.1f} ms" for m in MODES)
        print(f"  {case.name} {size}x{size}: {line} (median of {len(views.frame_indices)}; "
              f"{time.perf_counter() - t0:.0f} s)", flush=True)
    return CaseResult(
        name=case.name, checkpoint=str(case.checkpoint), data=str(case.data), split=views.split,
        frame_indices=views.frame_indices, native_size=native,
        settings={m: dataclasses.asdict(s) for m, s in settings.items()}, results=tuple(results),
        own_grid_build_ms=tuple(round(t, 1) for t in build_ms),
    )


def run_case(case: Case, opts: Options) -> CaseResult:
    """``measure_case``, or a skipped row with the reason: never stops the other checkpoints."""
    reason = None
    if not case.checkpoint.is_file():
        reason = f"checkpoint {case.checkpoint} does not exist"
    elif not case.data.is_dir():
        reason = f"dataset folder {case.data} does not exist"
    if reason is None:
        try:
            return measure_case(case, opts)
        except (OSError, ValueError) as exc:  # unreadable checkpoint or dataset, parameters that do not fit
            reason = f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # anything else: recorded with its traceback; the other checkpoints still run
            traceback.print_exc(file=sys.stderr)
            reason = f"{type(exc).__name__}: {exc}"
    print(f"  skipped {case.name}: {reason}", flush=True)
    return CaseResult(case.name, str(case.checkpoint), str(case.data), skipped=reason)


def ratio(a: ModeResult | None, b: ModeResult | None) -> float | None:
    return None if a is None or b is None or b.ms_median <= 0 else a.ms_median / b.ms_median


def psnr_delta(case: CaseResult, size: int) -> float | None:
    """PSNR against ground truth of fast minus plain at ``size`` (None off the native size)."""
    fast, plain = case.result("fast", size), case.result("plain", size)
    if fast is None or plain is None or fast.psnr_vs_gt is None or plain.psnr_vs_gt is None:
        return None
    return fast.psnr_vs_gt - plain.psnr_vs_gt


def table_rows(case: CaseResult, sizes: tuple[int, ...]) -> list[str]:
    if case.skipped:
        return [f"| {case.name} | skipped: {case.skipped} |" + " |" * 12]
    rows = []
    for size in sizes:
        plain, fast, prev, every = (case.result(m, size) for m in ("plain", "fast", "preview", "every"))
        if plain is None or fast is None or prev is None or every is None:
            continue
        own = case.result("fast_own", size)
        gt = " / ".join(fmt(r.psnr_vs_gt, 2) for r in (plain, fast, prev))
        rows.append(
            f"| {case.name} | {size}x{size} | {fmt(plain.ms_median)} / {fmt(plain.ms_p95)} | "
            f"{fmt(fast.ms_median)} / {fmt(fast.ms_p95)} | {fmt(ratio(plain, fast), 2)} | "
            f"{fmt(own.ms_median if own else None)} / {fmt(own.ms_p95 if own else None)} "
            f"({fmt(ratio(fast, own), 2)}x) | "
            f"{fmt(every.ms_median)} ({fmt(ratio(every, fast), 2)}x, {fmt(every.psnr_vs_plain, 2)} dB) | "
            f"{fmt(prev.ms_median)} / {fmt(prev.ms_p95)} ({prev.render_size}px) | {fmt(ratio(plain, prev), 2)} | "
            f"{fmt(fast.psnr_vs_plain, 2)} | {fmt(fast.max_abs_diff_vs_plain, 4)} | {fmt(prev.psnr_vs_plain, 2)} | "
            f"{gt} | {fmt(psnr_delta(case, size), 3)} |"
        )
    return rows


def target_rows(case: CaseResult) -> list[str]:
    """Each target against what was measured (only where the measurement exists)."""
    if case.skipped:
        return []
    fast256, prev128, own256 = case.result("fast", 256), case.result("preview", 128), case.result("fast_own", 256)
    fast800 = case.result("fast", 800)
    native = case.native_size[0] if case.native_size and case.native_size[0] == case.native_size[1] else None
    delta = psnr_delta(case, native) if native else None

    def verdict(ok: bool | None) -> str:
        return "-" if ok is None else ("met" if ok else "not met")

    full_ok = None if fast256 is None else fast256.ms_median <= TARGET_FULL_256_MS
    prev_ok = None if prev128 is None else prev128.ms_median <= TARGET_PREVIEW_128_MS
    delta_ok = None if delta is None else delta >= -TARGET_PSNR_DROP_DB
    big_ok = None if fast800 is None else fast800.ms_median <= TARGET_FULL_800_MS
    return [
        f"| {case.name} | {fmt(fast256.ms_median if fast256 else None)} ms: {verdict(full_ok)} | "
        f"{fmt(own256.ms_median if own256 else None)} ms | "
        f"{fmt(delta, 3)} dB at {native or '-'}px: {verdict(delta_ok)} | "
        f"{fmt(fast256.psnr_vs_plain if fast256 else None, 2)} dB | "
        f"{fmt(prev128.ms_median if prev128 else None)} ms: {verdict(prev_ok)} | "
        f"{fmt(fast800.ms_median if fast800 else None)} ms: {verdict(big_ok)} | "
        f"{fmt(fast800.psnr_vs_plain if fast800 else None, 2)} dB |"
    ]


def write_markdown(path: Path, record: dict, cases: list[CaseResult], sizes: tuple[int, ...]) -> None:
    lines = [
        *markdown_header("Render speed: plain exhaustive renderer against the fast one", record),
        "",
        f"{record['views']} held-out views per checkpoint (camera and parameters of those frames), rendered at each "
        "size by each setting, interleaved per view (fast, own grid, every pixel, plain, preview), one untimed warm-up render per setting "
        "and size first. ms per frame: median / p95 of the render call (the preview's upsampling included). "
        "\"Own grid\": the fast setting marching the occupancy grid of the view's own parameter setting instead of "
        "the union over the parameter space, as the server does once a setting has been asked for a few times "
        "(fast / own grid in brackets; the grids' build is timed apart, below the table). \"Every pixel\": the fast "
        "setting with every pixel marched, where the fast frame marches a lattice and the cells that differ "
        "(``rendering.refine``) once a voxel spans two pixels or more. "
        "Ratios are plain median / other median. PSNR against plain pools the squared error of all views "
        "(\"identical\": no difference at all); max |diff| is the largest channel difference in [0, 1]. PSNR against "
        "ground truth is the mean over views and is given only at the dataset's native image size (the frames "
        "are not resampled for it); delta = fast minus plain, against ground truth.",
        "",
        "| checkpoint | size | plain ms | fast ms | plain/fast | fast, own grid ms "
        "| every pixel ms (every / fast, vs plain) | preview ms "
        "| plain/preview | fast vs plain dB | fast max abs diff | preview vs plain dB "
        "| vs ground truth dB: plain / fast / preview | delta dB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for case in cases:
        lines += table_rows(case, sizes)
    builds = [c for c in cases if c.own_grid_build_ms]
    if builds:
        lines += ["", "Own grids, ms to build one (median / p95 over the views): " + "; ".join(
            f"{c.name} {fmt(float(np.median(c.own_grid_build_ms)))} / "
            f"{fmt(float(np.percentile(c.own_grid_build_ms, 95)))}" for c in builds) + "."]
    lines += [
        "",
        f"Targets: full quality 256x256 median at most {TARGET_FULL_256_MS:.0f} ms, within "
        f"{TARGET_PSNR_DROP_DB} dB of the plain renderer (against ground truth, at the native size), "
        f"preview 128x128 median at most {TARGET_PREVIEW_128_MS:.0f} ms, full quality 800x800 median at most "
        f"{TARGET_FULL_800_MS:.0f} ms (no ground truth at that size: the fast frame against the plain one).",
        "",
        "| checkpoint | fast 256x256 median | with the setting's own grid | fast minus plain vs ground truth "
        "| fast vs plain at 256x256 | preview 128x128 median | fast 800x800 median | fast vs plain at 800x800 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for case in cases:
        lines += target_rows(case)
    lines += ["", "Datasets and frames:", ""]
    for case in cases:
        if case.skipped:
            lines.append(f"- {case.name}: skipped, {case.skipped}")
        else:
            w, h = case.native_size or (0, 0)
            lines.append(f"- {case.name}: `{case.checkpoint}`, ground truth `{case.data}` {case.split}, "
                         f"{w}x{h}, frames {list(case.frame_indices)}")
    lines += ["", "![PSNR against ms per frame](render_speed.png)", ""]
    path.write_text("\n".join(lines))


def plot(path: Path, cases: list[CaseResult]) -> None:
    """PSNR against median ms per frame: against ground truth (native size) and against plain."""
    fig = Figure(figsize=(12, 4.6), layout="constrained")
    ax_gt, ax_plain = fig.subplots(1, 2)
    markers = {"plain": "s", "fast": "o", "fast_own": "D", "every": "x", "preview": "^"}
    colours = [f"C{i}" for i in range(10)]
    measured = [c for c in cases if not c.skipped]
    for i, case in enumerate(measured):
        colour = colours[i % len(colours)]
        for r in case.results:
            label = f"{case.name} {r.mode}"
            if r.psnr_vs_gt is not None:
                ax_gt.scatter(r.ms_median, r.psnr_vs_gt, marker=markers[r.mode], color=colour, label=label)
            if r.psnr_vs_plain is not None and math.isfinite(r.psnr_vs_plain):
                ax_plain.scatter(r.ms_median, r.psnr_vs_plain, marker=markers[r.mode], color=colour,
                                 label=f"{label} {r.size}px")
                ax_plain.annotate(f"{r.size}", (r.ms_median, r.psnr_vs_plain), fontsize=7,
                                  xytext=(3, 3), textcoords="offset points")
    for ax, title in ((ax_gt, "against ground truth (native size)"), (ax_plain, "fast and preview against plain")):
        ax.axvline(TARGET_PREVIEW_128_MS, color="gray", ls=":", lw=0.8, label="preview 128px target")
        ax.axvline(TARGET_FULL_256_MS, color="gray", ls="--", lw=0.8, label="full 256px target")
        ax.axvline(TARGET_FULL_800_MS, color="gray", ls="-.", lw=0.8, label="full 800px target")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("ms per frame (median)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize="medium")
        ax.grid(alpha=0.3)
    ax_gt.legend(fontsize="x-small", loc="best")
    handles, labels = ax_plain.get_legend_handles_labels()
    ax_plain.legend(handles, labels, fontsize="x-small", loc="center left", bbox_to_anchor=(1.02, 0.5), ncol=1)
    save_figure(fig, path)


def parse_args(argv: list[str] | None = None) -> Options:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", default=None, metavar="PATH[=DATASET]",
                    help="checkpoints to measure (default: checkpoints/*.safetensors and runs/nyx.safetensors)")
    ap.add_argument("--views", type=int, default=20, help="held-out views per checkpoint (default 20)")
    ap.add_argument("--sizes", default="128,256", help="square image sizes, comma separated (default 128,256)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the usable cores)")
    ap.add_argument("--out-dir", default=str(RESULTS), help="results folder (default bench/results)")
    args = ap.parse_args(argv)
    if args.views < 1:
        ap.error("--views must be at least 1")
    sizes = tuple(int(s) for s in args.sizes.split(",") if s.strip())
    if not sizes or min(sizes) < 2:
        ap.error("--sizes needs sizes of at least 2 pixels")
    cases = tuple(parse_case(s) for s in args.checkpoints) if args.checkpoints else default_cases()
    return Options(cases, args.views, sizes, args.threads, Path(args.out_dir))


def main(argv: list[str] | None = None) -> int:
    opts = parse_args(argv)
    configure(opts.threads)
    record = {"command": "python bench/render_speed.py " + " ".join(sys.argv[1:]), **machine_record(),
              "views": opts.views, "sizes": list(opts.sizes)}
    before = load_average()
    cases = []
    for case in opts.cases:
        print(f"{case.name}: {case.checkpoint} with {case.data}", flush=True)
        cases.append(run_case(case, opts))
    record["load_average_1min"] = {"before": before, "after": load_average()}
    record["cases"] = [dataclasses.asdict(c) for c in cases]
    opts.out_dir.mkdir(parents=True, exist_ok=True)
    write_json(opts.out_dir / "render_speed.json", record)
    write_markdown(opts.out_dir / "render_speed.md", record, cases, opts.sizes)
    plot(opts.out_dir / "render_speed.png", cases)
    print(f"wrote {opts.out_dir / 'render_speed.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
