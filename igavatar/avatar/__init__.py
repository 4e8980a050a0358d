"""A trained avatar as the stages use it: artifacts read into typed records, posed, meshed.

    model = load_model(Path("run/model"))              # ModelArtifact (avatar, grids, subject)
    poses = read_poses(model, Path("walk.npz"), lambda n, where: list(range(n)))   # every frame
    posed = model.posed(poses.bone_transforms[0], poses.pose_condition[0])         # PosedAvatar

Modules: subject (subject.npz), dataset (dataset artifact), model (model artifact), facts (what
both manifests carry), poses (every pose source -> PoseSequence), cameras (camera files),
boxes (posed bounds), surfaces (canonical/posed meshes and their colors and weights), glb (the
model's rigged GLB), canonical_report (eval's canonical-shape section).
This package sits on top of the library: it may import any igavatar package; none imports it.
"""
