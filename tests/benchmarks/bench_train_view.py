"""What `train --view` costs: the same training run without the page, with it and a client, and with a browser.

    python tests/benchmarks/bench_train_view.py --dataset igavatar-run/dataset [--steps 1500]
        [--mesh-every 250,100] [--browser] [--out tests/benchmarks/results]

Runs `train` (cpu preset, seed 0) in child processes, one after another:
    plain              no page
    view N             --view --view-mesh-every N, with a websocket client that receives every message
                       the page sends (what a browser's tab costs the training process, without the
                       browser's own drawing on the same cores)
    view N + chromium  --browser: the same with headless Chromium (software WebGL) showing the page on
                       this machine, as a user watching on the training machine would
Reports the step time (train_seconds / steps, the trainer's own clock) and the whole stage's time,
and the meshes made and their seconds, in train-view.md/.json with the commit and the command.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from provenance import command, commit  # noqa: E402


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _drain(port: int, stop: threading.Event, counts: dict) -> None:
    """A page's websocket: connect once the server is up, then receive until stopped."""
    import viser
    from websockets.sync.client import connect

    while not stop.is_set():
        try:
            with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                         max_size=None, open_timeout=5) as ws:
                while not stop.is_set():
                    try:
                        message = ws.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    counts["messages"] = counts.get("messages", 0) + 1
                    counts["bytes"] = counts.get("bytes", 0) + len(message)
        except (OSError, Exception):  # not up yet, or closed at the end of training
            time.sleep(0.5)


def run(dataset: Path, out: Path, steps: int, mesh_every: int | None, browser: bool) -> dict:
    port = _free_port()
    cmd = [sys.executable, "-m", "igavatar_cli.main", "train", "--dataset", str(dataset), "--out", str(out),
           "--preset", "cpu", "--steps", str(steps), "--force", "--json"]
    if mesh_every is not None:
        cmd += ["--view", "--view-port", str(port), "--view-mesh-every", str(mesh_every)]
    stop, counts, helpers = threading.Event(), {}, []
    chromium = None
    if mesh_every is not None:
        helpers.append(threading.Thread(target=_drain, args=(port, stop, counts), daemon=True))
    started = time.perf_counter()
    child = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for thread in helpers:
        thread.start()
    if browser and mesh_every is not None:
        profile = tempfile.mkdtemp()
        time.sleep(20)  # the server starts after the shape initialization
        chromium = subprocess.Popen(
            [shutil.which("chromium") or "chromium", "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", f"--user-data-dir={profile}", "--window-size=1280,800",
             "--remote-debugging-port=0", f"http://127.0.0.1:{port}/"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stdout, stderr = child.communicate()
    stage_s = time.perf_counter() - started
    stop.set()
    if chromium is not None:
        chromium.kill()
        chromium.wait()
    if child.returncode != 0:
        raise SystemExit(f"train failed: {stderr[-2000:]}")
    summary = json.loads(stdout)
    return {"mesh_every": mesh_every, "browser": bool(browser and mesh_every is not None), "steps": summary["steps"],
            "train_seconds": summary["train_seconds"], "step_ms": round(1000 * summary["train_seconds"] / summary["steps"], 1),
            "stage_seconds": round(stage_s, 1), "viewer": summary.get("viewer"),
            "page_messages": counts.get("messages", 0), "page_megabytes": round(counts.get("bytes", 0) / 1e6, 2),
            "validation_psnr": summary["validation_psnr"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--mesh-every", default="250,100")
    parser.add_argument("--browser", action="store_true")
    parser.add_argument("--out", type=Path, default=REPO / "tests/benchmarks/results")
    parser.add_argument("--repeats", type=int, default=1, help="run the list this many times, every other time reversed")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "bench-train-view")
    args = parser.parse_args()
    runs = [(None, False)] + [(int(n), False) for n in args.mesh_every.split(",")]
    if args.browser:
        runs.append((int(args.mesh_every.split(",")[0]), True))
    rows = []
    for repeat in range(args.repeats):
        for k, (mesh_every, browser) in enumerate(runs if repeat % 2 == 0 else runs[::-1]):
            rows.append({"repeat": repeat, **run(args.dataset.resolve(), args.work / f"model{k}", args.steps, mesh_every, browser)})
            print(json.dumps(rows[-1]), flush=True)
    plain = [r["step_ms"] for r in rows if r["mesh_every"] is None]
    base = sum(plain) / len(plain)
    results = {"commit": commit(), "command": command(), "machine": f"{os.cpu_count()} CPU cores",
               "dataset": str(args.dataset), "runs": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "train-view.json").write_text(json.dumps(results, indent=2) + "\n")
    lines = ["# What `train --view` costs a training run", "",
             f"commit `{results['commit']}`; command `{results['command']}`; {results['machine']}; "
             f"dataset `{args.dataset}`, cpu preset, {args.steps} steps, seed 0, one run after another "
             f"({args.repeats} rounds, every other one in reverse order; 'vs no page' against the mean of the no-page runs, "
             f"{base:.1f} ms)", "",
             "| round | run | step time | vs no page | stage time | meshes (s) | page traffic |", "|---|---|---|---|---|---|---|"]
    for row in rows:
        name = "no page" if row["mesh_every"] is None else (
            f"--view, mesh every {row['mesh_every']}" + (" + headless Chromium" if row["browser"] else " + client"))
        meshes = "-" if not row["viewer"] else f"{row['viewer']['meshes']} ({row['viewer']['mesh_seconds']} s)"
        traffic = "-" if row["mesh_every"] is None else f"{row['page_messages']} messages, {row['page_megabytes']} MB"
        lines.append(f"| {row['repeat'] + 1} | {name} | {row['step_ms']} ms | {100 * (row['step_ms'] / base - 1):+.1f} % | "
                     f"{row['stage_seconds']} s | {meshes} | {traffic} |")
    (args.out / "train-view.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
