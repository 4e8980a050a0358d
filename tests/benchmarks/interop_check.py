"""Interop check of igavatar's GLBs: Khronos glTF validator, Blender import, posed vertices, texture PSNR.

    python tests/benchmarks/interop_check.py --model igavatar-run/model [--pose igavatar-run/capture]
        [--validator-dir DIR] [--out tests/benchmarks/results/interop] [--frames 0,5,10]

Not part of the test suite, and it installs nothing. It:
1. exports the model with `--texture-size 1024 --textured-faces 30000 --pose POSE --all --glb-faces 0`
   (canonical.glb: rigged, full resolution so that its vertices compare in order with posed/*.ply,
   vertex colors, the capture's poses as an animation; textured/avatar.glb: decimated, textured,
   animated) twice, with 4 and with 8 influences, once with export's defaults (the engine-sized
   canonical.glb a user gets: its size, its distance to the full mesh, where it stands), and runs
   `animate walk --glb`;
2. runs the Khronos glTF validator (`npm install gltf-validator` in --validator-dir, then node) on
   every GLB and records errors/warnings/infos;
3. if `blender` is on PATH (Debian: `apt-get install blender`), imports each GLB headless
   (`blender -b --python blender_probe.py`), checks armature, skin, texture and animation,
   evaluates the skinned mesh at --frames and compares its vertices with igavatar's posed meshes of the
   same frames (`export --pose` posed/<frame>.ply), against the drift the manifest reports; and
   renders the textured avatar with Cycles (a PNG to look at);
4. renders the full-resolution vertex-colored mesh and the textured decimated mesh from 4 views
   (igavatar's ray caster, the same cameras) and reports the texture's PSNR against the former.
Results go to --out/interop.json and interop.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from provenance import command, commit  # noqa: E402
from igavatar.artifacts.manifest import read_artifact  # noqa: E402
from igavatar.geometry.raycast import CameraRays, MeshRayCaster, interpolate_vertex_values  # noqa: E402
from igavatar.mesh.gltf_read import gltf_to_world, read_rigged_glb  # noqa: E402
from igavatar.mesh.maps import frontal_camera  # noqa: E402
from igavatar.mesh.texture import sample_texture  # noqa: E402
from stages.animate import AnimateOptions, run_animate  # noqa: E402
from stages.export import ExportOptions, run_export  # noqa: E402

PROBE = Path(__file__).with_name("blender_probe.py")
VALIDATE_JS = """
const fs = require('fs');
const validator = require('gltf-validator');
(async () => {
  const out = {};
  for (const path of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(path)), {maxIssues: 50});
    out[path] = {numErrors: report.issues.numErrors, numWarnings: report.issues.numWarnings,
                 numInfos: report.issues.numInfos, numHints: report.issues.numHints,
                 messages: report.issues.messages.slice(0, 20), validatorVersion: report.validatorVersion,
                 info: report.info};
  }
  console.log(JSON.stringify(out));
})();
"""


def validate(glbs: list[Path], validator_dir: Path) -> dict:
    """The Khronos validator's report summary per file (needs node and gltf-validator installed there)."""
    if shutil.which("node") is None or not (validator_dir / "node_modules" / "gltf-validator").is_dir():
        return {"skipped": f"node or {validator_dir}/node_modules/gltf-validator missing (npm install gltf-validator)"}
    script = validator_dir / "validate_igavatar.js"
    script.write_text(VALIDATE_JS)
    result = subprocess.run(["node", str(script), *map(str, glbs)], capture_output=True, text=True, cwd=validator_dir)
    if result.returncode != 0:
        return {"failed": result.stderr[-2000:]}
    return json.loads(result.stdout)


def blender_probe(glb: Path, frames: list[int], out: Path, render: bool) -> dict:
    """Import `glb` in headless Blender, evaluate the skinned mesh at `frames`, optionally render."""
    if shutil.which("blender") is None:
        return {"skipped": "blender is not on PATH"}
    args = ["blender", "-b", "--factory-startup", "--python", str(PROBE), "--", str(glb), str(out),
            ",".join(map(str, frames)), "render" if render else "norender"]
    started = time.perf_counter()
    result = subprocess.run(args, capture_output=True, text=True)
    report_path = out.with_suffix(".json")
    if result.returncode != 0 or not report_path.is_file():
        return {"failed": (result.stdout + result.stderr)[-3000:]}
    report = json.loads(report_path.read_text())
    report["blender_seconds"] = time.perf_counter() - started
    return report


