"""Read the arrays of an SMPL model file (.pkl or .npz) without chumpy and without running its code.

    arrays = read_smpl_arrays(Path("SMPL_NEUTRAL.pkl"))   # {"v_template": ndarray, ...}
    arrays["J_regressor"]                                 # ndarray or scipy.sparse matrix

The official SMPL pickles were written by Python 2 with chumpy installed: some arrays are chumpy
`Ch` objects and `J_regressor` is a scipy sparse matrix. Pickles can run arbitrary code, so this
module unpickles with an allow-list (numpy arrays, scipy sparse matrices, plain containers) and
maps every chumpy class to a shim that keeps the pickled state: chumpy pickles a `Ch` as its
`__dict__` minus two weak-reference caches (`Ch.__getstate__`), and a plain `Ch` holds its value
in `x`. A chumpy expression node (no `x`) stays a shim and is an error only where it is used.
Anything else a pickle asks for is refused with an InputError naming the class.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from igavatar.errors import InputError

SMPL_MODEL_FLAG = "--smpl-model"
"""The CLI flag (also the IGAVATAR_SMPL_MODEL environment variable) that supplies the file."""

_HOW_TO_FIX = (
    f"pass your SMPL model file (SMPL_NEUTRAL/MALE/FEMALE .pkl or .npz from smpl.is.tue.mpg.de) "
    f"with {SMPL_MODEL_FLAG}"
)

_SPARSE_CLASSES = frozenset({"csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array"})
_BUILTINS = frozenset({"object", "set", "frozenset", "list", "dict", "tuple", "slice", "complex", "bytearray"})
# (module, name) pairs a pickle of numpy arrays needs; numpy 2 renamed numpy.core to numpy._core.
_NUMPY_GLOBALS = frozenset({
    ("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer"),
})


class ChumpyArray:
    """Stand-in for an unpickled chumpy object: keeps the pickled state, converts to an array."""

    def __setstate__(self, state: Any) -> None:
        self.state = state

    @property
    def has_value(self) -> bool:
        """Whether this is a plain `Ch` holding an array (not an expression of other Ch objects)."""
        state = getattr(self, "state", None)
        if not isinstance(state, dict) or "x" not in state:
            return False
        return state["x"].has_value if isinstance(state["x"], ChumpyArray) else True

    def to_array(self, where: str) -> np.ndarray:
        """The Ch's value as a float64 array; InputError (naming `where`) if it is an expression."""
        if not self.has_value:
            state = getattr(self, "state", None)
            keys = sorted(state) if isinstance(state, dict) else type(state).__name__
            raise InputError(
                f"{where}: a chumpy expression, not a chumpy array (its pickled state holds {keys}), which "
                "igavatar cannot evaluate; re-save the model with plain numpy arrays (e.g. smplx's tools/clean_ch.py)"
            )
        value = self.state["x"]
        if isinstance(value, ChumpyArray):
            return value.to_array(where)
        return np.asarray(value, dtype=np.float64)


class _Refused(Exception):
    """A pickle asked for a global outside the allow-list (turned into an InputError)."""


