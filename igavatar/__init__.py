"""igavatar: the library behind the `igavatar` command.

    from igavatar.body.skeleton import forward_kinematics, linear_blend_skinning

No Typer, no printing, no exit codes in here: functions return values or raise
`igavatar.errors.IgavatarError` subclasses that the CLI turns into one-line messages.
"""

__version__ = "0.1.0"
