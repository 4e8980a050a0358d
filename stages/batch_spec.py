"""`igavatar batch SPEC`: the spec file, checked whole and expanded into jobs before anything runs.

    spec = read_spec(Path("batch.json"), known_options)     # InputError naming the key on a bad spec
    spec.jobs[0].name, spec.jobs[0].run_dir, spec.jobs[0].options["train"]

A spec (JSON, or YAML when PyYAML is installed) names an output folder, defaults per stage, the
jobs (each a capture directory or a video), and optionally a grid of variants:

    {"out": "runs/",
     "defaults": {"preprocess": {"max_size": 64}, "train": {"preset": "tiny"}},
     "grid": {"train.seed": [0, 1, 2]},
     "jobs": [{"name": "a", "capture": "captures/a"},
              {"name": "b", "video": "clips/b.mp4", "train": {"steps": 300}}]}

Stage options are the commands' option names with underscores (`max_size` for `--max-size`;
`false` for a `--no-x` switch). A job's options override the defaults; a grid expands every job
into one job per combination, named `<job>_<option><value>` (`a_seed1`). Relative paths are
relative to the spec file's folder. Each job writes a run directory `OUT/<job>/` laid out as the
commands' `--run-dir` (capture/, dataset/, model/, mesh/, report/).
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from igavatar.errors import InputError

STAGES = ("preprocess", "train", "export", "eval")
#: Options batch sets itself for every job (paths inside its run directory, the console).
RESERVED_OPTIONS = frozenset({"run_dir", "out", "capture", "video", "dataset", "model", "json_out", "quiet"})
_TOP_KEYS = frozenset({"out", "defaults", "grid", "jobs", "stages"})
_JOB_KEYS = frozenset({"name", "capture", "video", *STAGES})
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class BatchJob:
    """One pipeline to run: its name, run directory, source and per-stage options.

    Attributes:
        source_kind: "capture" (a capture directory `preprocess` reads) or "video" (a clip).
        options: stage -> {option name (underscores): value}, defaults and grid merged in.
    """

    name: str
    run_dir: Path
    source_kind: str
    source: Path
    options: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass(frozen=True)
class BatchSpec:
    """A checked spec: where jobs write, the stages to run (None: the command line's) and the jobs."""

    out: Path
    stages: tuple[str, ...] | None
    jobs: tuple[BatchJob, ...]


def _load(path: Path) -> Any:
    if not path.is_file():
        raise InputError(f"{path}: no such spec file")
    text = path.read_text()
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise InputError(f"{path}: reading YAML needs PyYAML (pip install pyyaml), or write the spec as JSON") from None
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise InputError(f"{path}: not valid YAML: {str(error).splitlines()[0]}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise InputError(f"{path}: not valid JSON: {error.msg} at line {error.lineno}, column {error.colno}") from None


def parse_stages(text: str) -> tuple[str, ...]:
    """'preprocess,train' -> ('preprocess', 'train'), in the pipeline's order; InputError on an unknown one."""
    names = tuple(s.strip() for s in text.split(",") if s.strip())
    unknown = [s for s in names if s not in STAGES]
    if unknown or not names:
        raise InputError(f"--stages {text!r}: unknown stage {unknown[0]!r}; expected some of {', '.join(STAGES)}"
                         if unknown else f"--stages {text!r}: name at least one of {', '.join(STAGES)}")
    return tuple(s for s in STAGES if s in names)


def _check_options(where: str, stage: str, options: Any, known: dict[str, set[str]]) -> dict[str, Any]:
    if stage not in STAGES:
        raise InputError(f"{where}: unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    if not isinstance(options, dict):
        raise InputError(f"{where}.{stage}: expected an object of option: value")
    for name in options:
        if name in RESERVED_OPTIONS:
            raise InputError(f"{where}.{stage}.{name}: set by batch for every job (each job's run directory); remove it")
        if name not in known[stage]:
            raise InputError(f"{where}.{stage}.{name}: `igavatar {stage}` has no option --{name.replace('_', '-')}")
    return dict(options)


def _grid(spec: dict, known: dict[str, set[str]]) -> list[list[tuple[str, str, Any]]]:
    """Every combination of the grid as [(stage, option, value), ...] (one empty one without a grid)."""
    grid = spec.get("grid") or {}
    if not isinstance(grid, dict):
        raise InputError("grid: expected an object of \"stage.option\": [values]")
    axes = []
    for key, values in grid.items():
        stage, _, option = key.partition(".")
        _check_options("grid", stage, {option: None}, known)
        if not isinstance(values, list) or not values:
            raise InputError(f"grid.{key}: expected a non-empty list of values")
        axes.append([(stage, option, value) for value in values])
    return [list(combo) for combo in itertools.product(*axes)]


def _variant_name(name: str, combo: list[tuple[str, str, Any]]) -> str:
    parts = [name] + [f"{option}{re.sub(r'[^A-Za-z0-9.-]+', '-', str(value).lower())}" for _, option, value in combo]
    return "_".join(parts)


def _job(entry: Any, index: int, spec: dict, base: Path, out: Path, known: dict[str, set[str]]) -> BatchJob:
    where = f"jobs[{index}]"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected an object with name and capture (or video)")
    unknown = sorted(set(entry) - _JOB_KEYS)
    if unknown:
        raise InputError(f"{where}.{unknown[0]}: unknown key; a job has name, capture or video, and per-stage options "
                         f"({', '.join(STAGES)})")
    name = entry.get("name")
    if not isinstance(name, str) or not _NAME.match(name):
        raise InputError(f"{where}.name: expected a name of letters, digits, '.', '_' or '-' (it names OUT/<name>/)")
    sources = [key for key in ("capture", "video") if key in entry]
    if len(sources) != 1:
        raise InputError(f"{where} ({name}): give exactly one of capture (a capture directory) or video (a clip)")
    defaults = spec.get("defaults") or {}
    # The defaults were checked once by read_spec; a job's own options are checked here.
    options = {stage: {**defaults.get(stage, {}), **_check_options(where, stage, entry.get(stage, {}), known)}
               for stage in STAGES}
    source = Path(entry[sources[0]])
    return BatchJob(name, out / name, sources[0], source if source.is_absolute() else base / source, options)


def read_spec(path: Path, known_options: dict[str, set[str]]) -> BatchSpec:
    """Read and check a spec, expanding its grid (see the module docstring).

    Args:
        known_options: stage -> the option names (underscores) its command accepts.
    Raises:
        InputError: one line naming the file, key, stage or option that is wrong.
    """
    path = Path(path)
    spec = _load(path)
    if not isinstance(spec, dict):
        raise InputError(f"{path}: expected an object with out and jobs")
    unknown = sorted(set(spec) - _TOP_KEYS)
    if unknown:
        raise InputError(f"{path}: unknown key {unknown[0]!r}; a spec has {', '.join(sorted(_TOP_KEYS))}")
    if not isinstance(spec.get("out"), str) or not isinstance(spec.get("jobs"), list) or not spec["jobs"]:
        raise InputError(f"{path}: needs \"out\" (a folder) and \"jobs\" (a non-empty list)")
    for stage in (spec.get("defaults") or {}):
        _check_options("defaults", stage, spec["defaults"][stage], known_options)
    base = path.resolve().parent
    out = Path(spec["out"]) if Path(spec["out"]).is_absolute() else base / spec["out"]
    raw = spec.get("stages")
    stages = parse_stages(raw if isinstance(raw, str) else ",".join(map(str, raw))) if raw else None
    combos = _grid(spec, known_options)
    jobs: list[BatchJob] = []
    for index, entry in enumerate(spec["jobs"]):
        job = _job(entry, index, spec, base, out, known_options)
        for combo in combos:
            options = {stage: dict(values) for stage, values in job.options.items()}
            for stage, option, value in combo:
                options[stage][option] = value
            name = _variant_name(job.name, combo)
            jobs.append(BatchJob(name, out / name, job.source_kind, job.source, options))
    names = [job.name for job in jobs]
    duplicate = next((n for n in names if names.count(n) > 1), None)
    if duplicate:
        raise InputError(f"{path}: two jobs are named {duplicate!r}; job names must differ (they name OUT/<name>/)")
    return BatchSpec(out, stages, tuple(jobs))
