"""A trained avatar as the stages use it: artifacts read into typed records, posed, meshed.

    model = load_model(Path("run/model"))              # ModelArtifact (avatar, grids, subject)
    poses = read_poses("walk", model, ...)              # PoseSequence from any pose source
    posed = model.posed(poses.bone_transforms[0], poses.pose_condition[0])   # PosedAvatar

Modules: subject (subject.npz), dataset (dataset artifact), model (model artifact),
pose_files (pose I/O and retargeting), poses (every pose source -> PoseSequence),
boxes (posed bounds), surfaces (canonical/posed meshes and their colors and weights).
This package sits on top of the library: it may import any igavatar package; none imports it.
"""
