"""A bare skeleton's body: Anny fitted to its joints becomes the subject's template.

    subject = fitted_subject(skeleton_subject(capture), anny_cache, on_status)

A capture that gives only a skeleton (capture v1 'skeleton' poses, HumanNeRF / ZJU-MoCap's SMPL
joints) has no template: its shape prior is then the masks' visual hull, which keeps webs where
every training frame closes the body (under the arms, between the thighs) and skinning weights
from bone distances, which hand the side of a heavy torso to the arm. Where the skeleton is of a
kind igavatar can name (Anny's bones, SMPL's tree), Anny fitted to it (igavatar.body.anny_fit)
gives both a body and its weights, and from there the capture is treated like a body-model
capture (the template, or the hull over loose clothing, with the template's weights). A skeleton
of unknown kind, or a lone root (a static subject), keeps the masks-only path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from igavatar.body.anny_body import load_anny
from igavatar.body.anny_fit import fit_anny_to_skeleton
from igavatar.capture.posed_subject import PosedSubject

#: --body-fit choices: Anny fitted to a bare skeleton of a known kind, or no body (masks only).
BODY_FITS: tuple[str, ...] = ("anny", "none")
#: Bump when the fit changes (datasets made with another version are redone).
BODY_FIT_VERSION = 1
#: Skeleton kinds the fit knows how to name (igavatar.body.bones.skeleton_kind).
FITTABLE_KINDS: tuple[str, ...] = ("anny", "smpl")
#: A fit whose joints lie further than this (RMS, meters, before rebinding) from the skeleton's is
#: not used: no human body has those bones (a skeleton in centimetres, a non-human rig with human
#: names). Anny's own joints fit to under a millimetre, SMPL-convention adult skeletons to 4-6 cm.
MAX_JOINT_RMS_M = 0.15


def fits_body(subject: PosedSubject) -> bool:
    """Whether `fitted_subject` gives this subject a body: a bare skeleton of a kind Anny can be fitted to."""
    return subject.template_vertices_rest is None and subject.description.get("skeleton_kind") in FITTABLE_KINDS


def fitted_subject(
    subject: PosedSubject, anny_cache: Path | None = None, on_status: Callable[[str], None] | None = None
) -> PosedSubject:
    """`subject` with Anny fitted to its skeleton as the template (unchanged unless `fits_body`).

    The template lies in the skeleton's rest pose with weights over its joints, as a body model's
    would; the subject's description gains "body_fit" (the phenotype and the joint residual). A fit
    that no human body gives (joint RMS over MAX_JOINT_RMS_M) is not used: the subject keeps no
    template, its description says why and `on_status` is told.
    Raises BodyModelError when Anny cannot be loaded.
    """
    if not fits_body(subject):
        return subject
    kind = subject.description["skeleton_kind"]
    fit = fit_anny_to_skeleton(load_anny(anny_cache, on_status), subject.skeleton, kind)
    if fit.joint_rms_m > MAX_JOINT_RMS_M:
        why = (f"Anny fitted to the {kind} skeleton leaves its joints {1000 * fit.joint_rms_m:.0f} mm (RMS) from the "
               f"skeleton's (more than {1000 * MAX_JOINT_RMS_M:.0f}): are the rest joints in meters? The body is not "
               "used; the shape prior comes from the masks")
        if on_status is not None:
            on_status(why)
        return replace(subject, description={**subject.description, "body_fit": {"model": "anny", "rejected": why}})
    return replace(
        subject,
        template_vertices_rest=fit.vertices,
        template_faces=fit.faces,
        template_weights=fit.weights,
        description={**subject.description, "body_fit": fit.description()},
    )
