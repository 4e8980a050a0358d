"""The quality gate: a small synthetic subject trained at the cpu preset must come out whole.

Every other training test runs a few steps of the `tiny` preset, so a change that loses the hands
or the forearms again would pass them all. This one trains for real (about 75 s on 2 cores with
AVX-512, about 3 min with AVX2 only; the Anny model cached by the other tests) and checks the
canonical shape against the subject's true clothed surface: every limb is there, the legs are not
webbed, and IoU, CD-L1 and surface normal consistency are inside floors.

Floors, from the measured values at this setting (192 px, 30 frames, 500 steps, synthetic seed 0;
training seeds 0, 1, 2 at commit 107baba on 2 CPU cores): IoU 0.908 / 0.903 / 0.908,
CD-L1 4.20 / 4.54 / 4.05 mm, NC (surface) 0.961 / 0.956 / 0.961, leg-gap web 0 / 0.05 / 0. With the
colour grid in the preset (issue 36, the commit that made it the default): IoU 0.912 / 0.900 / 0.916, CD-L1 3.94 / 4.57 / 3.80 mm,
NC 0.964 / 0.961 / 0.964, web 0 / 0.05 / 0. With 0.3 of the colour's pull through the weights
(`color_weights_gradient`, commit 29b5984), seed 0: IoU 0.911, CD-L1 4.01 mm, NC 0.964, web 0; seeds 1
and 2 (commit c11d08c, the same training code): IoU 0.910 / 0.917, CD-L1 4.00 / 3.67 mm, NC 0.963 / 0.965,
web 0 / 0. With the full pull within the outline band (`color_weights_outline_px`, 2 px here; the
commit after a28c9af), seeds 0 and 1: IoU 0.918 / 0.918, CD-L1 3.87 / 3.77 mm, NC 0.964 / 0.963, web 0 / 0.05
(seed 2 not rerun). With the colour lit by the clip's light (`shading` sh9, commit a3b8ac0), seeds 0 and 1:
IoU 0.919 / 0.920, CD-L1 3.83 / 3.67 mm, NC 0.964 / 0.963, web 0 / 0.05. With half the person's patches
centred on the mask's edge (`outline_sampling` 0.5, d370c30), seeds 0 and 1: IoU 0.931 / 0.918, CD-L1
3.23 / 3.68 mm, NC 0.965 / 0.964, web 0 / 0 (seed 1 even with the last default at this small setting). Each floor
sits about five seed spreads from the mean, so noise does not trip it; the cpu preset as it was
before the geometry work (`KNOWN_BAD`: beta 7.5 cm -> 3 mm, Eq. 9 smoothness, no hull or body
priors) measured IoU 0.824, CD-L1 8.37 mm, NC 0.927, web 0.19 and a missing right hand, failing
every check. Run `python tests/test_quality_gate.py --known-bad` to see it fail again.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

#: The subject and the training run of the gate.
SUBJECT = {"resolution": 192, "train_frames": 30, "test_frames": 2, "seed": 0}
STEPS = 500
#: Floors on the canonical shape (see the module docstring for the measurements behind them).
FLOORS = {"volumetric_iou": 0.88, "chamfer_l1_mm": 5.5, "normal_consistency_surface": 0.94, "leg_gap_webbed": 0.15}
#: The cpu preset before issue 16's geometry work: it lost hands and forearms.
KNOWN_BAD = {"beta_init": 0.075, "beta_final": 0.003, "smooth_form": "eq9", "smooth_pairs": "valid",
             "free_space_weight": 0.0, "body_inside_weight": 0.0, "color_grid": False,
             "color_weights_gradient": 1.0, "color_weights_outline_px": 0, "shading": "none",
             "outline_sampling": 0.0}


def measure(run: Path, **train_overrides) -> dict:
    """Make the subject, train and evaluate it under `run`; the report's canonical section."""
    from stages.eval import EvalOptions, run_eval
    from stages.preprocess import PreprocessOptions, run_preprocess
    from stages.synth import SynthOptions, run_synth
    from stages.train import TrainOptions, run_train

    run_synth(SynthOptions(out=run / "capture", **SUBJECT))
    run_preprocess(PreprocessOptions(capture=run / "capture", out=run / "dataset", max_size=SUBJECT["resolution"]))
    run_train(TrainOptions(dataset=run / "dataset", out=run / "model", preset="cpu", steps=STEPS, device="cpu",
                           force=True, **train_overrides))
    run_eval(EvalOptions(model=run / "model", out=run / "report", images=False, mesh_resolution=160,
                         iou_points=100_000, device="cpu"))
    return json.loads((run / "report" / "metrics.json").read_text())["canonical"]


def failures(canonical: dict) -> list[str]:
    """Every check of the gate that `canonical` fails, as a readable line."""
    failed = []
    limbs, gap, truth = canonical["limb_check"], canonical["leg_gap"], canonical["against_truth"]
    if limbs is None or not limbs["passed"]:
        failed.append(f"limb check: missing {limbs['failed_parts'] if limbs else 'all (no check)'}")
    if gap is None or gap["webbed"] > FLOORS["leg_gap_webbed"]:
        failed.append(f"leg gap webbed {gap['webbed'] if gap else None} > {FLOORS['leg_gap_webbed']}")
    if truth is None:
        return failed + ["no true surface to compare with"]
    if truth["volumetric_iou"] < FLOORS["volumetric_iou"]:
        failed.append(f"IoU {truth['volumetric_iou']:.3f} < {FLOORS['volumetric_iou']}")
    if truth["chamfer_l1_mm"] > FLOORS["chamfer_l1_mm"]:
        failed.append(f"CD-L1 {truth['chamfer_l1_mm']:.2f} mm > {FLOORS['chamfer_l1_mm']}")
    if truth["normal_consistency_surface"] < FLOORS["normal_consistency_surface"]:
        failed.append(f"NC {truth['normal_consistency_surface']:.3f} < {FLOORS['normal_consistency_surface']}")
    return failed


def test_the_canonical_shape_passes_the_gate(tmp_path):
    canonical = measure(tmp_path)
    assert canonical["against_truth"] is None or canonical["against_truth"]["pred_watertight"]
    assert failures(canonical) == [], json.dumps(canonical["against_truth"])


def main() -> int:
    parser = argparse.ArgumentParser(description="Run the quality gate outside pytest (e.g. on the known-bad setting).")
    parser.add_argument("--run-dir", type=Path, default=Path("igavatar-gate"))
    parser.add_argument("--known-bad", action="store_true", help="train with KNOWN_BAD; the gate must fail")
    parser.add_argument("--seed", type=int, default=0, help="training seed (the floors were set over seeds 0, 1, 2)")
    args = parser.parse_args()
    canonical = measure(args.run_dir, seed=args.seed, **(KNOWN_BAD if args.known_bad else {}))
    print(json.dumps({"limb_check_failed": canonical["limb_check"]["failed_parts"], "leg_gap": canonical["leg_gap"]["webbed"],
                      "against_truth": canonical["against_truth"]}, indent=2))
    failed = failures(canonical)
    print("gate:", "FAILED\n  " + "\n  ".join(failed) if failed else "passed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.exit(main())
