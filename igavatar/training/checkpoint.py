"""Training state <-> flat dicts of numpy arrays, saved as .npz (no pickle).

    save_state(path, {"avatar": avatar.state_dict(), "optimizer": opt.state_dict(), "step": 10})
    state = load_state(path)        # the same nesting, tensors back as torch tensors

Keys are joined with '/'; ints, floats and strings are stored as 0-d arrays and come back as
Python scalars, so an optimizer's state_dict survives the round trip exactly. Empty dicts and
lists are recorded too: an optimizer that has not stepped yet has an empty "state", which
load_state_dict requires.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import torch

from igavatar.artifacts.atomic import atomic_write_bytes

_TENSOR = "t:"
_SCALAR = "s:"
_LIST = "l:"
_EMPTY_DICT = "d:"


def flatten(value: Any, prefix: str = "") -> dict[str, np.ndarray]:
    """Nested dicts/lists of tensors and scalars -> {'a/b/c': array} with type-tagged keys."""
    flat: dict[str, np.ndarray] = {}
    if isinstance(value, dict):
        if not value and prefix:
            flat[f"{_EMPTY_DICT}{prefix[:-1]}"] = np.array(0)
        for key, item in value.items():
            flat.update(flatten(item, f"{prefix}{key}/"))
    elif isinstance(value, (list, tuple)):
        flat[f"{_LIST}{prefix}len"] = np.array(len(value))
        for index, item in enumerate(value):
            flat.update(flatten(item, f"{prefix}{index}/"))
    elif isinstance(value, torch.Tensor):
        tensor = value.detach().cpu()
        flat[f"{_TENSOR}{prefix[:-1]}"] = tensor.numpy() if tensor.dtype != torch.bfloat16 else tensor.float().numpy()
    elif isinstance(value, (bool, int, float, str, np.integer, np.floating)) or value is None:
        flat[f"{_SCALAR}{prefix[:-1]}"] = np.array("__none__" if value is None else value)
    else:
        raise TypeError(f"cannot store {type(value).__name__} at {prefix!r} in a checkpoint")
    return flat


def _insert(tree: dict, path: list[str], value: Any) -> None:
    for part in path[:-1]:
        tree = tree.setdefault(part, {})
    tree[path[-1]] = value


def _ensure_node(tree: dict, path: list[str]) -> None:
    """An (empty) dict at `path` unless something is there: where an empty dict or list goes."""
    for part in path:
        tree = tree.setdefault(part, {})


def _listify(tree: Any, lists: set[str], prefix: str = "") -> Any:
    if not isinstance(tree, dict):
        return tree
    converted = {k: _listify(v, lists, f"{prefix}{k}/") for k, v in tree.items()}
    if prefix in lists:
        return [converted[str(i)] for i in range(len(converted))]
    return converted


def unflatten(flat: dict[str, np.ndarray]) -> dict:
    """Inverse of `flatten` (tensors come back as torch tensors)."""
    tree: dict = {}
    lists: set[str] = set()
    for key, array in flat.items():
        if key.startswith(_LIST):
            lists.add(key[len(_LIST):-len("len")])
            if key != f"{_LIST}len":
                _ensure_node(tree, key[len(_LIST):-len("/len")].split("/"))
        elif key.startswith(_EMPTY_DICT):
            _ensure_node(tree, key[len(_EMPTY_DICT):].split("/"))
        elif key.startswith(_TENSOR):
            _insert(tree, key[len(_TENSOR):].split("/"), torch.from_numpy(np.array(array)))
        elif key.startswith(_SCALAR):
            scalar = array.item()
            _insert(tree, key[len(_SCALAR):].split("/"), None if scalar == "__none__" else scalar)
    return _restore_int_keys(_listify(tree, lists))


def _restore_int_keys(tree: Any) -> Any:
    """Optimizer state is keyed by int parameter ids; npz keys are strings."""
    if isinstance(tree, list):
        return [_restore_int_keys(item) for item in tree]
    if not isinstance(tree, dict):
        return tree
    out = {}
    for key, value in tree.items():
        out_key = int(key) if isinstance(key, str) and key.isdigit() else key
        out[out_key] = _restore_int_keys(value)
    return out


def save_state(path: Path, state: dict) -> None:
    """Write `state` atomically as an uncompressed .npz."""
    buffer = io.BytesIO()
    np.savez(buffer, **flatten(state))
    atomic_write_bytes(Path(path), buffer.getvalue())


def load_state(path: Path) -> dict:
    """Read a state written by save_state."""
    with np.load(path, allow_pickle=False) as data:
        return unflatten({key: data[key] for key in data.files})
