"""Group a command's options into rich help panels, listed in one place per command.

    @app.command()
    @user_errors
    @help_panels({INPUTS: ("dataset", "out"), QUALITY: ("preset", "steps")})
    def train(dataset: ..., out: ..., preset: ..., steps: ...): ...

`--help` then shows "Inputs and outputs" first, with what most users set, and the research knobs
last under "Advanced". Every option must be named in exactly one panel (tested), so a new option
cannot land in an unnamed "Options" box.
"""

from __future__ import annotations

import typing
from collections.abc import Callable, Mapping, Sequence

from typer.models import ParameterInfo

INPUTS = "Inputs and outputs"
QUALITY = "Quality and time"
ADVANCED = "Advanced"
CONSOLE = "Console"


def help_panels(panels: Mapping[str, Sequence[str]]) -> Callable[[Callable], Callable]:
    """Put each named parameter of the decorated command into its panel (rich_help_panel).

    Typer evaluates string annotations (this package uses `from __future__ import annotations`)
    anew whenever it builds the command, so the evaluated ones, with their panels set, replace
    them on the function. Options shared by several commands (--run-dir, --quiet) get copies.
    """
    def apply(func: Callable) -> Callable:
        hints = typing.get_type_hints(func, include_extras=True)
        named = [name for names in panels.values() for name in names]
        unknown = sorted(set(named) - set(hints))
        if unknown:
            raise TypeError(f"{func.__name__}: help_panels names no such parameter: {unknown}")
        for panel, names in panels.items():
            for name in names:
                hints[name] = _with_panel(hints[name], panel)
        func.__annotations__ = hints
        return func

    return apply


def _with_panel(annotation, panel: str):
    """Annotated[T, typer.Option(...)] with a copy of the option info that carries `panel`."""
    base, *metadata = typing.get_args(annotation)
    copied = []
    for item in metadata:
        if isinstance(item, ParameterInfo):
            item = _copy_info(item)
            item.rich_help_panel = panel
        copied.append(item)
    return typing.Annotated[(base, *copied)]


def _copy_info(info: ParameterInfo) -> ParameterInfo:
    clone = object.__new__(type(info))
    clone.__dict__.update(info.__dict__)
    return clone
