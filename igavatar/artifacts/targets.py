"""The one rule for output paths: replace only an igavatar artifact of the same kind, never an input.

    check_output_target(Path("run/mesh"), "mesh", inputs=[Path("run/model")])   # UnsafeOutputError if not

An output path may be replaced when it does not exist, is an empty directory, or is a directory
whose `manifest.json` validates as an artifact of the kind being written and which holds no file
that manifest does not list. Anything else (a file, files added to an artifact,
a folder of the user's, an artifact of another kind, one of the command's inputs, a folder that
contains an input or lies inside one) is refused with one line saying what is there and how to
proceed. There is no option that deletes a non-artifact: the user deletes it, or picks another path.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from igavatar.artifacts.manifest import PRODUCED_BY, read_manifest, unlisted_files
from igavatar.errors import ArtifactError, UnsafeOutputError


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_output_target(target: Path, kind: str, inputs: Iterable[Path] = ()) -> None:
    """Raise UnsafeOutputError unless writing a `kind` artifact at `target` destroys nothing but an earlier one.

    Args:
        target: the artifact directory about to be (re)written.
        kind: the artifact kind the stage writes (a key of PRODUCED_BY).
        inputs: every path the command reads (artifacts, pose files, ground-truth folders).
    """
    target = Path(target)
    resolved = target.resolve()
    for item in inputs:
        if item is None:
            continue
        source = Path(item).resolve()
        if resolved == source:
            relation = "is"
        elif _within(source, resolved):
            relation = "contains"
        elif _within(resolved, source):
            relation = "lies inside"
        else:
            continue
        raise UnsafeOutputError(
            f"--out {target}: {relation} the input {item}; writing the {kind} there would destroy it. "
            f"Give another --out (outside every input)"
        )
    if not target.exists() and not target.is_symlink():
        return
    how = f"give another --out, or delete {target} yourself if you no longer need it"
    if target.is_symlink():
        # Replacing would swap the link for a folder and leave its target behind, unreported.
        raise UnsafeOutputError(
            f"--out {target}: is a symbolic link (to {target.resolve()}); igavatar writes artifacts as real "
            f"folders and does not replace links: give the link's target as --out, or another --out"
        )
    if not target.is_dir():
        raise UnsafeOutputError(f"--out {target}: is an existing file, not an igavatar {kind} artifact; {how}")
    if not any(target.iterdir()):
        return
    try:
        manifest = read_manifest(target)
    except ArtifactError:
        raise UnsafeOutputError(
            f"--out {target}: is a non-empty folder that is not an igavatar artifact (no valid manifest.json); "
            f"refusing to replace it: {how}"
        ) from None
    if manifest["artifact"] != kind:
        raise UnsafeOutputError(
            f"--out {target}: holds a {manifest['artifact']} artifact (made by `{PRODUCED_BY[manifest['artifact']]}`), "
            f"not a {kind}; {how}"
        )
    extra = unlisted_files(target, manifest)
    if extra:
        shown = ", ".join(extra[:3]) + (f" and {len(extra) - 3} more" if len(extra) > 3 else "")
        raise UnsafeOutputError(
            f"--out {target}: the {kind} artifact there also holds files it did not write ({shown}); replacing it "
            f"would delete them: move them out of {target}, or give another --out"
        )
