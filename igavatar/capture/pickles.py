"""Read pickles of plain arrays (dataset parameter files) without running arbitrary code.

    params = load_array_pickle(Path("SMPL/mesh-f00011_smpl.pkl"))   # {'global_orient': array, ...}

Some datasets (X-Humans) ship per-frame parameters and meshes as pickled dicts of numpy arrays.
`pickle.load` would execute whatever a file names; this unpickler resolves only the few globals
that numpy arrays and builtin containers need and refuses everything else with an InputError,
so a tampered or foreign pickle is reported instead of run.
"""

from __future__ import annotations

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


class _ArrayUnpickler(pickle.Unpickler):
    def __init__(self, file, path: Path) -> None:
        super().__init__(file, encoding="latin1")
        self.path = path

    def find_class(self, module: str, name: str):
        module = _MODULE_ALIASES.get(module, module)
        if (module, name) not in _ALLOWED:
            raise InputError(
                f"{self.path}: the pickle refers to {module}.{name}, which igavatar does not load "
                "(it reads pickles of plain numpy arrays only); is this the dataset's own file?"
            )
        return super().find_class(module, name)


def load_array_pickle(path: Path) -> object:
    """The object in a pickle made only of builtin containers and numpy arrays.

    Raises:
        InputError: the file is missing, not a pickle, truncated, or names any other class.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: missing")
    try:
        with path.open("rb") as file:
            return _ArrayUnpickler(file, path).load()
    except InputError:
        raise
    except Exception as exc:  # UnpicklingError, EOFError, ValueError, ...: all mean "not readable"
        raise InputError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc
