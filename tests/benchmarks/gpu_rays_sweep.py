"""What more rays a step cost on a GPU, and one full run at 4096 rays (issue 36), for the device machine.

    OUT=DIR DATASET=RUN/dataset DEADLINE_S=500 python tests/benchmarks/gpu_rays_sweep.py

Each run is `igavatar train --dataset DATASET --device cuda --preset cpu ...` in a fresh process (peak GPU
memory read when it ends). Short probes (300 steps) at 1024/2048/4096 rays with the paper's colour coupling
(`base`) and with the grid-detached colour (`gd`: --color-grid --no-color-feature-gradient
--no-color-normal-gradient); then 1500-step runs at 4096 rays (gd) and 1024 rays (base), as long as the
deadline allows. Writes DIR/sweep.json (it/s, median step time after step 50, peak GPU memory, timings)
and DIR/sweep.log, and the 4096-ray model as a tar split into 15 MB parts (the device machine sends
back no file over 16 MiB) to evaluate on another machine:
    cat DIR/model.tar.* | tar x -C MODEL && igavatar eval --model MODEL --dataset DATASET ...
"""
import csv
import json
import os
import statistics
import subprocess
import sys
import time

OUT, DATASET = os.environ["OUT"], os.environ.get("DATASET", ".gpu/run/dataset")
DEADLINE = float(os.environ.get("DEADLINE_S", "500"))
START = time.time()
GD = ["--color-grid", "--no-color-feature-gradient", "--no-color-normal-gradient"]
WRAP = ("import runpy,sys,torch,json\nsys.argv=['igavatar']+sys.argv[1:]\n"
        "try:\n  runpy.run_module('igavatar_cli.main', run_name='__main__')\n"
        "finally:\n  print('GPU_PEAK', json.dumps({'allocated_gb': torch.cuda.max_memory_allocated()/2**30,"
        " 'reserved_gb': torch.cuda.max_memory_reserved()/2**30}), flush=True)\n")
results: dict = {"device": None, "runs": []}
log = open(os.path.join(OUT, "sweep.log"), "w")


def say(text: str) -> None:
    print(text, flush=True)
    log.write(text + "\n")
    log.flush()


def train(name: str, steps: int, flags: list[str]) -> str:
    """One `igavatar train` on the GPU; its row (it/s, step time, peak memory) joins sweep.json."""
    out = f"/tmp/m/{name}"
    t0 = time.time()
    done = subprocess.run([sys.executable, "-c", WRAP, "train", "--dataset", DATASET, "--out", out, "--device", "cuda",
                           "--preset", "cpu", "--steps", str(steps), "--force", *flags],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.time() - t0
    say(f"--- {name} rc {done.returncode} wall {wall:.1f}s\n" + done.stdout[-1500:])
    row = {"name": name, "steps": steps, "flags": " ".join(flags), "rc": done.returncode, "wall_s": wall}
    for line in done.stdout.splitlines():
        if line.startswith("GPU_PEAK"):
            row["gpu_peak_gb"] = json.loads(line.split(" ", 1)[1])
    if done.returncode == 0:
        manifest = json.load(open(f"{out}/manifest.json"))
        row["it_per_s"] = manifest["data"]["speed"]["iterations_per_second"]
        row["samples_per_s"] = manifest["data"]["speed"]["samples_per_second"]
        row["timings"] = manifest.get("timings")
        # The first steps carry CUDA's warm-up (the first probe of a fresh process most).
        steps_s = [float(r["step_seconds"]) for r in csv.DictReader(open(f"{out}/training_log.csv")) if int(r["step"]) > 50]
        row["median_step_s_after_50"] = statistics.median(steps_s) if steps_s else None
    results["runs"].append(row)
    json.dump(results, open(os.path.join(OUT, "sweep.json"), "w"), indent=2)
    return out


def main() -> None:
    import torch
    results["device"], results["torch"] = torch.cuda.get_device_name(0), torch.__version__
    say(f"device {results['device']} {torch.__version__}")
    for name, flags in [("p1024-base", []), ("p1024-gd", GD), ("p2048-gd", ["--rays", "2048", *GD]),
                        ("p4096-gd", ["--rays", "4096", *GD]), ("p4096-base", ["--rays", "4096"])]:
        train(name, 300, flags)
    if time.time() - START < DEADLINE - 200:
        full = train("full4096-gd", 1500, ["--rays", "4096", *GD])
        if os.path.isfile(f"{full}/manifest.json"):
            subprocess.run(f"cd {full} && tar cf /tmp/model.tar manifest.json subject.npz weights.npz training_log.csv "
                           f"validation && split -b 15000000 -d /tmp/model.tar {OUT}/model.tar.", shell=True, check=True)
    if time.time() - START < DEADLINE - 110:
        train("full1024-base", 1500, [])
    say(f"total {time.time() - START:.1f}")


if __name__ == "__main__":
    main()
