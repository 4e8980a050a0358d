"""Read pickles of plain arrays (dataset parameter files) without running arbitrary code.

    params = load_array_pickle(Path("SMPL/mesh-f00011_smpl.pkl"))   # {'global_orient': array, ...}
    track = load_array_pickle(Path("hps/hps_track_0.npy"), torch_tensors=True)   # TRAM: a .npy of a dict
    results = load_joblib_pickle(Path("wham_output.pkl"))                        # WHAM: joblib.dump

Some datasets (X-Humans) ship per-frame parameters and meshes as pickled dicts of numpy arrays.
`pickle.load` would execute whatever a file names; this unpickler resolves only the few globals
that numpy arrays and builtin containers need and refuses everything else with an InputError,
so a tampered or foreign pickle is reported instead of run.

GPU pose estimators save their results the same way, with two twists: TRAM's `.npy` files hold a
pickled dict of torch tensors (np.save of a dict), and WHAM writes with joblib, which stores
arrays beside the pickle stream. Tensors are rebuilt through `torch.load(weights_only=True)`
(torch's own pickle would call it with weights_only=False), and joblib's unpickler is given the
same list of allowed globals.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

from igavatar.errors import InputError

# Globals a pickled dict/list of numpy arrays refers to (numpy 1.x pickles say numpy.core,
# numpy 2.x ones numpy._core; both resolve to numpy._core here).
_ALLOWED = {
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy._core.numeric", "_frombuffer"),  # protocol 5 pickles
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # numpy arrays pickled by Python 2 carry their bytes through it
}
_MODULE_ALIASES = {"numpy.core.multiarray": "numpy._core.multiarray", "numpy.core.numeric": "numpy._core.numeric"}


# Containers that estimators' result dicts use (WHAM: defaultdict(dict)).
_CONTAINERS = {("collections", "defaultdict"), ("builtins", "dict"), ("builtins", "list")}
# joblib's placeholders for the arrays it stores after the pickle stream.
_JOBLIB = {("joblib.numpy_pickle", "NumpyArrayWrapper"), ("joblib.numpy_pickle_compat", "NDArrayWrapper")}


def _storage_from_bytes(data: bytes):
    """A pickled torch storage, read as weights only: tensors, never code."""
    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


def _torch_global(module: str, name: str):
    """The torch globals a pickled tensor names, or None for any other."""
    if (module, name) == ("torch.storage", "_load_from_bytes"):
        return _storage_from_bytes
    if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
        import torch._utils

        return torch._utils._rebuild_tensor_v2
    return None


def _refused(path: Path, module: str, name: str) -> InputError:
    return InputError(
        f"{path}: the pickle refers to {module}.{name}, which igavatar does not load "
        "(it reads pickles of plain numpy arrays and tensors only); is this the tool's own file?"
    )


def _allowed_global(unpickler, module: str, name: str, path: Path, torch_tensors: bool, extra: set):
    module = _MODULE_ALIASES.get(module, module)
    if torch_tensors and (found := _torch_global(module, name)) is not None:
        return found
    if (module, name) not in _ALLOWED | extra:
        raise _refused(path, module, name)
    return super(type(unpickler), unpickler).find_class(module, name)


class _ArrayUnpickler(pickle.Unpickler):
    def __init__(self, file, path: Path, torch_tensors: bool = False) -> None:
        super().__init__(file, encoding="latin1")
        self.path, self.torch_tensors = path, torch_tensors

    def find_class(self, module: str, name: str):
        extra = _CONTAINERS if self.torch_tensors else set()
        return _allowed_global(self, module, name, self.path, self.torch_tensors, extra)


def _skip_npy_header(file, path: Path) -> None:
    """Move `file` past a .npy header of a pickled object array (np.save of a dict)."""
    import numpy.lib.format as npy_format

    version = npy_format.read_magic(file)
    header = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
    _, _, dtype = header(file)
    if dtype.hasobject is False:
        raise InputError(f"{path}: a .npy of plain {dtype} numbers, expected a saved dict (np.save of a dict)")


def load_array_pickle(path: Path, torch_tensors: bool = False) -> object:
    """The object in a pickle made only of builtin containers and numpy arrays; with
    `torch_tensors`, torch tensors too. A `.npy` file is read as np.save wrote an object (its
    pickle after the header); np.load(allow_pickle=True) would run whatever it names.

    Raises:
        InputError: the file is missing, not a pickle, truncated, or names any other class.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: missing")
    try:
        with path.open("rb") as file:
            if path.suffix.lower() == ".npy":
                _skip_npy_header(file, path)
            loaded = _ArrayUnpickler(file, path, torch_tensors).load()
    except InputError:
        raise
    except Exception as exc:  # UnpicklingError, EOFError, ValueError, ...: all mean "not readable"
        raise InputError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc
    # np.save of a dict stores a 0-d object array around it.
    if path.suffix.lower() == ".npy" and getattr(loaded, "shape", None) == ():
        loaded = loaded.item()
    return loaded


def load_joblib_pickle(path: Path) -> object:
    """What joblib.dump wrote to `path` (arrays, tensors, containers only), without running code.

    Raises:
        InputError: missing, not a joblib/pickle file, or naming any other class.
    """
    from joblib import numpy_pickle

    class _JoblibArrays(numpy_pickle.NumpyUnpickler):
        def find_class(self, module: str, name: str):
            return _allowed_global(self, module, name, path, True, _CONTAINERS | _JOBLIB)

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: missing")
    try:
        with path.open("rb") as raw, numpy_pickle._validate_fileobject_and_memmap(raw, str(path), None) as (file, _):
            if isinstance(file, str):
                raise InputError(f"{path}: written by joblib before 0.10, which igavatar does not read")
            return _JoblibArrays(str(path), file, ensure_native_byte_order=True).load()
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: not a readable joblib pickle ({type(exc).__name__}: {exc})") from exc