class _SmplUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals an SMPL model file legitimately contains."""

    def find_class(self, module: str, name: str) -> Any:
        root = module.split(".")[0]
        if root == "chumpy":  # chumpy.ch.Ch, or an expression node such as chumpy.ch_ops.add
            return ChumpyArray
        if root == "numpy":
            if module == "numpy" and name in ("ndarray", "dtype"):
                return getattr(np, name)
            parts = module.split(".")
            if len(parts) == 3 and parts[1] in ("core", "_core") and (parts[2], name) in _NUMPY_GLOBALS:
                # Resolve through numpy._core when it exists: importing numpy.core warns on numpy 2.
                internal = "numpy._core" if hasattr(np, "_core") else "numpy.core"
                return super().find_class(f"{internal}.{parts[2]}", name)
        if root == "scipy" and module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            return getattr(scipy.sparse, name)
        if module in ("builtins", "__builtin__") and name in _BUILTINS:
            return super().find_class("builtins", name)
        if module in ("copyreg", "copy_reg") and name == "_reconstructor":
            return super().find_class("copyreg", name)
        if module == "_codecs" and name == "encode":  # how protocol-2 pickles from Python 3 store bytes
            return super().find_class(module, name)
        if module == "collections" and name == "OrderedDict":
            return super().find_class(module, name)
        raise _Refused(
            f"holds a Python object of class {module}.{name}; an SMPL model file holds only arrays "
            "(igavatar never unpickles other classes)"
        )


def _unpickle(stream, path: Path) -> Any:
    """Unpickle one object from `stream` with the allow-list; InputError naming `path` otherwise."""
    try:
        # latin1: the official files are Python 2 pickles whose numpy buffers are byte strings.
        return _SmplUnpickler(stream, encoding="latin1").load()
    except _Refused as exc:
        raise InputError(f"{path}: {exc}; {_HOW_TO_FIX}") from None
    except Exception as exc:  # UnpicklingError, EOFError, ValueError, ...: the bytes are not a pickle
        raise InputError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc}); {_HOW_TO_FIX}") from exc


def _read_pkl(path: Path) -> dict[str, Any]:
    with path.open("rb") as stream:
        loaded = _unpickle(stream, path)
    if not isinstance(loaded, dict):
        raise InputError(
            f"{path}: holds a {type(loaded).__name__}, not the dict of arrays of an SMPL model file; {_HOW_TO_FIX}"
        )
    return {str(key): value for key, value in loaded.items()}


def _read_npz_object_member(archive: zipfile.ZipFile, key: str, path: Path) -> Any:
    """An .npy member holding pickled objects (e.g. a sparse J_regressor saved by np.savez), read
    with the allow-list unpickler instead of numpy's unrestricted pickle.load."""
    with archive.open(f"{key}.npy") as stream:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            np.lib.format.read_array_header_1_0(stream)
        else:
            np.lib.format.read_array_header_2_0(stream)
        value = _unpickle(stream, path)
    if isinstance(value, np.ndarray) and value.dtype == object and value.shape == ():
        return value.item()
    return value


def _read_npz(path: Path) -> dict[str, Any]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {}
            for key in data.files:
                try:
                    arrays[key] = data[key]
                except ValueError:  # an object array: numpy refuses it without allow_pickle
                    arrays[key] = _read_npz_object_member(data.zip, key, path)
            return arrays
    except InputError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, OSError, ...
        raise InputError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc}); {_HOW_TO_FIX}") from exc


def read_smpl_arrays(path: Path) -> dict[str, Any]:
    """The raw entries of an SMPL model file: key -> ndarray, scipy sparse matrix or other value.

    chumpy arrays come back as float64 ndarrays, chumpy expressions as ChumpyArray objects (whose
    to_array raises). Shapes are not checked here (see smpl_model).

    Raises:
        InputError: the file is missing, has another suffix, is not a pickle/npz, is not a dict,
            or asks for a class outside the allow-list.
    """
    path = Path(path)
    if path.is_dir():
        found = sorted(p.name for p in path.iterdir() if p.suffix.lower() in (".pkl", ".npz"))
        hint = f" (it holds {', '.join(found[:6])})" if found else ""
        raise InputError(f"{path}: is a directory{hint}; {SMPL_MODEL_FLAG} takes the model file itself")
    if not path.is_file():
        raise InputError(f"{path}: does not exist; {_HOW_TO_FIX}")
    suffix = path.suffix.lower()
    if suffix in (".pkl", ".pickle"):
        raw = _read_pkl(path)
    elif suffix == ".npz":
        raw = _read_npz(path)
    else:
        raise InputError(f"{path}: unknown SMPL model file type {suffix!r}, expected .pkl or .npz; {_HOW_TO_FIX}")
    return {
        key: value.to_array(f"{path}: key '{key}'") if isinstance(value, ChumpyArray) and value.has_value else value
        for key, value in raw.items()
    }
