"""The pure hand model: pad geometry, kinematics, friction cone, tactile contact estimation.

Numbers in, numbers out: no I/O, no clocks, no globals. Millimetres and radians throughout.
"""

from sdh2svc.model.calibration import DistanceMap
from sdh2svc.model.contact import (
    NO_CONTACT,
    Blob,
    ContactEstimate,
    MatrixLayout,
    TactileCalibration,
    estimate_contact,
)
from sdh2svc.model.depth import ContactDepth, ContactDepthModel, PadCompliance, contact_depth
from sdh2svc.model.friction import cone_margin, inside_cone, omega, pad_tangent
from sdh2svc.model.geometry import (
    L_from_x3,
    PadProfile,
    pad_point_from_L,
    pad_slope,
    pad_y3,
    virtual_joint,
    x3_from_L,
)
from sdh2svc.model.kinematics import (
    Finger,
    FingerLimits,
    HandGeometry,
    HandPoints,
    HandPose,
    IKFailure,
    IKResult,
    IKSolution,
    Point,
    contact_point,
    distal_joint,
    finger_ik,
    frame3_axes,
    hand_points,
    ik_branches,
    pad_point,
    segment,
    wrap_angle,
)

__all__ = [
    "NO_CONTACT", "Blob", "ContactDepth", "ContactDepthModel", "ContactEstimate", "DistanceMap",
    "Finger", "FingerLimits", "HandGeometry", "HandPoints", "HandPose", "IKFailure", "IKResult",
    "IKSolution", "L_from_x3", "MatrixLayout", "PadCompliance", "PadProfile", "Point",
    "TactileCalibration", "cone_margin", "contact_depth", "contact_point", "distal_joint",
    "estimate_contact", "finger_ik", "frame3_axes", "hand_points", "ik_branches", "inside_cone",
    "omega", "pad_point", "pad_point_from_L", "pad_slope", "pad_tangent", "pad_y3", "segment",
    "virtual_joint", "wrap_angle", "x3_from_L",
]  # fmt: skip