def to_blender(points: np.ndarray, glb_record: dict) -> np.ndarray:
    """Capture-frame points in Blender's frame: glTF's Y-up frame (origin on the floor), then
    Blender's (x, -z, y) import."""
    gltf = np.asarray(points, np.float64) @ np.asarray(glb_record["world_to_gltf"]).T + glb_record["world_to_gltf_offset"]
    return np.stack((gltf[:, 0], -gltf[:, 2], gltf[:, 1]), axis=1)


def compare_frames(probe: dict, mesh_dir: Path, glb_record: dict, frame_names: list[str], picked: list[int],
                   reference_vertices: int) -> list[dict]:
    """Blender's evaluated vertices against posed/<frame>.ply (same vertex order when counts match)."""
    rows = []
    for k, index in enumerate(picked):
        posed = np.asarray(trimesh.load(mesh_dir / "posed" / f"{frame_names[index]}.ply", process=False).vertices)
        ours = to_blender(posed, glb_record)
        local = np.fromfile(probe["vertex_files"][k], dtype=np.float64).reshape(-1, 3)
        matrix = np.asarray(probe["matrix_world"][k])
        theirs = local @ matrix[:3, :3].T + matrix[:3, 3]
        row = {"frame_index": index, "frame": frame_names[index], "blender_vertices": int(theirs.shape[0]),
               "igavatar_vertices": int(ours.shape[0])}
        if theirs.shape == ours.shape:
            gap = np.linalg.norm(theirs - ours, axis=1) * 1e3
            row.update(max_mm=float(gap.max()), mean_mm=float(gap.mean()), matching="vertex order")
        else:  # the importer reordered or merged vertices: nearest igavatar vertex instead
            from scipy.spatial import cKDTree

            gap = cKDTree(ours).query(theirs)[0] * 1e3
            row.update(max_mm=float(gap.max()), mean_mm=float(gap.mean()), matching="nearest vertex (upper bound is the true gap)")
        rows.append(row)
    return rows


def render_views(vertices: np.ndarray, faces: np.ndarray, color_at_hits, size: int, axes_list) -> list[np.ndarray]:
    """sRGB float images on white of a mesh from cameras framing it; color_at_hits(hits) -> (R, 3)."""
    caster = MeshRayCaster(vertices, faces)
    images = []
    for K, w2c in axes_list:
        rays = CameraRays(K, w2c, size, size, supersample=1)
        directions = rays.directions.reshape(-1, 3)
        hits = caster.first_hits(np.broadcast_to(rays.origin, directions.shape), directions)
        rgb = np.where(hits.hit[:, None], color_at_hits(hits), 1.0)
        images.append(rgb.reshape(size, size, 3))
    return images


