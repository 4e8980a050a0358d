"""JSON Schemas of igavatar's artifacts and inputs, shipped as package data.

    from schemas import load_schema
    schema = load_schema("manifest")   # dict parsed from manifest.schema.json
"""

import json
from functools import lru_cache
from importlib import resources


@lru_cache(maxsize=None)
def load_schema(name: str) -> dict:
    """Return the parsed JSON Schema `<name>.schema.json`; KeyError if there is none."""
    path = resources.files(__name__) / f"{name}.schema.json"
    if not path.is_file():
        raise KeyError(f"no schema named {name!r}")
    return json.loads(path.read_text(encoding="utf-8"))


def schema_names() -> list[str]:
    """Names of every schema shipped (file names without `.schema.json`)."""
    return sorted(
        p.name[: -len(".schema.json")]
        for p in resources.files(__name__).iterdir()
        if p.name.endswith(".schema.json")
    )
