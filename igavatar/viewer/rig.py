"""The avatar as a browser rig: a canonical mesh, its top-4 skinning and per-frame bone poses.

    rig = ViewerRig.build(vertices, faces, colors, skin_weights, canonical_joints, parents)
    wxyz, positions = rig.bone_poses(bone_transforms)        # (J, 4), (J, 3): what viser's bones take
    x_posed = rig.skin(bone_transforms)                       # (V, 3): the same top-4 skinning, on the CPU

A skinned mesh in the browser (viser's `add_mesh_skinned`, three.js underneath) binds each bone at
its initial pose; moving a bone then moves its vertices by current @ inverse(bind). The rig binds
every bone world-aligned at its canonical joint (rotation identity, position J_b), so for a frame
whose canonical -> posed world transform of bone b is G_b = [R_b | t_b] the bone's pose is
rotation R_b at G_b(J_b): current @ inverse(bind) = G_b. `skin` applies exactly that with the
same four largest weights (renormalized), so a mesh posed here and one posed in the browser match.
Linear blend skinning only: the non-rigid offset is not shown (as in the exported GLB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.rotations import matrix_to_quaternion

#: Influences per vertex of the browser's skinned mesh (three.js reads four).
INFLUENCES = 4


@dataclass(frozen=True, eq=False)
class ViewerRig:
    """A canonical mesh ready for skinning (float32 unless stated).

    Attributes:
        vertices: (V, 3) canonical; faces: (F, 3) int64; colors: (V, 3) uint8 sRGB.
        skin_weights: (V, J) every weight (viser keeps the top 4 itself).
        top_indices: (V, 4) int64 and top_weights: (V, 4), rows summing to 1: the weights skinned here.
        canonical_joints: (J, 3); parents: (J,) int64, -1 at the root.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    skin_weights: np.ndarray
    top_indices: np.ndarray
    top_weights: np.ndarray
    canonical_joints: np.ndarray
    parents: np.ndarray

    @classmethod
    def build(cls, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, skin_weights: np.ndarray,
              canonical_joints: np.ndarray, parents: np.ndarray) -> ViewerRig:
        skin_weights = np.asarray(skin_weights, np.float32)
        # The same choice as viser's (argsort, the last four): ties resolve to the same bones.
        top = np.argsort(skin_weights, axis=-1)[:, -INFLUENCES:]
        weights = np.take_along_axis(skin_weights, top, axis=-1)
        weights = weights / np.maximum(weights.sum(-1, keepdims=True), 1e-12)
        return cls(np.asarray(vertices, np.float32), np.asarray(faces, np.int64), np.asarray(colors, np.uint8),
                   skin_weights, top.astype(np.int64), weights.astype(np.float32),
                   np.asarray(canonical_joints, np.float32), np.asarray(parents, np.int64))

    @property
    def n_bones(self) -> int:
        return int(self.canonical_joints.shape[0])

    def bind_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Bones at bind time: wxyz (J, 4) identity, positions (J, 3) the canonical joints."""
        wxyz = np.zeros((self.n_bones, 4), np.float32)
        wxyz[:, 0] = 1.0
        return wxyz, self.canonical_joints.copy()

    def bone_poses(self, bone_transforms: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Browser bone poses of one frame.

        Args:
            bone_transforms: (J, 4, 4) canonical -> posed world.
        Returns:
            wxyz (J, 4) unit quaternions of R_b, positions (J, 3) = G_b applied to the canonical joints.
        """
        g = torch.as_tensor(np.asarray(bone_transforms, np.float64))
        wxyz = matrix_to_quaternion(g[:, :3, :3]).numpy()
        joints = torch.as_tensor(self.canonical_joints, dtype=torch.float64)
        positions = torch.einsum("jab,jb->ja", g[:, :3, :3], joints) + g[:, :3, 3]
        return wxyz.astype(np.float32), positions.numpy().astype(np.float32)

    def posed_joints(self, bone_transforms: np.ndarray | torch.Tensor) -> np.ndarray:
        """(J, 3) world joints of one frame."""
        return self.bone_poses(bone_transforms)[1]

    def skin(self, bone_transforms: np.ndarray | torch.Tensor) -> np.ndarray:
        """(V, 3) world vertices: top-4 linear blend skinning of one frame's (J, 4, 4) transforms."""
        g = np.asarray(bone_transforms, np.float64)
        blended = np.einsum("vk,vkab->vab", self.top_weights.astype(np.float64), g[self.top_indices])  # (V, 4, 4)
        x = self.vertices.astype(np.float64)
        return (np.einsum("vab,vb->va", blended[:, :3, :3], x) + blended[:, :3, 3]).astype(np.float32)

    def bone_segments(self, joints: np.ndarray) -> np.ndarray:
        """(J-1, 2, 3) parent -> child segments of a skeleton with joints (J, 3), for drawing."""
        children = np.nonzero(self.parents >= 0)[0]
        return np.stack([joints[self.parents[children]], joints[children]], axis=1).astype(np.float32)
