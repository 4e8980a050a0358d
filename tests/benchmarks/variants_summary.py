"""Several `bench_variants.py` results side by side: per subject, each variant's mean over seeds and its
change against a reference variant, and per seed whether it is no worse on CD-L1 and IoU.

    python tests/benchmarks/variants_summary.py --reference base --name color-protocol \\
        color-protocol-bold color-protocol-demo color-protocol-stripes-shirt ...

Reads tests/benchmarks/results/<name>.json for each name given and writes <--name>.md beside them,
naming the commit of each input and this command.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
COLUMNS = (("chamfer_l1_surface_mm", "CD-L1 mm", "{:.2f}"), ("volumetric_iou", "IoU", "{:.3f}"),
           ("normal_consistency_surface", "NC surf", "{:.3f}"), ("normal_consistency_vertices", "paper NC", "{:.3f}"),
           ("psnr_mask_bbox_db", "box PSNR 1/4", "{:.2f}"), ("ssim_mask_bbox", "box SSIM 1/4", "{:.3f}"),
           ("psnr_mask_bbox_db_full", "box PSNR full", "{:.2f}"), ("ssim_mask_bbox_full", "box SSIM full", "{:.3f}"))


def _mean(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if isinstance(r.get(key), (int, float))]
    return statistics.mean(values) if values else None


def subject_lines(name: str, document: dict, reference: str) -> list[str]:
    """The table rows of one subject: each variant's means (and the change against the reference)."""
    rows = document["rows"]
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    ref = [r for r in rows if r["variant"] == reference]
    lines = []
    for variant in variants:
        mine = [r for r in rows if r["variant"] == variant]
        seeds = sorted(r["seed"] for r in mine)
        cells = []
        for key, _, form in COLUMNS:
            mean, base = _mean(mine, key), _mean(ref, key)
            text = "-" if mean is None else form.format(mean)
            if variant != reference and mean is not None and base is not None:
                text += f" ({mean - base:+.2f})" if "mm" in key or "db" in key else f" ({mean - base:+.3f})"
            cells.append(text)
        limbs = "all" if all(r.get("limbs") for r in mine) else "failed on " + ", ".join(
            str(r["seed"]) for r in mine if not r.get("limbs"))
        no_worse = "-"
        if variant != reference:
            verdicts = []
            for r in mine:
                other = next((o for o in ref if o["seed"] == r["seed"]), None)
                if other is not None:
                    ok = (r["chamfer_l1_surface_mm"] <= other["chamfer_l1_surface_mm"]
                          and r["volumetric_iou"] >= other["volumetric_iou"])
                    verdicts.append(f"s{r['seed']} {'yes' if ok else 'no'}")
            no_worse = ", ".join(verdicts)
        lines.append(f"| {name} | {variant} | {','.join(map(str, seeds))} | " + " | ".join(cells) + f" | {limbs} | {no_worse} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="+", help="results names (NAME.json in tests/benchmarks/results)")
    parser.add_argument("--reference", default="base")
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    command = "python tests/benchmarks/variants_summary.py " + shlex.join(sys.argv[1:])
    documents = {name: json.loads((RESULTS / f"{name}.json").read_text()) for name in args.names}
    lines = [f"# Variants side by side: {args.name}", "", f"Made by `{command}` from:", ""]
    lines += [f"- `{name}.md` (commit `{doc['commit']}`): `{doc['command']}`" for name, doc in documents.items()]
    lines += ["", f"Means over the seeds; in brackets the change against `{args.reference}`. \"No worse\": CD-L1 "
              "and IoU both at least as good as the reference's at the same seed.", "",
              "| results | variant | seeds | " + " | ".join(label for _, label, _ in COLUMNS) + " | limbs | no worse |",
              "|" + "---|" * (len(COLUMNS) + 5)]
    for name, document in documents.items():
        lines += subject_lines(name, document, args.reference)
    (RESULTS / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
