"""Textured export from the field or from the images, against the field's own render, at held-out frames.

    python tests/benchmarks/bench_texture.py --run-dir igavatar-run [--texture-size 1024] [--scale 0.5]
        [--frames 10] [--out tests/benchmarks/results] [--name texture-from]

For a trained run directory (model/, dataset/), it:
1. exports the textured mesh twice (`export --texture-size S --texture-from field` and `images`,
   into RUN/mesh-texture-field and RUN/mesh-texture-images), timing each;
2. at the dataset's held-out test frames (the same frames eval renders images of), renders
   - the trained field (volume rendering, as `eval` does), and
   - each textured mesh, posed as export poses meshes (skinning + non-rigid offset), ray cast from
     the test camera (one ray per pixel center, as the field's render) with the texture sampled
     bilinearly, on white;
3. scores each against the ground truth as eval does (PSNR and SSIM, whole image and the mask's box).
Writes NAME.md/.json (commit, command, per-frame and mean values) and NAME-frame.png (ground truth |
field | field texture | image texture for one frame) to --out.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from provenance import command, commit  # noqa: E402
from igavatar.artifacts.png import write_png  # noqa: E402
from igavatar.avatar.dataset import read_dataset  # noqa: E402
from igavatar.avatar.model import load_model  # noqa: E402
from igavatar.capture.images import scale_intrinsics  # noqa: E402
from igavatar.geometry.raycast import MeshRayCaster, interpolate_vertex_values  # noqa: E402
from igavatar.mesh.texture import sample_texture  # noqa: E402
from igavatar.metrics.image import evaluate_image  # noqa: E402
from igavatar.model.render_avatar import render_posed_view  # noqa: E402
from stages.eval_options import image_frame_indices, render_size  # noqa: E402

SOURCES = ("field", "images")
METRICS = ("psnr_full_db", "ssim_full", "psnr_mask_bbox_db", "ssim_mask_bbox")

def export(run: Path, source: str, size: int) -> tuple[Path, float]:
    out = run / f"mesh-texture-{source}"
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "igavatar_cli.main", "export", "--run-dir", str(run), "--out", str(out),
                    "--formats", "obj,glb", "--texture-size", str(size), "--texture-from", source, "--force", "-q"],
                   cwd=REPO, check=True)
    return out, time.perf_counter() - started

def load_textured(mesh_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Canonical vertices (V, 3), faces, uv (V, 2, v down) and the texture of an export's textured mesh."""
    record = json.loads((mesh_dir / "manifest.json").read_text())["data"]["textured"]
    loaded = trimesh.load(mesh_dir / "textured" / "avatar.obj", process=False, maintain_order=True)
    a, offset = np.asarray(record["glb"]["world_to_gltf"]), np.asarray(record["glb"]["world_to_gltf_offset"])
    vertices = (np.asarray(loaded.vertices) - offset) @ a
    uv = np.asarray(loaded.visual.uv, np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # OBJ's vt (v up) -> glTF's (v down)
    import imageio.v3 as iio

    texture = np.asarray(iio.imread(mesh_dir / "textured" / "avatar.png"))[..., :3]
    return vertices, np.asarray(loaded.faces), uv, texture

def render_textured(x_posed: np.ndarray, faces: np.ndarray, uv: np.ndarray, texture: np.ndarray,
                    K: np.ndarray, w2c: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) float in [0, 1] on white: one ray per pixel center."""
    h, w = size_hw
    ys, xs = np.mgrid[0:h, 0:w]
    pixels = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)], axis=1)
    directions = (pixels @ np.linalg.inv(K).T) @ w2c[:3, :3]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    center = -w2c[:3, :3].T @ w2c[:3, 3]
    hits = MeshRayCaster(x_posed, faces).first_hits(np.broadcast_to(center, directions.shape), directions)
    image = np.ones((h * w, 3))
    hit_uv = interpolate_vertex_values(uv, faces, hits)[hits.hit]
    image[hits.hit] = sample_texture(texture.astype(np.float64) / 255.0, hit_uv)
    return image.reshape(h, w, 3)

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--texture-size", type=int, default=1024)
    parser.add_argument("--scale", type=float, default=0.5, help="render size as a fraction of the dataset's")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--samples", type=int, default=128)
    parser.add_argument("--out", type=Path, default=REPO / "tests/benchmarks/results")
    parser.add_argument("--name", default="texture-from")
    args = parser.parse_args()
    run = args.run_dir
    exports = {source: export(run, source, args.texture_size) for source in SOURCES}
    meshes = {source: load_textured(path) for source, (path, _) in exports.items()}
    model = load_model(run / "model")
    dataset = read_dataset(run / "dataset")
    frames = dataset.frames()
    test = frames.select(frames.test_indices)
    chosen = sorted(image_frame_indices(test.n_frames, args.frames))
    size_hw = render_size(dataset.image_size, args.scale)
    sx, sy = size_hw[1] / dataset.image_size[1], size_hw[0] / dataset.image_size[0]
    rows, panel = [], None
    for i in chosen:
        K = scale_intrinsics(test.K[i].astype(np.float64), (sx, sy))
        w2c = test.w2c[i].astype(np.float64)
        gt, mask = dataset.image_on_white(test.names[i], size_hw)
        with torch.no_grad():
            posed = model.posed(torch.from_numpy(test.bone_transforms[i]), torch.from_numpy(test.pose_condition[i]))
            render = render_posed_view(posed, model.canonical_grid, torch.from_numpy(K).float(), torch.from_numpy(w2c).float(),
                                       size_hw[0], size_hw[1], torch.from_numpy(test.posed_boxes[i]).float(),
                                       num_samples=args.samples, occupancy_resolution=model.config.occupancy_resolution)
        images = {"field render": render.rgb.clamp(0, 1).cpu().numpy().astype(np.float64)}
        for source, (vertices, faces, uv, texture) in meshes.items():
            with torch.no_grad():
                x_posed = posed.pose_vertices(vertices.astype(np.float32))
            images[f"{source} texture"] = render_textured(x_posed, faces, uv, texture, K, w2c, size_hw)
        row = {"frame": test.names[i]}
        for key, image in images.items():
            metrics = evaluate_image(image, gt, mask)
            row[key] = {m: round(float(getattr(metrics, m)), 4) for m in METRICS}
        rows.append(row)
        if panel is None:
            panel = np.concatenate([gt, *images.values()], axis=1)
        print(json.dumps(row), flush=True)
    keys = list(rows[0].keys())[1:]
    means = {key: {m: round(float(np.mean([r[key][m] for r in rows])), 4) for m in METRICS} for key in keys}
    results = {"commit": commit(), "command": command(), "run_dir": str(run), "texture_size": args.texture_size,
               "render_hw": list(size_hw), "frames": [r["frame"] for r in rows],
               "export_seconds": {s: round(t, 1) for s, (_, t) in exports.items()},
               "fusion": json.loads((exports["images"][0] / "manifest.json").read_text())["data"]["textured"]["texture_from"],
               "means": means, "per_frame": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(results, indent=2) + "\n")
    write_png(args.out / f"{args.name}-frame.png", (panel * 255).round().astype(np.uint8))
    lines = [f"# Textured export: texture from the field or from the images, at held-out frames", "",
             f"commit `{results['commit']}`; command `{results['command']}`", "",
             f"run `{run}`; texture {args.texture_size} px; {len(rows)} held-out test frames rendered at "
             f"{size_hw[1]}x{size_hw[0]} px; export seconds: field {results['export_seconds']['field']}, images "
             f"{results['export_seconds']['images']}; fusion: {results['fusion']}", "",
             "| rendered | PSNR full | SSIM full | box PSNR | box SSIM |", "|---|---|---|---|---|"]
    lines += [f"| {key} | {v['psnr_full_db']:.2f} | {v['ssim_full']:.4f} | {v['psnr_mask_bbox_db']:.2f} | {v['ssim_mask_bbox']:.4f} |"
              for key, v in means.items()]
    lines += ["", f"`{args.name}-frame.png`: ground truth | field render | field texture | image texture, {rows[0]['frame']}."]
    (args.out / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

if __name__ == "__main__":
    main()
