"""Browser check of `igavatar view`: headless Chromium loads the page and takes screenshots at two frames.

    python tests/benchmarks/view_browser_check.py --run-dir igavatar-run [--frames 0,60] [--surface colors]
        [--out tests/benchmarks/results] [--chromium chromium]

Not part of the test suite, and it installs nothing (Debian: `apt-get install chromium`). It serves
the run directory as `igavatar view` does (loopback, a free port), opens the page in headless
Chromium with software WebGL (SwiftShader), once per frame, moving the server's frame slider in
between (the GUI state is the server's, so a new page shows the new frame), and checks that:
    - each screenshot shows the avatar: enough pixels differ from the page's empty background
      (a screenshot of the page with the avatar hidden);
    - the two frames differ where the avatar is.
Writes view-<frame>.png for each frame and view-browser.md/.json (commit, command, numbers) to --out.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from provenance import command, commit  # noqa: E402
from stages.view import ViewOptions, serve_view  # noqa: E402

WINDOW = (1280, 800)
#: A pixel counts as "drawn" when it differs from the empty page by more than this (0-255, any channel).
PIXEL_THRESHOLD = 24


def screenshot(chromium: str, url: str, path: Path, budget_ms: int) -> np.ndarray:
    """Headless Chromium's screenshot of `url` after `budget_ms` of virtual time; (H, W, 3) uint8."""
    import imageio.v3 as iio

    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--ignore-gpu-blocklist", f"--user-data-dir={profile}", f"--window-size={WINDOW[0]},{WINDOW[1]}",
             f"--virtual-time-budget={budget_ms}", f"--screenshot={path}", url],
            check=True, capture_output=True, timeout=300,
        )
    return np.asarray(iio.imread(path))[..., :3]


def texture_and_scan(chromium: str, url: str, scene, path: Path, budget_ms: int) -> dict | None:
    """A third look, when the run has them: the export's texture, the first scanned test frame with its
    scan beside the avatar and the capture's camera, seen from the front and a little to the side."""
    scanned = [i for i, name in enumerate(scene.frames.names) if name in scene.scans]
    if scene.textured is None or not scanned:
        return None
    scene.surface.value = "texture"
    scene.show_scan.value = scene.show_cameras.value = scene.show_skeleton.value = True
    scene.set_frame(scanned[0])
    up = np.asarray(scene.server.initial_camera.up, np.float64)
    look_at = np.asarray(scene.server.initial_camera.look_at, np.float64) + 0.5 * scene.scan_offset
    position = np.asarray(scene.server.initial_camera.position, np.float64)
    scene.server.initial_camera.look_at = tuple(look_at)
    scene.server.initial_camera.position = tuple(position + 0.8 * scene.scan_offset + 0.6 * up)
    screenshot(chromium, url, path, budget_ms)
    return {"frame": scene.frames.names[scanned[0]], "png": path.name}


