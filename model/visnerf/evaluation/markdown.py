"""The Markdown report of an evaluation, written from its summary document (see ``report.py``)."""


def _num(value: object, digits: int = 2) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _metrics_row(name: str, group: dict) -> str:
    return (f"| {name} | {group['n']} | {_num(group['psnr'])} | {_num(group['ssim'], 4)} | "
            f"{_num(group['lpips'], 4)} | {_num(group['delta_e_mean'])} | {_num(group['ms_median'], 1)} |")


def _summary(s: dict) -> list[str]:
    m = s["metrics"]
    lpips = _num(m["lpips"], 4) if m["lpips"] is not None else f"not computed: {m['lpips_note']}"
    return [
        "## Summary",
        "",
        "| frames | PSNR (dB) | SSIM | LPIPS | mean ΔE*uv | ms per frame (median) | model MB |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        f"| {m['n']} | {_num(m['psnr'])} | {_num(m['ssim'], 4)} | {_num(m['lpips'], 4)} | "
        f"{_num(m['delta_e_mean'])} | {_num(m['ms_median'], 1)} | {_num(s['model_mb'], 3)} |",
        "",
        f"LPIPS: {lpips}.",
        "",
        f"Notes: {m['note']}. Per frame: [frames.csv](frames.csv).",
        "",
        f"![PSNR and render time per frame]({s['figures']['per_frame']})",
        "",
    ]


def _parameter_space(s: dict) -> list[str]:
    p = s["parameter_space"]
    lines = [
        "## Error by place in parameter space",
        "",
        "| frames | n | PSNR (dB) | SSIM | LPIPS | mean ΔE*uv | ms (median) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    lines += [_metrics_row(g["description"], g) for g in p["groups"].values()]
    empty = [g["description"] for g in p["groups"].values() if g["n"] == 0]
    lines += ["", f"Note: {p['note']}."]
    if empty:
        lines += ["", f"No frame of this split falls in: {'; '.join(empty)}."]
    return [*lines, ""]


def _differences(s: dict) -> list[str]:
    d = s["differences"]
    lines = [
        "## Difference images (CIELUV)",
        "",
        f"{d['metric']} in {d['space']}, mapped through one fixed legend from 0 to "
        f"{_num(d['scale_max'], 0)} (larger values take the top colour):",
        "",
        f"![legend]({d['legend']})",
        "",
        "| frame | chosen as | PSNR (dB) | mean ΔE*uv | 95th pct | max | images |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for f in d["frames"]:
        links = ", ".join(f"[{k}]({v})" for k, v in f["images"].items())
        lines.append(f"| {f['frame']} | {f['reason']} | {_num(f['psnr'])} | {_num(f['delta_e_mean'])} | "
                     f"{_num(f['delta_e_p95'])} | {_num(f['delta_e_max'])} | {links} |")
    lines.append("")
    lines += [f"![difference, frame {f['frame']}]({f['figure']})\n" for f in d["frames"]]
    return lines


def _render_sweep(s: dict) -> list[str]:
    r = s["render_sweep"]
    lines = ["## Error against render time", ""]
    if not r["points"]:
        return [*lines, "The render-settings sweep was not run.", ""]
    lines += [
        f"Each setting renders the same {r['frames']} frame(s); PSNR and SSIM are their means, the time their "
        "median. On the Pareto front: no other setting is both as fast and as accurate. "
        f"Data: [{r['data']}]({r['data']}).",
        "",
        "| setting | step (voxels) | skipping | early stop | scale | PSNR (dB) | SSIM | ms per frame | Pareto |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in r["points"]:
        stop = f"T < {p['early_stop_eps']:g}" if p["early_termination"] else "off"
        lines.append(f"| {p['name']} | {p['step_ratio']:g} | {_num(p['use_occupancy'])} | {stop} | "
                     f"{p['resolution_scale']:g} | {_num(p['psnr'])} | {_num(p['ssim'], 4)} | "
                     f"{_num(p['ms_median'], 1)} | {'yes' if p['on_front'] else ''} |")
    return [*lines, "", f"![PSNR against milliseconds per frame]({r['figure']})", ""]


def _training(s: dict) -> list[str]:
    t = s["training"]
    lines = ["## Error against training time", ""]
    if t["note"]:
        lines += [f"Note: {t['note']}.", ""]
    if not t["runs"]:
        return [*lines, "No training log to plot (pass `--train-log PATH` for other runs).", ""]
    lines += [
        f"PSNR against training time (validation excluded) from the training logs. Data: [{t['data']}]({t['data']}).",
        "",
        "| run | metric | points | training minutes | final PSNR (dB) | best PSNR (dB) | final SSIM |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in t["runs"]:
        lines.append(f"| {r['name']} | {r['metric']} | {r['points']} | {_num(r['train_minutes'], 2)} | "
                     f"{_num(r['final_psnr'])} | {_num(r['best_psnr'])} | {_num(r['final_ssim'], 4)} |")
    return [*lines, "", f"![validation PSNR against training time]({t['figure']})", ""]


def render_markdown(s: dict) -> str:
    """The whole report."""
    scene = s["scene"]
    axes = ", ".join(f"{a['name']} [{a['min']:g}, {a['max']:g}] ({len(a['values'])} training values)"
                     for a in scene["param_axes"]) or "none (static scene)"
    head = [
        f"# Evaluation: {scene['title'] or s['checkpoint']}",
        "",
        f"- checkpoint: `{s['checkpoint']}` ({_num(s['model_mb'], 3)} MB), {scene['kind']}, K = {scene['K']}: {axes}",
        f"- ground truth: `{s['data']}`, split `{s['split']}`",
        f"- rendering: {s['quality']} quality on {s['device']}, {s['torch_threads']} torch thread(s)",
        "",
    ]
    body = _summary(s) + _parameter_space(s) + _differences(s) + _render_sweep(s) + _training(s)
    return "\n".join(head + body)
