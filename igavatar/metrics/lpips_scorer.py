"""LPIPS from weights already on this machine, or an honest "not computed".

    score, status = lpips_scorer(torch.device("cpu"))
    if score is not None: value = score(pred_rgb, gt_rgb)
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

#: torchvision's AlexNet checkpoint that the `lpips` package loads (never downloaded here).
LPIPS_BACKBONE_FILE = "alexnet-owt-7be5be79.pth"


def lpips_scorer(device: torch.device) -> tuple[Callable[[np.ndarray, np.ndarray], float] | None, str]:
    """An LPIPS (AlexNet, v0.1) scorer built only from weights already on this machine.

    Returns:
        (score(pred, gt) -> float on (H, W, 3) [0, 1] RGB, status) or (None, why not). LPIPS needs
        the `lpips` package and torchvision's AlexNet checkpoint in the torch hub cache; nothing is
        downloaded, and without them the report says "not computed" (never a made-up value).
    """
    if importlib.util.find_spec("lpips") is None or importlib.util.find_spec("torchvision") is None:
        return None, ("not computed: the `lpips` and `torchvision` packages are not installed "
                      "(weights cannot be downloaded here)")
    backbone = Path(torch.hub.get_dir()) / "checkpoints" / LPIPS_BACKBONE_FILE
    if not backbone.is_file():
        return None, f"not computed: the AlexNet weights are not present locally ({backbone})"
    import lpips  # noqa: PLC0415 - optional dependency, imported only when its weights exist

    try:
        net = lpips.LPIPS(net="alex", version="0.1", verbose=False).to(device).eval()
    except (OSError, RuntimeError) as exc:
        return None, f"not computed: LPIPS could not load its local weights ({exc})"

    @torch.no_grad()
    def score(pred: np.ndarray, gt: np.ndarray) -> float:
        def to_tensor(rgb: np.ndarray) -> torch.Tensor:  # (H, W, 3) [0, 1] -> (1, 3, H, W) [-1, 1]
            return torch.from_numpy(np.ascontiguousarray(rgb, np.float32)).permute(2, 0, 1)[None].to(device) * 2 - 1

        return float(net(to_tensor(pred), to_tensor(gt)).item())

    return score, "computed: LPIPS AlexNet v0.1 (lpips package, local weights), inputs scaled to [-1, 1]"
