"""Synthetic files in the SMPL model layout (never the real, licensed model) and SMPL captures.

    arrays = make_smpl_arrays(seed=0)                      # v_template (V,3), shapedirs (V,3,10), ...
    write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", arrays)   # also write_smpl_npz, write_chumpy_smpl_pkl
    capture = write_smpl_capture(tmp_path / "capture", tmp_path / "SMPL_NEUTRAL.pkl")

The body is a rough 24-joint SMPL-like T-pose (meters, +Y up, facing +Z) with a few hundred
vertices along its bones, smooth skinning weights whose rows sum to 1, a joint regressor whose rows
sum to 1 (each joint = the mean of two vertices beside it), small random shape and pose blend
shapes, and kintree_table / dtypes as the official files store them. `load_smplx` opens such a file
with the `smplx` package, the reference the tests compare igavatar's SMPL against.
"""

from __future__ import annotations

import contextlib
import json
import pickle
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse

from igavatar.body.skeleton import SMPL_PARENTS

# A rough SMPL neutral T-pose skeleton (meters): left is +X, up +Y, the face looks towards +Z.
SMPL_LIKE_REST_JOINTS = np.array([
    [0.00, 0.00, 0.00], [0.06, -0.09, 0.00], [-0.06, -0.09, 0.00], [0.00, 0.11, -0.02],
    [0.10, -0.47, 0.00], [-0.10, -0.47, 0.00], [0.00, 0.25, 0.00], [0.09, -0.87, -0.04],
    [-0.09, -0.87, -0.04], [0.00, 0.31, 0.02], [0.11, -0.93, 0.08], [-0.11, -0.93, 0.08],
    [0.00, 0.52, -0.02], [0.08, 0.42, 0.00], [-0.08, 0.42, 0.00], [0.00, 0.61, 0.03],
    [0.18, 0.45, -0.01], [-0.18, 0.45, -0.01], [0.44, 0.44, -0.03], [-0.44, 0.44, -0.03],
    [0.69, 0.45, -0.03], [-0.69, 0.45, -0.03], [0.77, 0.44, -0.04], [-0.77, 0.44, -0.04],
])
NUM_BETAS = 10
POSE_BASIS = 207
# The official pickles store the root's parent as uint32 -1.
_ROOT_PARENT_IN_FILE = 4294967295


def _tube(start: np.ndarray, end: np.ndarray, radius: float, rings: int, sides: int = 8) -> tuple[np.ndarray, list]:
    """Vertices (rings * sides, 3) of a closed-side tube along a bone, and its quad strips as triangles."""
    axis = (end - start) / np.linalg.norm(end - start)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    circle = radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    centers = start + np.linspace(0.0, 1.0, rings)[:, None] * (end - start)
    vertices = (centers[:, None] + circle[None]).reshape(-1, 3)
    faces = []
    for r in range(rings - 1):
        for k in range(sides):
            a, b = r * sides + k, r * sides + (k + 1) % sides
            faces += [(a, b, a + sides), (b, b + sides, a + sides)]
    return vertices, faces


