"""The report of Nyx training runs made side by side: two or more `bench/nyx_train.py` runs started
together on the same machine (``--threads 1`` each), so that they share its noise, which runs from
different sessions do not (the machines have differed between sessions: an AMD EPYC without AMX
traced Nyx rays at half the rate of the machine of an earlier session).

It reads each run's nyx_train.json and writes, into the folder that holds the runs, a README.md:
the commands, the final figures of each run in columns, and the validation PSNR of each run at each
validation with its difference from the first run.

    python bench/nyx_side_by_side.py bench/results/nyx_train_ab_batch \\
        --run b2048="2048 rays" --run b4096="4096 rays" \\
        --title "Nyx, side by side: batches of 2048 rays against 4096"

``--run SUBFOLDER=LABEL`` names a run's folder within the first argument; the first run is the one
the differences are taken against (its value minus the other's). ``--about`` adds a paragraph of
text after the commands (what the runs share and what they differ in).
"""

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from nyx_train import NYX_VALIDATION_FRAMES


def parse_run(text: str) -> tuple[str, str]:
    """``SUBFOLDER=LABEL`` (or ``SUBFOLDER``, labelled by itself) as (subfolder, label)."""
    folder, _, label = text.partition("=")
    if not folder or "/" in folder or folder in (".", ".."):
        raise argparse.ArgumentTypeError(f"expected SUBFOLDER=LABEL with a plain subfolder name, got {text!r}")
    return folder, label or folder


def load_run(folder: Path) -> dict[str, Any]:
    path = folder / "nyx_train.json"
    if not path.is_file():
        raise SystemExit(f"error: {path} does not exist: is {folder} a finished bench/nyx_train.py run?")
    with open(path) as f:
        result = json.load(f)
    missing = [k for k in ("command", "final", "log", "iterations", "iterations_per_second", "peak_rss_mb")
               if k not in result]
    if missing:
        raise SystemExit(f"error: {path} lacks {', '.join(missing)}: not a bench/nyx_train.py report")
    return result


def validation_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    return [row for row in result["log"] if row.get("val_psnr") is not None]


def spacing_chosen(note: str | None) -> str:
    """The spacing from the trainer's note ("full-quality spacing 1 voxel (exhaustive ...)")."""
    if not note:
        return "none"
    return note.split(" (")[0].removeprefix("full-quality spacing ")


def summary_table(labels: list[str], runs: list[dict[str, Any]]) -> list[str]:
    def row(name: str, cell) -> str:  # noqa: ANN001
        return f"| {name} | " + " | ".join(cell(r) for r in runs) + " |"

    return [
        "| | " + " | ".join(labels) + " |",
        "| --- | " + " | ".join("---" for _ in runs) + " |",
        row(f"held-out PSNR / SSIM ({runs[0]['final']['frames']} frames)",
            lambda r: f"{r['final']['psnr']:.2f} dB / {r['final']['ssim']:.3f}"),
        row("at held-out settings / views",
            lambda r: f"{r['final']['psnr_held_out_settings']:.2f} / {r['final']['psnr_held_out_views']:.2f} dB"),
        row("iterations", lambda r: f"{r['iterations']} ({r['iterations_per_second']:.2f} it/s)"),
        row("peak RSS", lambda r: f"{r['peak_rss_mb']:.0f} MB"),
        row("checkpoint", lambda r: f"{r.get('checkpoint_mb', float('nan')):.2f} MB"),
        row("full-quality spacing chosen", lambda r: spacing_chosen(r.get("full_spacing"))),
        row("seconds per 256x256 frame (median)", lambda r: f"{r['final']['seconds_per_frame_256_median']:.2f}"),
    ]


def validation_table(labels: list[str], runs: list[dict[str, Any]]) -> list[str]:
    """One line per validation, matched by order: the runs validate every ``--validate-every``
    seconds of training, but a step or a milestone can carry one past that; the first column gives
    each run's own training seconds."""
    rows = [validation_rows(r) for r in runs]
    head = "| train s | " + " | ".join(f"iterations ({lab}) | val PSNR ({lab})" for lab in labels)
    head += "".join(f" | {labels[0]} minus {lab}" for lab in labels[1:]) + " |"
    lines = [head, "|" + " --- |" * (3 * len(runs))]  # train s; 2 per run; a difference per other run
    for i in range(min(len(r) for r in rows)):
        at = [r[i] for r in rows]
        cells = [" / ".join(f"{a['train_seconds']:.0f}" for a in at)]
        for a in at:
            cells += [str(a["iteration"]), f"{a['val_psnr']:.2f}"]
        cells += [f"{at[0]['val_psnr'] - a['val_psnr']:+.2f} dB" for a in at[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def report(folder: Path, runs: list[tuple[str, str]], title: str, about: str) -> str:
    results = [load_run(folder / sub) for sub, _ in runs]
    labels = [label for _, label in runs]
    lines = [f"# {title}", "", "The runs, started together on this machine:", ""]
    lines += [f"    {r['command']}" for r in results]
    lines += ["", "Machine: " + " / ".join(sorted({str(r.get("machine")) for r in results})) + "."]
    lines += ["", "Reports written at " + " / ".join(str(r.get("date")) for r in results)
              + "; 1-min load average before / after each: "
              + ", ".join(f"{r['load_average_before_after'][0]} / {r['load_average_before_after'][1]}"
                          for r in results if "load_average_before_after" in r)
              + ". Each run's own report: " + ", ".join(f"{sub}/nyx_train.md" for sub, _ in runs) + "."]
    if about:
        lines += ["", about]
    lines += ["", *summary_table(labels, results), "",
              f"Validation PSNR (bench/nyx_train.py validates on {NYX_VALIDATION_FRAMES} held-out frames) "
              "against training time:", "",
              *validation_table(labels, results), ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", type=Path, help="the folder that holds the runs' result folders")
    ap.add_argument("--run", type=parse_run, action="append", required=True, metavar="SUBFOLDER=LABEL",
                    help="a run's result folder within FOLDER, and its label (twice or more; the first is the reference)")
    ap.add_argument("--title", required=True)
    ap.add_argument("--about", default="", help="a paragraph on what the runs share and differ in")
    args = ap.parse_args()
    if len(args.run) < 2:
        ap.error("give at least two --run")
    text = report(args.folder, args.run, args.title, args.about)
    (args.folder / "README.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
