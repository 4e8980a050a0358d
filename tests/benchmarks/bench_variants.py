"""Training variants side by side on one dataset: geometry, images at two scales, time per step.

    python tests/benchmarks/bench_variants.py --dataset RUN/dataset --gt RUN/capture/scans --out OUT \\
        --variant base= --variant grid=--color-grid --steps 800 --seeds 0,1 --name color-grid-bold

Each variant is `name=extra train flags` (empty for the preset as it is). For every variant and
seed it runs, as a user would:
    igavatar train --dataset D --out OUT/<name>-s<seed>/model --preset P --steps S --seed <seed> <flags>
    igavatar eval  --model ... --dataset D [--gt G] --out .../report                 (geometry, images at 1/4)
    igavatar eval  --model ... --dataset D --no-geometry --image-scale 1 --out .../report-full
and writes NAME.md / NAME.json to tests/benchmarks/results with the commit and this command. The
variants run one after another, so their step times share the machine's noise only roughly;
the it/s column is the model manifest's own. `--reuse` keeps runs whose reports exist.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from provenance import commit  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"
GEOMETRY = ("chamfer_l1_surface_mm", "volumetric_iou", "normal_consistency_surface", "normal_consistency_vertices")
IMAGES = ("psnr_mask_bbox_db", "ssim_mask_bbox")


def igavatar(*args: str) -> None:
    command = [sys.executable, "-m", "igavatar_cli.main", *args, "--json", "-q"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-3000:]}")


def _mean(report: Path, key: str) -> float | None:
    value = json.loads((report / "metrics.json").read_text())["metrics"].get(key)
    return value.get("mean") if isinstance(value, dict) else value


def run_one(args: argparse.Namespace, name: str, flags: list[str], seed: int) -> dict:
    run = args.out / f"{name}-s{seed}"
    model, report, full = run / "model", run / "report", run / "report-full"
    if not (args.reuse and (full / "metrics.json").is_file()):
        igavatar("train", "--dataset", str(args.dataset), "--out", str(model), "--preset", args.preset, "--steps",
                 str(args.steps), "--seed", str(seed), "--device", "cpu", "--force", *flags)
        gt = ["--gt", str(args.gt), "--iou-points", "200000"] if args.gt else ["--no-geometry"]
        igavatar("eval", "--model", str(model), "--dataset", str(args.dataset), "--out", str(report), "--device", "cpu",
                 "--force", *gt)
        igavatar("eval", "--model", str(model), "--dataset", str(args.dataset), "--out", str(full), "--device", "cpu",
                 "--force", "--no-geometry", "--image-scale", "1")
    manifest = json.loads((model / "manifest.json").read_text())
    row = {"variant": name, "flags": " ".join(flags), "seed": seed,
           "it_per_s": manifest["data"]["speed"]["iterations_per_second"], "train_s": manifest["timings"]["train_s"]}
    metrics = json.loads((report / "metrics.json").read_text())
    canonical = metrics.get("canonical") or {}
    row.update({key: _mean(report, key) for key in GEOMETRY + IMAGES})
    row.update({f"{key}_full": _mean(full, key) for key in IMAGES})
    row["limbs"] = (canonical.get("limb_check") or {}).get("passed")
    row["canon_nc_vertices"] = (canonical.get("against_truth") or {}).get("normal_consistency_vertices")
    return row


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.3f}"
    return "-" if value is None else str(value)


def markdown(rows: list[dict], args: argparse.Namespace, command: str) -> str:
    columns = ["variant", "seed", "chamfer_l1_surface_mm", "volumetric_iou", "normal_consistency_surface",
               "normal_consistency_vertices", "canon_nc_vertices", "limbs", "psnr_mask_bbox_db", "ssim_mask_bbox",
               "psnr_mask_bbox_db_full", "ssim_mask_bbox_full", "it_per_s"]
    lines = [f"# Training variants: {args.name}", "", f"Commit: `{commit()}`. Command:", "", f"    {command}", "",
             f"Dataset `{args.dataset}`, preset `{args.preset}`, {args.steps} steps, seeds {args.seeds}; images at 1/4 "
             "(eval's default) and at the dataset's full size; canon NC = the canonical mesh's vertex normal "
             "consistency against the true clothed surface (paper protocol). Flags per variant: "
             + "; ".join(f"`{name}`: `{flags or '(none)'}`" for name, flags in args.variant_flags.items()) + ".", "",
             "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(row.get(c)) for c in columns) + " |" for row in rows]
    lines += ["", "Means over seeds:", "", "| variant | " + " | ".join(columns[2:]) + " |", "|" + "---|" * (len(columns) - 1)]
    for name in args.variant_flags:
        mine = [r for r in rows if r["variant"] == name]
        means = [statistics.mean(r[c] for r in mine) if all(isinstance(r.get(c), (int, float)) and not isinstance(r.get(c), bool)
                                                         for r in mine) else None for c in columns[2:]]
        lines.append(f"| {name} | " + " | ".join(_cell(m) for m in means) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--gt", type=Path, default=None, help="scans for posed geometry (none: images only)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--variant", action="append", required=True, help="name=flags, e.g. grid=--color-grid")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--name", required=True)
    parser.add_argument("--reuse", action="store_true")
    args = parser.parse_args()
    args.variant_flags = dict(v.split("=", 1) for v in args.variant)
    command = "python tests/benchmarks/bench_variants.py " + shlex.join(sys.argv[1:])
    rows = []
    for seed in [int(s) for s in args.seeds.split(",")]:
        for name, flags in args.variant_flags.items():
            rows.append(run_one(args, name, flags.split(), seed))
            print(json.dumps(rows[-1]), flush=True)
    text = markdown(rows, args, command)
    (RESULTS / f"{args.name}.md").write_text(text)
    (RESULTS / f"{args.name}.json").write_text(json.dumps({"commit": commit(), "command": command, "rows": rows}, indent=2) + "\n")
    print(text)


if __name__ == "__main__":
    main()