def _bone_points(rng: np.random.Generator, points_per_bone: int, tube_radius: float | None) -> tuple[list, list]:
    """Per bone: noisy points along it with strip triangles, or (tube_radius) a tube around it."""
    joints = SMPL_LIKE_REST_JOINTS
    points, faces = [], []
    for child in range(1, len(SMPL_PARENTS)):
        parent = SMPL_PARENTS[child]
        first = sum(len(p) for p in points)
        if tube_radius is not None:
            vertices, tube_faces = _tube(joints[parent], joints[child], tube_radius, max(2, points_per_bone // 4))
            points.append(vertices)
            faces += [(first + a, first + b, first + c) for a, b, c in tube_faces]
            continue
        t = np.linspace(0.1, 0.9, points_per_bone)[:, None]
        along = joints[parent] + t * (joints[child] - joints[parent])
        points.append(along + rng.normal(scale=0.03, size=along.shape))
        # Strips of consecutive vertices of one bone: real, non-degenerate triangles for masks.
        faces += [(first + i, first + i + 1, first + i + 2) for i in range(points_per_bone - 2)]
    return points, faces


def make_smpl_arrays(seed: int = 0, points_per_bone: int = 10, tube_radius: float | None = None) -> dict:
    """Arrays of a synthetic SMPL model file, in the official layout and dtypes.

    Returns keys v_template (V,3), shapedirs (V,3,10), posedirs (V,3,207), J_regressor
    (24,V) scipy.sparse.csc_matrix, weights (V,24), kintree_table (2,24) int64, f (F,3) uint32,
    bs_style, bs_type (strings, as in the real files); V = 23 * points_per_bone + 48. With
    `tube_radius` (meters) each bone is a tube of that radius instead, so that the posed body
    has a silhouette of about a person's width.
    """
    rng = np.random.default_rng(seed)
    joints = SMPL_LIKE_REST_JOINTS
    num_joints = len(SMPL_PARENTS)
    points, faces = _bone_points(rng, points_per_bone, tube_radius)
    pair_offsets = rng.normal(scale=0.015, size=(num_joints, 3))
    first_pair = sum(len(p) for p in points)
    points.append(np.concatenate((joints + pair_offsets, joints - pair_offsets)))
    vertices = np.concatenate(points)
    num_vertices = len(vertices)
    regressor = np.zeros((num_joints, num_vertices))
    for j in range(num_joints):  # each joint is the mean of its two vertices, before and after shaping
        regressor[j, [first_pair + j, first_pair + num_joints + j]] = 0.5

    # Weights: Gaussian falloff from each joint's bone center (towards its children), top 4 kept.
    children = [[c for c in range(num_joints) if SMPL_PARENTS[c] == j] for j in range(num_joints)]
    centers = np.array([
        0.5 * (joints[j] + joints[kids].mean(0)) if kids else joints[j] for j, kids in enumerate(children)
    ])
    logits = -((vertices[:, None] - centers[None]) ** 2).sum(-1) / (2 * 0.08**2)
    keep = np.argsort(logits, axis=1)[:, -4:]
    weights = np.zeros((num_vertices, num_joints))
    kept = np.take_along_axis(logits, keep, axis=1)
    np.put_along_axis(weights, keep, np.exp(kept - kept.max(1, keepdims=True)), axis=1)
    weights /= weights.sum(1, keepdims=True)

    # Shape blend shapes: a smooth (affine) displacement field per component, plus a little noise.
    homogeneous = np.concatenate((vertices, np.ones((num_vertices, 1))), axis=1)
    fields = rng.normal(scale=0.02, size=(NUM_BETAS, 3, 4))
    shapedirs = np.einsum("bcd,vd->vcb", fields, homogeneous)
    shapedirs += rng.normal(scale=0.002, size=(num_vertices, 3, NUM_BETAS))
    posedirs = rng.normal(scale=0.002, size=(num_vertices, 3, POSE_BASIS))

    kintree = np.stack((np.array(SMPL_PARENTS, np.int64), np.arange(num_joints, dtype=np.int64)))
    kintree[0, 0] = _ROOT_PARENT_IN_FILE
    return {
        "v_template": vertices, "shapedirs": shapedirs, "posedirs": posedirs,
        "J_regressor": scipy.sparse.csc_matrix(regressor), "weights": weights,
        "kintree_table": kintree, "f": np.array(faces, dtype=np.uint32),
        "bs_style": "lbs", "bs_type": "lrotmin",
    }


def write_smpl_pkl(path: Path, arrays: dict, protocol: int = 2) -> Path:
    """Pickle `arrays` as the official files are: a dict, protocol 2, sparse J_regressor."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as stream:
        pickle.dump(dict(arrays), stream, protocol=protocol)
    return path


def write_smpl_npz(path: Path, arrays: dict, dense_regressor: bool = True) -> Path:
    """Save `arrays` as an .npz; with dense_regressor=False the sparse J_regressor goes in as a
    pickled object (what np.savez does with a dict loaded from the .pkl)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    out = dict(arrays)
    if dense_regressor:
        out["J_regressor"] = out["J_regressor"].toarray()
    else:
        out["J_regressor"] = np.array(out["J_regressor"], dtype=object)
    np.savez(path, **out)
    return path


class FakeCh:
    """Pickles like chumpy's Ch: its __dict__ minus the weak-reference caches (Ch.__getstate__).
    Pickles as chumpy.ch.Ch (inside `fake_chumpy()`)."""

    __module__ = "chumpy.ch"
    __qualname__ = "Ch"

    def __init__(self, x: np.ndarray) -> None:
        self.x = np.asarray(x, np.float64)
        self._dirty_vars = set()
        self._itr = None
        self._parents = {}
        self._cache = {"r": None, "drs": {}}
        self._depends_on_deps = {}
        self._make_dense = False
        self._make_sparse = False

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        del state["_parents"], state["_cache"]
        return state


class FakeChumpyAdd(FakeCh):
    """A chumpy expression node, chumpy.ch_ops.add: its operands, no value 'x' of its own."""

    __module__ = "chumpy.ch_ops"
    __qualname__ = "add"

    def __init__(self, a: FakeCh, b: FakeCh) -> None:
        super().__init__(np.zeros(0))
        del self.x
        self.a, self.b = a, b


@contextlib.contextmanager
def fake_chumpy():
    """Install a stand-in `chumpy` package (chumpy.ch.Ch, chumpy.ch_ops.add) while pickling, and
    remove it afterwards so that loading cannot use it. Yields (Ch, add)."""
    names = ("chumpy", "chumpy.ch", "chumpy.ch_ops")
    saved = {name: sys.modules.get(name) for name in names}
    package, ch, ch_ops = (types.ModuleType(name) for name in names)
    ch.Ch, ch_ops.add = FakeCh, FakeChumpyAdd
    package.ch, package.ch_ops = ch, ch_ops
    sys.modules.update(zip(names, (package, ch, ch_ops)))
    try:
        yield FakeCh, FakeChumpyAdd
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def write_chumpy_smpl_pkl(
    path: Path, arrays: dict, protocol: int = 2, wrapped=("v_template", "shapedirs", "posedirs", "weights")
) -> Path:
    """Pickle `arrays` with the `wrapped` ones as chumpy `Ch` objects, as the official files are."""
    with fake_chumpy() as (Ch, _):
        out = {
            key: Ch(value) if key in wrapped and not isinstance(value, FakeCh) else value
            for key, value in arrays.items()
        }
        return write_smpl_pkl(path, out, protocol=protocol)


def smplx_vertex_ids(num_vertices: int) -> dict[str, int]:
    """Indices for smplx's extra (face, feet, finger-tip) joints that exist in a small mesh."""
    names = ["nose", "reye", "leye", "rear", "lear", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"]
    names += [side + tip for side in "lr" for tip in ("thumb", "index", "middle", "ring", "pinky")]
    return {name: i % num_vertices for i, name in enumerate(names)}


def load_smplx(path: Path, num_vertices: int):
    """The smplx package's SMPL (float64) on a pickled synthetic file: the reference."""
    import torch
    import smplx

    return smplx.SMPL(
        model_path=str(path), dtype=torch.float64, num_betas=NUM_BETAS, vertex_ids=smplx_vertex_ids(num_vertices)
    )


def random_smpl_poses(n_frames: int, seed: int = 0, scale: float = 0.3) -> dict[str, np.ndarray]:
    """poses.npz arrays of body model 'smpl': betas (10,), global_orient, body_pose, transl."""
    rng = np.random.default_rng(seed)
    return {
        "betas": rng.normal(size=NUM_BETAS),
        "global_orient": rng.normal(scale=scale, size=(n_frames, 3)),
        "body_pose": rng.normal(scale=scale, size=(n_frames, 69)),
        "transl": rng.normal(scale=0.1, size=(n_frames, 3)),
    }


def smplx_posed(model, poses: dict[str, np.ndarray], zero_posedirs: bool = False):
    """smplx's posed vertices (N, V, 3) and 24 joints (N, 24, 3) for `poses`, as float64 numpy."""
    import torch

    if zero_posedirs:
        model.posedirs.zero_()
    with torch.no_grad():
        output = model(
            betas=torch.as_tensor(poses["betas"], dtype=torch.float64)[None],
            global_orient=torch.as_tensor(poses["global_orient"], dtype=torch.float64),
            body_pose=torch.as_tensor(poses["body_pose"], dtype=torch.float64),
            transl=torch.as_tensor(poses["transl"], dtype=torch.float64),
        )
    return output.vertices.numpy(), output.joints[:, : len(SMPL_PARENTS)].numpy()


def write_smpl_capture(root: Path, model_pkl: Path, n_frames: int = 3, size: int = 48, seed: int = 0) -> dict:
    """A capture v1 with body model 'smpl' posed by `model_pkl` (a plain pickle, posed with smplx):
    images and masks are the
    filled projection of the posed mesh, seen by one camera 3 m in front of the body (+Z).

    Returns the poses.npz arrays written.
    """
    arrays = pickle.loads(model_pkl.read_bytes())
    faces = np.asarray(arrays["f"], np.int64)
    poses = random_smpl_poses(n_frames, seed)
    vertices, _ = smplx_posed(load_smplx(model_pkl, len(arrays["v_template"])), poses)

    root.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir()
    (root / "masks").mkdir()
    K = np.array([[1.4 * size, 0, size / 2], [0, 1.4 * size, size / 2], [0, 0, 1]], np.float64)
    w2c = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera looking at the body's front (-Z), y down
    w2c[2, 3] = 3.0
    frames = [f"f{i:03d}" for i in range(n_frames)]
    for name, posed in zip(frames, vertices):
        camera = posed @ w2c[:3, :3].T + w2c[:3, 3]
        uv = camera[:, :2] / camera[:, 2:] @ K[:2, :2].T + K[:2, 2]
        mask = np.zeros((size, size), np.uint8)
        cv2.fillPoly(mask, [np.round(tri).astype(np.int32) for tri in uv[faces]], 255)
        for u, v in np.round(uv).astype(int):
            cv2.circle(mask, (int(u), int(v)), 1, 255, -1)
        image = np.where(mask[..., None] > 0, np.array([90, 140, 200], np.uint8), np.uint8(20))
        cv2.imwrite(str(root / "images" / f"{name}.png"), image)
        cv2.imwrite(str(root / "masks" / f"{name}.png"), mask)
    np.savez(root / "cameras.npz", K=K, w2c=w2c, height=size, width=size)
    np.savez(root / "poses.npz", **poses)
    meta = {
        "format": "igavatar-capture", "version": 1, "body_model": "smpl", "frames": frames,
        "splits": {"train": frames[:-1], "test": frames[-1:]},
    }
    (root / "capture.json").write_text(json.dumps(meta))
    return poses
