"""Axis-aligned boxes given as (box_min (3,), box_max (3,)): the one check every grid uses."""

from __future__ import annotations

import torch

from igavatar.errors import InputError


def check_box(box_min: torch.Tensor, box_max: torch.Tensor, where: str, error: type[Exception] = InputError) -> None:
    """Raise `error` naming `where` unless both corners have shape (3,) and box_max > box_min on every axis."""
    if tuple(box_min.shape) != (3,) or tuple(box_max.shape) != (3,):
        raise error(
            f"{where}: box_min and box_max must have shape (3,), got {tuple(box_min.shape)} and {tuple(box_max.shape)}"
        )
    if not bool((box_max > box_min).all()):
        raise error(f"{where}: box_max {box_max.tolist()} must exceed box_min {box_min.tolist()} on every axis")
