"""`igavatar demo`: every available stage on the built-in synthetic subject, in order.

    summary = run_demo(DemoOptions(run_dir=Path("igavatar-run")), progress)

Every stage writes its usual artifact into the run directory; the summary gathers per-stage
times and the headline numbers (geometry and image metrics, paths of mesh, GLB, video, report).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from stages.animate import AnimateOptions, run_animate
from stages.eval import EvalOptions, run_eval
from stages.export import ExportOptions, run_export
from stages.layout import RunLayout
from stages.preprocess import PreprocessOptions, run_preprocess
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.synth import SynthOptions, run_synth
from stages.train import TrainOptions, run_train


#: The stages `run_demo` runs, in order.
DEMO_STAGES = ("synth", "preprocess", "train", "export", "animate", "eval")


@dataclass(frozen=True)
class DemoOptions:
    """Options of `igavatar demo`."""

    run_dir: Path
    preset: str | None = None
    steps: int | None = None
    resolution: int = 512
    train_frames: int = 100
    test_frames: int = 30
    device: str = "auto"
    seed: int = 0


def run_demo(options: DemoOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """synth -> preprocess -> train -> export -> animate (walk) -> eval; per-stage results and times."""
    import torch

    layout = RunLayout(options.run_dir)
    preset = options.preset or ("paper" if options.device != "cpu" and torch.cuda.is_available() else "cpu")
    stages: dict[str, dict] = {}

    def timed(name: str, call) -> dict:
        # A line per stage start and end, so a log without a TTY (nohup, CI, > log.txt) shows where it is.
        number = len(stages) + 1
        progress.status(f"demo stage {number}/{len(DEMO_STAGES)} {name}: started")
        started = time.perf_counter()
        result = call()
        result["stage_seconds"] = round(time.perf_counter() - started, 1)
        stages[name] = result
        progress.status(f"demo stage {number}/{len(DEMO_STAGES)} {name}: done in {result['stage_seconds']} s")
        return result

    timed("synth", lambda: run_synth(SynthOptions(
        out=layout.capture, resolution=options.resolution, train_frames=options.train_frames,
        test_frames=options.test_frames, seed=options.seed), progress=progress))
    timed("preprocess", lambda: run_preprocess(PreprocessOptions(capture=layout.capture, out=layout.dataset), progress=progress))
    timed("train", lambda: run_train(TrainOptions(
        dataset=layout.dataset, out=layout.model, preset=preset, steps=options.steps, seed=options.seed,
        device=options.device), progress=progress))
    timed("export", lambda: run_export(ExportOptions(model=layout.model, out=layout.mesh, device=options.device), progress=progress))
    timed("animate", lambda: run_animate(AnimateOptions(model=layout.model, out=layout.animation, motion="walk", seconds=2.0,
                                                        seed=options.seed, device=options.device), progress=progress))
    timed("eval", lambda: run_eval(EvalOptions(model=layout.model, out=layout.report, device=options.device, seed=options.seed), progress=progress))
    return {"run_dir": str(options.run_dir), "preset": preset, "stages": stages}