def button_screenshot(chromium: str, url: str, scene, budget_ms: int) -> dict:
    """What the page's 'save screenshot' button does (the client renders its view and sends it back),
    while a headless Chromium has the page open."""
    browser = subprocess.Popen(
        [chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         f"--user-data-dir={tempfile.mkdtemp()}", f"--window-size={WINDOW[0]},{WINDOW[1]}", "--remote-debugging-port=0", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + budget_ms / 1000 + 30
        while not scene.server.get_clients() and time.monotonic() < deadline:
            time.sleep(0.5)
        clients = list(scene.server.get_clients().values())
        if not clients:
            return {"saved": None, "note": "no page connected"}
        time.sleep(5)  # let the page draw its first frames
        path = scene.save_screenshot(clients[0], size_hw=(400, 640))
        return {"saved": path.name}
    except Exception as exc:  # recorded, not fatal: the two-frame check is the acceptance
        return {"saved": None, "note": f"{type(exc).__name__}: {exc}"}
    finally:
        browser.kill()
        browser.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, default=Path("igavatar-run"))
    parser.add_argument("--frames", default="0,60", help="two frame indices of the slider")
    parser.add_argument("--surface", default="colors", help="the page's surface menu: colors, texture, skinned")
    parser.add_argument("--out", type=Path, default=REPO / "tests/benchmarks/results")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    parser.add_argument("--cameras", action="store_true", help="show the capture's cameras too")
    parser.add_argument("--mesh", type=Path, default=None, help="mesh artifact (default RUN/mesh)")
    parser.add_argument("--budget-ms", type=int, default=20000)
    args = parser.parse_args()
    frames = [int(f) for f in args.frames.split(",")]
    run = args.run_dir
    options = ViewOptions(model=run / "model", mesh=args.mesh or run / "mesh", report=run / "report", port=0,
                          screenshots=args.out)
    ready, stop, box = threading.Event(), threading.Event(), {}

    def on_ready(server, scene):
        box.update(server=server, scene=scene)
        ready.set()

    thread = threading.Thread(target=lambda: box.setdefault("summary", serve_view(options, stop=stop, on_ready=on_ready)))
    thread.start()
    if not ready.wait(600):
        raise SystemExit("the viewer did not come up")
    server, scene = box["server"], box["scene"]
    url = f"http://127.0.0.1:{server.get_port()}/"
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"commit": commit(), "command": command(), "run_dir": str(run), "frames": {}, "surface": args.surface}
    try:
        scene.surface.value = args.surface
        # The empty page: the same view with the avatar, its skeleton and cameras hidden.
        scene.show_skeleton.value = scene.show_cameras.value = False
        scene.set_frame(frames[0])
        hidden = [scene.skinned, scene._posed]
        for node in hidden:
            if node is not None:
                node.visible = False
        background = screenshot(args.chromium, url, args.out / "view-empty.png", args.budget_ms)
        shots = {}
        for frame in frames:
            scene.show_skeleton.value = True
            scene.show_cameras.value = args.cameras
            scene.set_frame(frame)  # a fresh mesh node per frame: visible again
            started = time.perf_counter()
            path = args.out / f"view-{args.surface}-frame-{frame:04d}.png"
            shots[frame] = screenshot(args.chromium, url, path, args.budget_ms)
            drawn = (np.abs(shots[frame].astype(int) - background.astype(int)).max(-1) > PIXEL_THRESHOLD)
            results["frames"][frame] = {"name": scene.frames.names[frame], "png": path.name,
                                        "drawn_fraction": round(float(drawn.mean()), 4),
                                        "seconds": round(time.perf_counter() - started, 1)}
        results["screenshot_button"] = button_screenshot(args.chromium, url, scene, args.budget_ms)
        results["texture_and_scan"] = texture_and_scan(args.chromium, url, scene, args.out / "view-texture-scan.png",
                                                       args.budget_ms)
        a, b = (shots[f].astype(int) for f in frames)
        changed = np.abs(a - b).max(-1) > PIXEL_THRESHOLD
        results["frames_differ_fraction"] = round(float(changed.mean()), 4)
    finally:
        stop.set()
        thread.join(60)
    (args.out / "view-empty.png").unlink(missing_ok=True)
    ok = all(f["drawn_fraction"] > 0.01 for f in results["frames"].values()) and results["frames_differ_fraction"] > 0.002
    results["pass"] = ok
    (args.out / "view-browser.json").write_text(json.dumps(results, indent=2) + "\n")
    lines = [f"# `igavatar view` in headless Chromium (software WebGL)", "",
             f"commit `{results['commit']}`; command `{results['command']}`", "",
             f"run directory `{run}`, surface `{args.surface}`, window {WINDOW[0]}x{WINDOW[1]}", "",
             "| frame | name | pixels showing the avatar | screenshot |", "|---|---|---|---|"]
    lines += [f"| {k} | {f['name']} | {100 * f['drawn_fraction']:.1f} % | `{f['png']}` |" for k, f in results["frames"].items()]
    lines += ["", f"Pixels that differ between the two frames: {100 * results['frames_differ_fraction']:.1f} %.",
              f"The page's 'save screenshot' button (the browser renders its view and sends it back): "
              f"{results['screenshot_button']}.",
              f"The export's texture with the frame's scan beside the avatar and the capture's camera: "
              f"{results['texture_and_scan']}.",
              f"Result: {'pass' if ok else 'FAIL'} (each frame > 1 % drawn, the two differ on > 0.2 %)."]
    (args.out / "view-browser.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    raise SystemExit(0 if ok else 1)


if __name__ == "__main__":
    main()
