"""An adult SMPL-tree skeleton for tests (approximate neutral T-pose rest joints, +Y up, face +Z).

    skeleton = smpl_like_skeleton()       # Skeleton with SMPL_PARENTS and SMPL_JOINT_NAMES

The numbers are rounded from a typical neutral SMPL body (meters); no SMPL file is involved.
"""

from __future__ import annotations

import numpy as np

from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton

SMPL_LIKE_REST_JOINTS = np.array([
    [0.000, -0.223, 0.028],   # pelvis
    [0.070, -0.314, 0.015],   # left_hip
    [-0.068, -0.314, 0.020],  # right_hip
    [-0.004, -0.114, -0.002],  # spine1
    [0.102, -0.690, 0.017],   # left_knee
    [-0.106, -0.696, 0.015],  # right_knee
    [0.001, 0.021, 0.003],    # spine2
    [0.088, -1.088, -0.027],  # left_ankle
    [-0.092, -1.095, -0.027],  # right_ankle
    [0.003, 0.074, 0.028],    # spine3
    [0.115, -1.144, 0.092],   # left_foot
    [-0.118, -1.143, 0.096],  # right_foot
    [0.000, 0.288, -0.015],   # neck
    [0.078, 0.198, -0.006],   # left_collar
    [-0.075, 0.196, -0.010],  # right_collar
    [0.005, 0.354, 0.045],    # head
    [0.172, 0.226, -0.015],   # left_shoulder
    [-0.173, 0.225, -0.015],  # right_shoulder
    [0.432, 0.213, -0.043],   # left_elbow
    [-0.427, 0.211, -0.040],  # right_elbow
    [0.685, 0.222, -0.036],   # left_wrist
    [-0.689, 0.222, -0.036],  # right_wrist
    [0.769, 0.214, -0.051],   # left_hand
    [-0.773, 0.214, -0.051],  # right_hand
])


def smpl_like_skeleton(scale: float = 1.0) -> Skeleton:
    """SMPL's tree and names with SMPL_LIKE_REST_JOINTS (times `scale`) as rest joints."""
    return Skeleton(np.array(SMPL_PARENTS), SMPL_LIKE_REST_JOINTS * scale, SMPL_JOINT_NAMES)
