"""From a batch spec to each job's command lines, checked by the commands' own option parsers.

    known = known_options(group)                    # stage -> option names (underscores)
    spec = read_spec(path, known)
    plans = job_plans(group, spec, stages, threads=1)   # InputError naming the job/stage/option

Spec options become the flags a user would type (`max_size: 64` -> `--max-size 64`, `nonrigid:
false` -> `--no-nonrigid`), and each command line is parsed by that command's click parser before
anything runs, so a bad value is one line naming the job, the stage and the option, with the same
checks (types, ranges) as on the command line.
"""

from __future__ import annotations

from typing import Any

# The commands are Typer's click objects (Typer 0.29+ carries its own copy of click): they are read
# by their attributes (param_type_name, opts, is_flag) rather than by click's classes.


from igavatar.errors import InputError
from stages.batch_job import JobPlan
from stages.batch_spec import RESERVED_OPTIONS, STAGES, BatchJob, BatchSpec


def _command(group: Any, stage: str) -> Any:
    return group.commands[stage]


def known_options(group: Any) -> dict[str, set[str]]:
    """Each stage's option names (underscores), without the ones batch sets itself."""
    return {stage: {p.name for p in _command(group, stage).params if p.name not in RESERVED_OPTIONS and
                    p.param_type_name == "option"} for stage in STAGES}


def _flag_args(parameter: Any, value: Any) -> list[str]:
    long = [o for o in parameter.opts if o.startswith("--")] or parameter.opts
    if parameter.is_flag:
        if value is True:
            return [long[0]]
        if parameter.secondary_opts:
            return [parameter.secondary_opts[0]]
        return []
    if isinstance(value, (list, tuple)):
        value = ",".join(str(v) for v in value)
    return [long[0], str(value)]


def stage_args(group: Any, job: BatchJob, stage: str) -> list[str]:
    """The job's command line for `stage` (without `igavatar`), its paths inside OUT/<job>/."""
    args = [stage, "--run-dir", str(job.run_dir)]
    if stage == "preprocess":
        args += ["--capture", str(job.source)] if job.source_kind == "capture" else ["--video", str(job.source)]
    parameters = {p.name: p for p in _command(group, stage).params}
    for name, value in job.options.get(stage, {}).items():
        args += _flag_args(parameters[name], value)
    return args


def _check_args(group: Any, job: BatchJob, args: list[str]) -> None:
    stage = args[0]
    try:
        _command(group, stage).make_context(stage, list(args[1:]), resilient_parsing=False)
    except Exception as error:  # click's UsageError / BadParameter (Typer's copy or click's)
        if not hasattr(error, "format_message"):
            raise
        raise InputError(f"job {job.name}: {stage}: {error.format_message()}") from None


def job_plans(group: Any, spec: BatchSpec, stages: tuple[str, ...], threads: int) -> list[JobPlan]:
    """Every job's plan (command lines of `stages`, in order), each command line checked."""
    plans = []
    for job in spec.jobs:
        commands = []
        for stage in stages:
            args = stage_args(group, job, stage)
            _check_args(group, job, args)
            commands.append((stage, args))
        plans.append(JobPlan(job.name, job.run_dir, commands, threads))
    return plans
