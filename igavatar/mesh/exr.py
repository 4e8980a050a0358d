"""Float image maps (depth, normals, color) as OpenEXR files, written atomically.

    write_exr(path, {"Z": depth (H, W), "N": normals (H, W, 3), "RGB": rgb (H, W, 3)})
    maps = read_exr(path)          # {"Z": (H, W), "N": (H, W, 3), "RGB": (H, W, 3)} float32

Channel naming (OpenEXR's own conventions, so any EXR viewer shows the layers):
- a 2-D map under key K is the single channel "K"; use "Z" for depth (camera z in meters, OpenEXR's
  standard depth channel) and "A" for alpha/coverage;
- a (H, W, 3) map under key "RGB" is the default layer's channels "R", "G", "B";
- a (H, W, 3) map under any other key K is the layer "K" with channels "K.R", "K.G", "K.B" (the
  three components in order; use "N" for normals, x/y/z in the frame the caller documents).
`read_exr` undoes this: "R","G","B" -> "RGB"; "K.R","K.G","K.B" (or "K.X","K.Y","K.Z", as other
tools write) -> "K" (H, W, 3); every other channel -> its own (H, W) array. Pixels are stored as
32-bit float with lossless ZIP compression, so float32 maps (inf and NaN included) round-trip bit
for bit; other dtypes are converted to float32 first.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from igavatar.artifacts.atomic import current_umask
from igavatar.errors import InputError

_COMPONENTS = ("R", "G", "B")
_ALTERNATIVE_COMPONENTS = ("X", "Y", "Z")


def _channel_names(key: str) -> tuple[str, str, str]:
    """EXR channel names of a 3-component map stored under `key`."""
    if key == "RGB":
        return _COMPONENTS
    return tuple(f"{key}.{c}" for c in _COMPONENTS)  # type: ignore[return-value]


def write_exr(path: str | os.PathLike[str], channels: dict[str, np.ndarray]) -> None:
    """Write float maps to one EXR file (temporary sibling + rename, so never half-written).

    Args:
        path: the .exr file to write (parent directories are created).
        channels: name -> (H, W) or (H, W, 3) array, every one of the same H and W; see the module
            docstring for how names become EXR channels.
    """
    path = Path(path)
    if not channels:
        raise InputError(f"{path}: write_exr was given no channels")
    size: tuple[int, int] | None = None
    exr_channels: dict[str, np.ndarray] = {}
    for key, array in channels.items():
        if not isinstance(key, str) or not key or key.startswith(".") or key.endswith("."):
            raise InputError(f"{path}: channel name {key!r} must be a non-empty string not starting or ending with '.'")
        data = np.asarray(array)
        if data.ndim not in (2, 3) or (data.ndim == 3 and data.shape[2] != 3):
            raise InputError(f"{path}: channel {key!r} has shape {data.shape}, expected (H, W) or (H, W, 3)")
        if not (np.issubdtype(data.dtype, np.number) or data.dtype == bool):
            raise InputError(f"{path}: channel {key!r} has dtype {data.dtype}, expected numbers")
        if size is None:
            size = data.shape[:2]
        elif data.shape[:2] != size:
            raise InputError(
                f"{path}: channel {key!r} is {data.shape[0]}x{data.shape[1]} but the first channel "
                f"is {size[0]}x{size[1]}; every map in one EXR must have the same size"
            )
        if data.shape[0] == 0 or data.shape[1] == 0:
            raise InputError(f"{path}: channel {key!r} has shape {data.shape}; an image needs pixels")
        names: tuple[str, ...] = (key,) if data.ndim == 2 else _channel_names(key)
        planes = [data] if data.ndim == 2 else [data[..., i] for i in range(3)]
        for name, plane in zip(names, planes):
            if name in exr_channels:
                raise InputError(f"{path}: two maps both write the EXR channel {name!r}; rename one")
            # Separate contiguous planes: OpenEXR would regroup a (H, W, 3) array under its own names.
            exr_channels[name] = np.ascontiguousarray(plane, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=".exr", dir=path.parent)
    os.close(fd)
    try:
        OpenEXR.File(header, exr_channels).write(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp's file is private (0600)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_exr(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file, regrouping 3-component layers.

    Args:
        path: an .exr file.
    Returns:
        name -> (H, W) or (H, W, 3) array (float32 for float and half channels, uint32 for UINT).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: EXR file not found")
    try:
        planes = {
            name: np.asarray(channel.pixels)
            for name, channel in OpenEXR.File(str(path), separate_channels=True).channels().items()
        }
    except Exception as error:  # OpenEXR raises bare exceptions for corrupt or non-EXR files
        raise InputError(f"{path}: not a readable OpenEXR file ({error})") from error
    planes = {
        name: plane.astype(np.float32) if plane.dtype == np.float16 else plane
        for name, plane in planes.items()
    }
    result: dict[str, np.ndarray] = {}
    used: set[str] = set()
    # Layers: the default one ("R","G","B") and every "K.R/G/B" or "K.X/Y/Z" triple.
    layer_names = {name.rsplit(".", 1)[0] for name in planes if "." in name}
    candidates = [("RGB", _COMPONENTS)] + [
        (layer, tuple(f"{layer}.{c}" for c in components))
        for layer in sorted(layer_names)
        for components in (_COMPONENTS, _ALTERNATIVE_COMPONENTS)
    ]
    for key, names in candidates:
        if key in result or not all(n in planes for n in names):
            continue
        if len({planes[n].dtype for n in names}) != 1:
            continue
        result[key] = np.stack([planes[n] for n in names], axis=-1)
        used.update(names)
    for name, plane in planes.items():
        if name not in used:
            if name in result:
                raise InputError(f"{path}: channel {name!r} clashes with the layer of the same name")
            result[name] = plane
    return result
