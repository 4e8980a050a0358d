"""The pieces of a GLB that igavatar.mesh.gltf's writer assembles: the binary buffer with its views
and accessors, the animation of a motion, and the material.

    builder = BinaryBuilder()
    positions = builder.add(vertices.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, pygltflib.ARRAY_BUFFER,
                            with_bounds=True)
    animation = animation_of(builder, rotations_gltf, translation_gltf, fps, root_offset)
    material, images, textures, samplers = material_of(builder, png_bytes_or_none)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pygltflib
import torch

from igavatar.body.rotations import matrix_to_quaternion
from igavatar.errors import InputError


class BinaryBuilder:
    """Accumulates 4-byte-aligned buffer views and their accessors for one GLB buffer."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def add(
        self,
        array: np.ndarray,
        component_type: int,
        accessor_type: str,
        target: int | None = None,
        with_bounds: bool = False,
        normalized: bool = False,
    ) -> int:
        """Append `array` (count, components) as one view + accessor; returns the accessor index."""
        data = np.ascontiguousarray(array)
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        self.views.append(
            pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=data.nbytes, target=target)
        )
        self.blob.extend(data.tobytes())
        accessor = pygltflib.Accessor(
            bufferView=len(self.views) - 1,
            byteOffset=0,
            componentType=component_type,
            normalized=normalized,
            count=int(data.shape[0]),
            type=accessor_type,
        )
        if with_bounds:
            flat = data.reshape(data.shape[0], -1)
            accessor.min = [float(x) for x in flat.min(axis=0)]
            accessor.max = [float(x) for x in flat.max(axis=0)]
        else:
            accessor.min = None
            accessor.max = None
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def as_array(value: Any) -> np.ndarray:
    """numpy view of an array-like or a (CPU or device) tensor."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """glTF quaternions (..., 4) as x, y, z, w of rotation matrices (..., 3, 3)."""
    wxyz = matrix_to_quaternion(torch.as_tensor(rotations, dtype=torch.float64)).numpy()
    return np.concatenate((wxyz[..., 1:], wxyz[..., :1]), axis=-1)


def check_rotations(rotations: np.ndarray, what: str) -> None:
    gram = np.swapaxes(rotations, -1, -2) @ rotations
    if not np.allclose(gram, np.eye(3), atol=1e-4) or np.any(np.linalg.det(rotations) <= 0):
        raise InputError(f"{what}: not all 3x3 matrices are rotations (orthonormal, det +1)")


def checked_animation(animation: Any, num_joints: int, path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(local_rotations (N, J, 3, 3), root_translation (N, 3), fps) as float64 arrays and a float;
    InputError naming `path` when a part is malformed."""
    try:
        rotations, translation, fps = animation
    except (TypeError, ValueError):
        raise InputError(f"{path}: animation must be (local_rotations, root_translation, fps)") from None
    rotations = as_array(rotations).astype(np.float64)
    translation = as_array(translation).astype(np.float64)
    if rotations.ndim != 4 or rotations.shape[1:] != (num_joints, 3, 3) or rotations.shape[0] == 0:
        raise InputError(
            f"{path}: animation rotations have shape {rotations.shape}, expected (N, {num_joints}, 3, 3)"
        )
    num_frames = rotations.shape[0]
    if translation.shape != (num_frames, 3) or not np.all(np.isfinite(translation)):
        raise InputError(
            f"{path}: animation root_translation has shape {translation.shape}, expected finite ({num_frames}, 3)"
        )
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise InputError(f"{path}: animation fps = {fps!r}, expected a number > 0") from None
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"{path}: animation fps = {fps}, expected > 0")
    check_rotations(rotations, f"{path}: animation rotations")
    return rotations, translation, fps


def animation_of(builder: BinaryBuilder, rotations: np.ndarray, translation: np.ndarray, fps: float,
                 root_offset: np.ndarray) -> pygltflib.Animation:
    """Keyframe accessors and the Animation of a motion already in glTF's frame.

    Args:
        rotations: (N, J, 3, 3) node rotations; translation: (N, 3) root offsets from its bind
            position root_offset (3,); fps: keys per second (LINEAR interpolation).
    """
    num_frames, num_joints = rotations.shape[:2]
    times = builder.add(
        (np.arange(num_frames, dtype=np.float64) / float(fps)).astype(np.float32),
        pygltflib.FLOAT, pygltflib.SCALAR, with_bounds=True,  # sampler inputs need min/max
    )
    quaternions = quaternions_xyzw(rotations)  # (N, J, 4)
    # LINEAR rotation keyframes are slerped: keep consecutive quaternions in one hemisphere so
    # every viewer takes the short way.
    for n in range(1, num_frames):
        flip = (quaternions[n] * quaternions[n - 1]).sum(axis=-1) < 0
        quaternions[n, flip] *= -1.0
    samplers, channels = [], []
    for j in range(num_joints):
        output = builder.add(quaternions[:, j].astype(np.float32), pygltflib.FLOAT, pygltflib.VEC4)
        samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(
            sampler=j, target=pygltflib.AnimationChannelTarget(node=j, path="rotation")))
    root_positions = builder.add(
        (root_offset[None, :] + translation).astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3
    )
    samplers.append(pygltflib.AnimationSampler(input=times, output=root_positions, interpolation="LINEAR"))
    channels.append(pygltflib.AnimationChannel(
        sampler=num_joints, target=pygltflib.AnimationChannelTarget(node=0, path="translation")))
    return pygltflib.Animation(name="motion", samplers=samplers, channels=channels, extras={"fps": float(fps)})


def material_of(builder: BinaryBuilder, png: bytes | None) -> tuple[pygltflib.Material, list, list, list]:
    """The material (vertex colours, or the embedded PNG) and the images, textures, samplers it uses."""
    color = pygltflib.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0)
    material = pygltflib.Material(name="vertex_color" if png is None else "texture", pbrMetallicRoughness=color,
                                  doubleSided=False)
    if png is None:
        return material, [], [], []
    builder.blob.extend(b"\0" * (-len(builder.blob) % 4))
    builder.views.append(pygltflib.BufferView(buffer=0, byteOffset=len(builder.blob), byteLength=len(png)))
    builder.blob.extend(png)
    images = [pygltflib.Image(name="base_color", mimeType="image/png", bufferView=len(builder.views) - 1)]
    # Linear filtering with mipmaps; clamp, since the atlas charts never wrap.
    samplers = [pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR_MIPMAP_LINEAR,
                                  wrapS=pygltflib.CLAMP_TO_EDGE, wrapT=pygltflib.CLAMP_TO_EDGE)]
    color.baseColorTexture = pygltflib.TextureInfo(index=0, texCoord=0)
    return material, images, [pygltflib.Texture(sampler=0, source=0)], samplers