def texture_psnr(mesh_dir: Path, body_axes: np.ndarray, size: int = 512) -> dict:
    """PSNR of the textured decimated mesh against the full vertex-colored mesh, 4 views about the body."""
    full = trimesh.load(mesh_dir / "canonical.ply", process=False)
    glb = read_rigged_glb(mesh_dir / "textured" / "avatar.glb")
    texture = cv2.cvtColor(cv2.imread(str(mesh_dir / "textured" / "avatar.png")), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
    world = gltf_to_world(glb["vertices"], glb["world_to_gltf"], glb["world_to_gltf_offset"])  # capture frame
    cameras = []
    for angle in (0.0, 90.0, 180.0, 270.0):
        turn = np.deg2rad(angle)
        # Rotate the body's left and forward axes about its up axis: front, side, back, side.
        left, up, forward = body_axes.T
        axes = np.stack((np.cos(turn) * left + np.sin(turn) * forward, up,
                         -np.sin(turn) * left + np.cos(turn) * forward), axis=1)
        cameras.append(frontal_camera(np.asarray(full.vertices), axes, size))
    colors = np.asarray(full.visual.vertex_colors)[:, :3] / 255.0
    reference = render_views(np.asarray(full.vertices), np.asarray(full.faces),
                             lambda hits: interpolate_vertex_values(colors, np.asarray(full.faces), hits), size, cameras)

    def sample(hits):
        return sample_texture(texture, interpolate_vertex_values(glb["uv"], glb["faces"], hits))

    textured = render_views(world, glb["faces"], sample, size, cameras)
    rows = []
    for name, a, b in zip(("front", "left", "back", "right"), reference, textured):
        mse = float(np.mean((a - b) ** 2))
        rows.append({"view": name, "psnr_db": float(10 * np.log10(1.0 / max(mse, 1e-12)))})
    sheet = np.concatenate([np.concatenate(reference, axis=1), np.concatenate(textured, axis=1)], axis=0)
    cv2.imwrite(str(mesh_dir.parent / "psnr_views.png"), cv2.cvtColor((sheet * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    return {"views": rows, "mean_psnr_db": float(np.mean([r["psnr_db"] for r in rows])), "size": size,
            "sheet": str(mesh_dir.parent / "psnr_views.png"),
            "note": "top row: full vertex-colored mesh; bottom: decimated textured mesh; white background"}


def capture_psnr(mesh_dir: Path, model_path: Path, capture: Path) -> dict:
    """PSNR inside the subject's mask against the capture's own images (ground truth) of 4 training
    views, for the full vertex-colored posed mesh (posed/<frame>.ply) and for the textured decimated
    mesh posed the same way (igavatar's posing, so only the texture differs), both ray cast with the
    capture's camera. Acceptance: the textured mesh within 1.5 dB of the full one."""
    from igavatar.body.pose_files import read_pose_sequence, sequence_local_pose
    from igavatar.avatar.model import load_model

    meta = json.loads((capture / "capture.json").read_text())
    frames = [f["name"] if isinstance(f, dict) else f for f in meta["frames"]]
    train = [f if isinstance(f, str) else f["name"] for f in meta["splits"]["train"]]
    cameras = np.load(capture / "cameras.npz")
    model = load_model(model_path)
    glb = read_rigged_glb(mesh_dir / "textured" / "avatar.glb")
    canonical_textured = gltf_to_world(glb["vertices"], glb["world_to_gltf"], glb["world_to_gltf_offset"])
    texture = cv2.cvtColor(cv2.imread(str(mesh_dir / "textured" / "avatar.png")), cv2.COLOR_BGR2RGB).astype(np.float64) / 255
    rows, panels = [], []
    views = [train[round(i * len(train) / 4)] for i in range(4)]  # the training turn: front, side, back, side
    sequence = read_pose_sequence(capture)
    phenotype = model.manifest["data"].get("subject", {}).get("phenotype")
    rotations, translation = sequence_local_pose(sequence, model.skeleton, model.body_model, phenotype=phenotype)
    posed = model.pose(rotations, translation)
    for name in views:
        index = frames.index(name)
        K = cameras["K"][index] if cameras["K"].ndim == 3 else cameras["K"]
        w2c = cameras["w2c"][index] if cameras["w2c"].ndim == 3 else cameras["w2c"]
        height, width = int(cameras["height"]), int(cameras["width"])
        image = cv2.cvtColor(cv2.imread(str(capture / "images" / f"{name}.png")), cv2.COLOR_BGR2RGB) / 255.0
        mask = cv2.imread(str(capture / "masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        rays = CameraRays(K, w2c, height, width, supersample=1)
        directions = rays.directions.reshape(-1, 3)
        origins = np.broadcast_to(rays.origin, directions.shape)

        full = trimesh.load(mesh_dir / "posed" / f"{name}.ply", process=False)
        hits = MeshRayCaster(np.asarray(full.vertices), np.asarray(full.faces)).first_hits(origins, directions)
        colors = np.asarray(full.visual.vertex_colors)[:, :3] / 255.0
        render_full = np.where(hits.hit[:, None], interpolate_vertex_values(colors, np.asarray(full.faces), hits), 0.0)

        x_posed = model.posed(posed.bone_transforms[index], posed.pose_condition[index]).pose_vertices(canonical_textured)
        hits = MeshRayCaster(x_posed, glb["faces"]).first_hits(origins, directions)
        uv = interpolate_vertex_values(glb["uv"], glb["faces"], hits)
        render_tex = np.where(hits.hit[:, None], sample_texture(texture, uv), 0.0)
        row = {"frame": name}
        for label, render in (("full_vertex_color", render_full), ("textured", render_tex)):
            diff = (render.reshape(height, width, 3) - image)[mask]
            row[f"{label}_psnr_db"] = float(10 * np.log10(1.0 / max(float(np.mean(diff ** 2)), 1e-12)))
        rows.append(row)
        panels.append(np.concatenate([image, render_full.reshape(height, width, 3), render_tex.reshape(height, width, 3)], axis=0))
    sheet = np.concatenate(panels, axis=1)
    cv2.imwrite(str(mesh_dir.parent / "capture_psnr_views.png"), cv2.cvtColor((sheet * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    mean_full = float(np.mean([r["full_vertex_color_psnr_db"] for r in rows]))
    mean_tex = float(np.mean([r["textured_psnr_db"] for r in rows]))
    return {"views": rows, "mean_full_vertex_color_psnr_db": mean_full, "mean_textured_psnr_db": mean_tex,
            "textured_minus_full_db": mean_tex - mean_full, "sheet": str(mesh_dir.parent / "capture_psnr_views.png"),
            "note": "PSNR inside the capture's subject mask; sheet rows: capture image, full vertex-colored, textured"}


def markdown(report: dict) -> str:
    """The human-readable summary of a report (interop.md)."""
    lines = ["# GLB interop check", "", f"Commit: `{report.get('commit', 'not recorded')}`. Command: `{report.get('command')}`", "",
             f"Model `{report['model']}`, poses `{report['pose']}`.", "",
             "## Khronos glTF validator", "", "| file | errors | warnings | infos | hints |", "|---|---|---|---|---|"]
    for path, result in report["validator"].items():
        if isinstance(result, dict) and "numErrors" in result:
            lines.append(f"| {'/'.join(Path(path).parts[-3:])} | {result['numErrors']} | {result['numWarnings']} | "
                         f"{result['numInfos']} | {result['numHints']} |")
        else:
            lines.append(f"| {path} | {result} | | | |")
    lines += ["", "## Blender (headless import)", "",
              "| GLB | bones | vertices | max influences | texture | action frames | head above feet (m, Blender Z) | moved between keys (mm) | lowest vertex Z (m) | feet centre XY (m) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for label, probe in report["blender"].items():
        if "failed" in probe or "skipped" in probe:
            lines.append(f"| {label} | {probe.get('skipped') or 'failed'} | | | | | | |")
            continue
        action = probe.get("action") or {}
        texture = ", ".join(f"{t['size'][0]}x{t['size'][1]}" + (" -> Base Color" if t["to_base_color"] else "")
                            for t in probe.get("textures", [])) or "vertex colors"
        lines.append(f"| {label} | {probe.get('bones')} | {probe['vertices']} | {probe['max_influences']} | {texture} | "
                     f"{action.get('frame_range')} | {probe.get('head_above_feet_m', float('nan')):.3f} | "
                     f"{probe.get('motion_between_keys_mm', 0):.0f} | {probe.get('rest_min_z_m', float('nan')):.4f} | "
                     f"{', '.join(f'{x:.3f}' for x in probe.get('feet_center_xy_m', []))} |")
    lines += ["", "## Blender's skinned vertices vs `igavatar export --pose` (same frames)", "",
              "| GLB | frame | Blender vs igavatar max / mean (mm) | manifest drift max / mean (mm) |", "|---|---|---|---|"]
    for label, probe in report["blender"].items():
        influences = label.rsplit("_", 1)[-1]
        for row in probe.get("frames_vs_export_pose", []) or []:
            drift = probe["reported_drift_mm"][str(row["frame_index"])][influences]
            lines.append(f"| {label} | {row['frame']} | {row['max_mm']:.2f} / {row['mean_mm']:.2f} ({row['matching']}) | "
                         f"{drift['max']:.2f} / {drift['mean']:.2f} |")
    walk = report.get("animate", {}).get("glb")
    if walk:
        lines += ["", f"`animate walk --glb` (30 frames): drift max top-4 {walk['drift_mm']['4']:.1f} mm, "
                      f"top-8 {walk['drift_mm']['8']:.1f} mm over the frames."]
    default = report.get("default_export")
    if default:
        mesh = default["glb"]["mesh"]
        lines += ["", "## The default export (what a user gets)", "",
                  f"canonical.glb: {mesh['faces']} faces, {mesh['vertices']} vertices, decimated from {mesh['full_faces']} "
                  f"(canonical.ply keeps them), {default['bytes']['canonical.glb'] / 1e6:.2f} MB "
                  f"(canonical.ply {default['bytes']['canonical.ply'] / 1e6:.2f} MB); distance to the full mesh "
                  f"max {mesh['deviation_mm']['max']:.2f} mm, mean {mesh['deviation_mm']['mean']:.3f} mm; "
                  f"origin {default['glb'].get('origin')}."]
    lines += ["", "## Texture", ""]
    for influences, export in report["exports"].items():
        textured = export["textured"]
        timings = export["timings"]
        lines.append(f"- export with {influences} influences: textured {textured['faces']} faces, "
                     f"{textured['vertices']} vertices, {textured['texture_size']} px, texel coverage "
                     f"{textured['texel_coverage']:.2f}; files {textured['bytes']}; canonical.glb "
                     f"{export['bytes']['canonical.glb']} B; textured mesh build {timings.get('textured_s', float('nan')):.1f} s, "
                     f"whole export {timings['total_s']:.1f} s")
    psnr = report["texture_psnr"]
    lines.append(f"- textured vs full vertex-colored render, 4 views ({psnr['size']} px): "
                 + ", ".join(f"{r['view']} {r['psnr_db']:.2f} dB" for r in psnr["views"]) + f"; mean {psnr['mean_psnr_db']:.2f} dB")
    capture = report.get("capture_psnr")
    if capture:
        lines.append(f"- against the capture's images (inside the mask, 4 training views): full vertex-colored "
                     f"{capture['mean_full_vertex_color_psnr_db']:.2f} dB, textured {capture['mean_textured_psnr_db']:.2f} dB "
                     f"(difference {capture['textured_minus_full_db']:+.2f} dB)")
    return "\n".join(lines) + "\n"


def capture_subset(capture: Path, count: int, dest: Path) -> Path:
    """A capture v1 directory holding `count` training frames spread over the turn (front, side, ...).

    Exporting every frame of a long capture at full resolution takes minutes per frame on two
    shared cores; the check needs only a few. Images and masks are linked, arrays sliced.
    """
    meta = json.loads((capture / "capture.json").read_text())
    names = [f if isinstance(f, str) else f["name"] for f in meta["frames"]]
    train = [f if isinstance(f, str) else f["name"] for f in meta["splits"]["train"]]
    chosen = [train[round(i * len(train) / count)] for i in range(count)]
    index = [names.index(n) for n in chosen]
    if dest.exists():
        shutil.rmtree(dest)
    (dest / "images").mkdir(parents=True)
    (dest / "masks").mkdir()
    for name in chosen:
        for folder in ("images", "masks"):
            if (capture / folder / f"{name}.png").is_file():
                (dest / folder / f"{name}.png").symlink_to((capture / folder / f"{name}.png").resolve())
    meta["frames"] = [meta["frames"][i] for i in index]
    meta["splits"] = {"train": chosen, "test": []}
    (dest / "capture.json").write_text(json.dumps(meta))
    per_frame = len(names)
    for file in ("poses.npz", "cameras.npz"):
        with np.load(capture / file) as arrays:
            sliced = {k: (v[index] if v.ndim and v.shape[0] == per_frame and k not in ("K", "w2c") or
                          (k in ("K", "w2c") and v.ndim == 3) else v) for k, v in arrays.items()}
        np.savez(dest / file, **sliced)
    return dest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, default=Path("igavatar-run/model"))
    parser.add_argument("--pose", type=Path, default=None, help="pose source for the animated export (default: the model's capture)")
    parser.add_argument("--out", type=Path, default=REPO / "tests" / "benchmarks" / "results" / "interop")
    parser.add_argument("--work", type=Path, default=Path("/tmp/igavatar-interop"))
    parser.add_argument("--validator-dir", type=Path, default=Path("/tmp/gltfval"))
    parser.add_argument("--frames", default="0,1,2", help="frame indices of the exported poses compared in Blender")
    parser.add_argument("--views", type=int, default=4,
                        help="with a capture as --pose: export only this many training frames spread over the turn (0: all)")
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--texture-size", type=int, default=1024)
    parser.add_argument("--textured-faces", type=int, default=30_000)
    parser.add_argument("--reuse", action="store_true", help="reuse the exports and animation already in --work")
    args = parser.parse_args()
    picked = [int(f) for f in args.frames.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    model_manifest = read_artifact(args.model, expected="model")
    pose = args.pose
    if pose is None:
        dataset = Path(model_manifest["inputs"][0]["path"])
        pose = Path(read_artifact(dataset, expected="dataset")["inputs"][0]["path"])
        pose = pose.parent if pose.is_file() else pose  # a capture without a manifest is recorded by its capture.json
    if args.views and (pose / "capture.json").is_file():
        pose = capture_subset(pose, args.views, args.work / "capture_subset")
    report: dict = {"commit": commit(), "command": command(), "model": str(args.model), "pose": str(pose), "exports": {}}

    glbs: list[Path] = []
    for influences in (4, 8):
        out = args.work / f"mesh{influences}"
        started = time.perf_counter()
        summary = run_export(ExportOptions(
            model=args.model, out=out, resolution=args.resolution, pose=pose, all_frames=True, influences=influences,
            texture_size=args.texture_size, textured_faces=args.textured_faces, force=not args.reuse, device="cpu",
            texture_from="field",  # this check measures baking fidelity against the vertex colors
            glb_faces=0,  # the full mesh, so that Blender's vertices compare with posed/*.ply in order
        ))
        data = read_artifact(out, expected="mesh")
        report["exports"][str(influences)] = {
            "seconds": time.perf_counter() - started, "summary": summary,
            "timings": data["timings"], "glb": data["data"]["glb"], "textured": data["data"]["textured"],
            "bytes": {p.name: p.stat().st_size for p in [out / "canonical.glb", out / "canonical.ply"]},
        }
        glbs += [out / "canonical.glb", out / "textured" / "avatar.glb"]
    # The default export, as a user gets it: canonical.glb decimated for engines, on the floor.
    default_dir = args.work / "mesh_default"
    run_export(ExportOptions(model=args.model, out=default_dir, resolution=args.resolution, force=not args.reuse,
                             device="cpu"))
    default = read_artifact(default_dir, expected="mesh")["data"]
    report["default_export"] = {"glb": default["glb"], "canonical_faces": default["canonical"]["faces"],
                                "bytes": {p.name: p.stat().st_size for p in [default_dir / "canonical.glb",
                                                                             default_dir / "canonical.ply"]}}
    glbs.append(default_dir / "canonical.glb")
    started = time.perf_counter()
    if not (args.reuse and (args.work / "animation" / "animation.glb").is_file()):
        run_animate(AnimateOptions(model=args.model, out=args.work / "animation", motion="walk", frames=30, glb=True,
                                   meshes=True, resolution=128, samples=16, device="cpu"))
    animation = read_artifact(args.work / "animation", expected="animation")["data"]
    report["animate"] = {"seconds": time.perf_counter() - started, "glb": animation["glb"]}
    glbs.append(args.work / "animation" / "animation.glb")

    report["validator"] = validate(glbs, args.validator_dir)

    report["blender"] = {}
    for influences in (4, 8):
        mesh_dir = args.work / f"mesh{influences}"
        data = read_artifact(mesh_dir, expected="mesh")["data"]
        names = [f["name"] for f in data["posed"]["frames"]]
        for label, glb in (("canonical", mesh_dir / "canonical.glb"), ("textured", mesh_dir / "textured" / "avatar.glb")):
            probe = blender_probe(glb, picked, args.work / f"blender_{label}{influences}",
                                  render=(label == "textured" and influences == 4))
            if "vertex_files" in probe and label == "canonical":
                probe["frames_vs_export_pose"] = compare_frames(probe, mesh_dir, data["glb"], names, picked,
                                                                data["canonical"]["vertices"])
                probe["reported_drift_mm"] = {str(i): data["posed"]["frames"][i]["glb_drift_mm"] for i in picked}
            report["blender"][f"{label}_{influences}"] = probe
            if probe.get("render"):
                shutil.copy(probe["render"], args.out / "blender_textured_render.png")
    report["blender"]["default_canonical"] = blender_probe(default_dir / "canonical.glb", [], args.work / "blender_default",
                                                           render=False)
    report["blender"]["animation_walk"] = blender_probe(args.work / "animation" / "animation.glb", [0, 15, 29],
                                                        args.work / "blender_walk", render=False)

    from igavatar.body.motions import body_to_world

    report["texture_psnr"] = texture_psnr(args.work / "mesh4", body_to_world("anny"))
    shutil.copy(report["texture_psnr"]["sheet"], args.out / "psnr_views.png")
    if (pose / "capture.json").is_file():
        report["capture_psnr"] = capture_psnr(args.work / "mesh4", args.model, pose)
        shutil.copy(report["capture_psnr"]["sheet"], args.out / "capture_psnr_views.png")
    (args.out / "interop.json").write_text(json.dumps(report, indent=1, default=str))
    (args.out / "interop.md").write_text(markdown(report))
    print(json.dumps({k: report.get(k) for k in ("texture_psnr", "capture_psnr")}, indent=1, default=str)[:6000])


if __name__ == "__main__":
    main()
