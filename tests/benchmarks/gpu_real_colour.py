"""Colour on a real capture against the ray budget (issue 36), for the device machine.

    OUT=DIR DATASET=RUN/dataset [ONLY=name,name] DEADLINE_S=520 python tests/benchmarks/gpu_real_colour.py

Each run is `igavatar train --dataset DATASET --device cuda --preset cpu --seed 0 [flags]` in a fresh process, then
`igavatar eval --no-geometry --image-frames 0` on the dataset's held-out frames at its own size (`--image-scale 1`) and
at half of it (bench_video_real.py's scale). Runs start only while DEADLINE_S leaves two minutes. Writes DIR/real.log
and DIR/real.tar (each model's manifest, training log and validation panels, each report's metrics.json and three
of its images), which the device machine sends back.

The device machine has no pymeshlab or OpenEXR wheel small enough to carry: empty stand-in modules let the CLI
import, and `eval --no-geometry` never calls them (a run that did would fail, not score wrongly).
"""
import json
import os
import subprocess
import sys
import tarfile
import time

START = time.time()
OUT, DATASET = os.environ["OUT"], os.environ["DATASET"]
DEADLINE = float(os.environ.get("DEADLINE_S", "520"))
DEVICE = os.environ.get("DEVICE", "cuda")
RUNS = {
    "grid4096x3000": ["--color-grid", "--rays", "4096", "--steps", "3000"],
    "grid1024x1500": ["--color-grid", "--steps", "1500"],
    "base1024x1500": ["--steps", "1500"],
}
WRAP = ("import runpy,sys,types,torch,json\n"
        "sys.modules.setdefault('pymeshlab', types.ModuleType('pymeshlab'))\n"
        "sys.modules.setdefault('OpenEXR', types.ModuleType('OpenEXR'))\n"
        "sys.argv=['igavatar']+sys.argv[1:]\n"
        "try:\n  runpy.run_module('igavatar_cli.main', run_name='__main__')\n"
        "finally:\n  print('GPU_PEAK', json.dumps({'allocated_gb': torch.cuda.max_memory_allocated()/2**30,"
        " 'reserved_gb': torch.cuda.max_memory_reserved()/2**30}), flush=True)\n")
log = open(os.path.join(OUT, "real.log"), "w")


def say(text: str) -> None:
    print(text, flush=True)
    log.write(text + "\n")
    log.flush()


def igavatar(*args: str) -> int:
    """One CLI command in a fresh process; its output's tail goes to the log."""
    t0 = time.time()
    done = subprocess.run([sys.executable, "-c", WRAP, *args, "--device", DEVICE],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    say(f"--- {' '.join(args[:3])} rc {done.returncode} wall {time.time() - t0:.1f}s\n" + done.stdout[-1200:])
    return done.returncode


def main() -> None:
    names = os.environ["ONLY"].split(",") if os.environ.get("ONLY") else list(RUNS)
    keep: list[str] = []
    for name in names:
        if time.time() - START > DEADLINE - 120:
            say(f"skip {name}: deadline")
            continue
        model = f"/tmp/m/{name}"
        if igavatar("train", "--dataset", DATASET, "--out", model, "--preset", "cpu", "--seed", "0", "--force",
                    *RUNS[name]) != 0:
            continue
        keep += [f"{model}/manifest.json", f"{model}/training_log.csv"]
        keep += [f"{model}/validation/{f}" for f in sorted(os.listdir(f"{model}/validation"))]
        for scale in ("1", "0.5"):
            report = f"/tmp/r/{name}-{scale}"
            if igavatar("eval", "--model", model, "--dataset", DATASET, "--out", report, "--no-geometry",
                        "--image-frames", "0", "--image-scale", scale, "--seed", "0") == 0:
                keep.append(f"{report}/metrics.json")
                keep += [f"{report}/images/{f}" for f in sorted(os.listdir(f"{report}/images"))[:3]]
        with tarfile.open(os.path.join(OUT, "real.tar"), "w") as tar:
            for path in keep:
                tar.add(path, arcname=path.lstrip("/"))
    say(json.dumps({"done_s": round(time.time() - START, 1)}))


if __name__ == "__main__":
    main()
