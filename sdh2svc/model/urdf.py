"""A URDF of the SDH2, generated from the configuration's geometry (hand-model §1–§3).

Three identical fingers stand on an equilateral triangle whose side is the base offset (66 mm):
the thumb on its own, fingers 1 and 2 turned about their vertical axes by the coupling joint φ1
(0°: both face the thumb, 90°: they face each other in the plane of work). Each finger has a
proximal and a distal revolute joint (φ2, φ3 / φ4, φ5 / the thumb's two) whose positive angles
close the finger, with the configured limits and the SDH2's velocity limits
(:data:`~sdh2svc.model.hand.HAND_VELOCITY_LIMIT_DEG_S`); the pads are drawn (the distal one
along its flat-and-arc profile). Every visual is a collision body too, of the same shape and
place, so that a simulator or a planner sees the hand's volume. The joints' ``effort`` is a
placeholder (:data:`EFFORT_PLACEHOLDER`), and the links carry no ``<inertial>``: no source gives
the SDH2's joint torques or its links' masses.

Frames (URDF's units: metres, radians):

* ``palm``: at the palm's base below the finger bases' circle, z along the straightened fingers,
  x from the thumb towards the coupled fingers, y from Finger 2 towards Finger 1 (SCHUNK's own
  palm frame: knuckles at (19.05, ±33) mm, the thumb at (−38.11, 0) mm).
* ``frame0``: the model's frame 0 (at Finger 1's proximal joint O, y0 towards Finger 2, z0 along
  the straightened finger, x0 towards the thumb); its y and z are the model's (y, z) in mm / 1000.
* ``<finger>_frame3``: frame 3 at the distal joint (x along the distal link, y towards the pad),
  so a pad point (x3, y3) sits at (x3, y3, 0) there.
* ``<finger>_<proximal|distal>_pad``: a tactile matrix's plane, origin at the corner of cell
  (row 0, column 0), x across the finger (columns), y along it (rows), z out of the pad.

Only the coupled fingers' kinematics is in the thesis; the rest (the proximal pad's place, the
palm's and links' bulk) is display geometry, marked so below.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final, Literal

from sdh2svc.model.geometry import pad_slope, pad_y3, x3_from_L
from sdh2svc.model.hand import HAND_VELOCITY_LIMIT_DEG_S, AxisMap, JointLimits, TactileConfig
from sdh2svc.model.kinematics import HandGeometry

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # x, y, z, w

FINGERS = ("finger1", "finger2", "thumb")
PADS = ("proximal", "distal")
_MM = 1e-3
_CLOSE = (-1.0, 0.0, 0.0)  # every finger joint's axis: positive angles close towards +y
_UP, _DOWN = (0.0, 0.0, 1.0), (0.0, 0.0, -1.0)
_PAD_FRAME_RPY = (-math.pi / 2, 0.0, 0.0)  # link (x, y, z) → pad (x, −z, y)
_ARC_SEGMENTS = 8  # boxes approximating the distal pad's arc
# A joint's <limit effort=…> (URDF: N·m), which URDF requires: a placeholder, not the SDH2's
# torque, which no source the project has gives (SCHUNK's own sdh.urdf.xacro, ipa320/
# schunk_modular_robotics, says effort 100 with placeholder inertials, mass 0.1 kg, inertia
# 0.01). No <inertial> is written: nothing gives the links' masses either.
EFFORT_PLACEHOLDER = 10.0
# display only: the model has no such dimensions (SCHUNK's URDF's: the palm's base to the
# knuckles, the knuckle to the proximal joint)
PALM_HEIGHT_MM = 74.5
KNUCKLE_MM = 16.5
_LINK_WIDTH_MM = 22.0
_PROXIMAL_BODY_Y_MM = (-12.0, 12.0)
_DISTAL_BODY_Y_MM = (-12.0, 3.0)  # behind the distal pad, whose back is the plane y3 = 3 mm
_DISTAL_BODY_BEHIND_MM, _DISTAL_BODY_SHORT_MM = 8.0, 6.0  # from the joint, of the link's length
_PAD_BACK_Y3_MM = 3.0
PROXIMAL_PAD_Y_MM = 14.0  # the proximal pad's surface…
PROXIMAL_ROW0_FROM_DISTAL_MM = 15.0  # …and its row 0's centre below the distal joint


@dataclass(frozen=True, slots=True)
class Joint:
    """One URDF joint; angles in radians, lengths in metres."""

    name: str
    parent: str
    child: str
    xyz: Vec3
    rpy: Vec3 = (0.0, 0.0, 0.0)
    kind: Literal["revolute", "fixed"] = "fixed"
    axis: Vec3 = (0.0, 0.0, 1.0)
    lower: float = 0.0
    upper: float = 0.0
    mimic: str | None = None  # moves with this joint (the coupling φ1's second finger)
    velocity: float = 0.0  # rad/s: the axis's velocity limit (a revolute joint's)


#: The visuals' colours (r, g, b, a): the URDF's materials, and the links drawn in Foxglove.
MATERIALS: Final[dict[str, tuple[float, float, float, float]]] = {
    "shell": (0.55, 0.57, 0.6, 1.0),
    "pad": (0.15, 0.15, 0.15, 1.0),
}


@dataclass(frozen=True, slots=True)
class Visual:
    """A box (size x, y, z) or a cylinder (radius, length, 0) on a link, metres."""

    link: str
    shape: Literal["box", "cylinder"]
    size: Vec3
    xyz: Vec3
    rpy: Vec3 = (0.0, 0.0, 0.0)
    material: Literal["shell", "pad"] = "shell"


@dataclass(frozen=True, slots=True)
class HandDescription:
    """The hand as links, joints and visuals (what the URDF says, as values)."""

    links: tuple[str, ...]
    joints: tuple[Joint, ...]
    visuals: tuple[Visual, ...]

    @property
    def actuated(self) -> tuple[str, ...]:
        """Names of the joints an angle drives (the revolute ones without a mimic)."""
        return tuple(j.name for j in self.joints if j.kind == "revolute" and j.mimic is None)


def _revolute(
    name: str,
    parent: str,
    child: str,
    xyz: Vec3,
    axis: Vec3,
    limits: tuple[float, float],
    *,
    velocity: float,
    yaw: float = 0.0,
    mimic: str | None = None,
) -> Joint:
    rpy = (0.0, 0.0, yaw)
    return Joint(name, parent, child, xyz, rpy, "revolute", axis, *limits, mimic, velocity)


def joint_names(axes: AxisMap) -> dict[int, str]:
    """Wire axis → the URDF joint it drives (the configuration's names for the axes)."""
    return {
        axes.phi1: "phi1",
        axes.phi2: "phi2",
        axes.phi3: "phi3",
        axes.phi4: "phi4",
        axes.phi5: "phi5",
        axes.thumb_proximal: "thumb_proximal",
        axes.thumb_distal: "thumb_distal",
    }


# The thumb's joints are named as its links and as AxisMap's fields (thumb_proximal,
# thumb_distal): service/foxglove_mcap.py's JOINTS names both the AxisMap fields it reads and
# the URDF joints it poses, so a rename here must change it too (else /tf parks the thumb at 0).
def _finger_joint_names(finger: str) -> tuple[str, str]:
    return {"finger1": ("phi2", "phi3"), "finger2": ("phi4", "phi5")}.get(
        finger, ("thumb_proximal", "thumb_distal")
    )


def pad_matrix(axes: AxisMap, finger: str, pad: str) -> int:
    """The DSACON32m matrix index of a finger's pad (``finger1``…, ``proximal``|``distal``)."""
    index: int = getattr(axes, f"{finger}_{pad}_matrix")
    return index


def describe(
    geom: HandGeometry, axes: AxisMap, limits: JointLimits, tactile: TactileConfig
) -> HandDescription:
    """The SDH2 as links, joints and visuals, from the configuration's sections."""
    side = geom.base_offset_mm * _MM
    r = side / math.sqrt(3.0)  # the finger bases' circle
    h = PALM_HEIGHT_MM * _MM
    base = {"finger1": (r / 2, side / 2, h), "finger2": (r / 2, -side / 2, h)}
    base["thumb"] = (-r, 0.0, h)
    lim = {
        name: (math.radians(limits.min_deg[ax]), math.radians(limits.max_deg[ax]))
        for ax, name in joint_names(axes).items()
    }
    speed = {  # the hand's own limit of each wire axis, deg/s → rad/s
        name: math.radians(HAND_VELOCITY_LIMIT_DEG_S[ax]) for ax, name in joint_names(axes).items()
    }
    o = (base["finger1"][0], base["finger1"][1], h + KNUCKLE_MM * _MM)
    joints = [Joint("frame0", "palm", "frame0", o, (0.0, 0.0, math.pi))]
    # the coupling: Finger 1 turns by +φ1, Finger 2 by −φ1, from facing the thumb (yaw π/2)
    turn = lim["phi1"]
    joints += [
        _revolute(
            "phi1",
            "palm",
            "finger1_knuckle",
            base["finger1"],
            _UP,
            turn,
            velocity=speed["phi1"],
            yaw=math.pi / 2,
        ),
        _revolute(
            "phi1_finger2",
            "palm",
            "finger2_knuckle",
            base["finger2"],
            _DOWN,
            turn,
            velocity=speed["phi1"],
            yaw=math.pi / 2,
            mimic="phi1",
        ),
        # the thumb stands still, facing the coupled fingers
        Joint("thumb_base", "palm", "thumb_knuckle", base["thumb"], (0.0, 0.0, -math.pi / 2)),
    ]
    links = ["palm", "frame0"]
    visuals = [_palm(r)]
    for finger in FINGERS:
        f_links, f_joints, f_visuals = _finger(finger, geom, tactile, lim, speed)
        links += f_links
        joints += f_joints
        visuals += f_visuals
    return HandDescription(tuple(links), tuple(joints), tuple(visuals))


def _palm(r: float) -> Visual:
    h = PALM_HEIGHT_MM * _MM
    return Visual("palm", "cylinder", (r + _LINK_WIDTH_MM * _MM, h, 0.0), (0.0, 0.0, h / 2))


def _finger(
    finger: str,
    geom: HandGeometry,
    tactile: TactileConfig,
    lim: Mapping[str, tuple[float, float]],
    speed: Mapping[str, float],
) -> tuple[list[str], list[Joint], list[Visual]]:
    """One finger's links, joints and visuals below its knuckle (the frame after the base)."""
    l1, l2 = geom.proximal_length_mm * _MM, geom.distal_length_mm * _MM
    pad = geom.pad
    prox_name, dist_name = _finger_joint_names(finger)
    knuckle, prox, dist = f"{finger}_knuckle", f"{finger}_proximal", f"{finger}_distal"
    frame3, ppad, dpad = f"{finger}_frame3", f"{finger}_proximal_pad", f"{finger}_distal_pad"
    k = KNUCKLE_MM * _MM
    joints = [
        _revolute(
            prox_name,
            knuckle,
            prox,
            (0.0, 0.0, k),
            _CLOSE,
            lim[prox_name],
            velocity=speed[prox_name],
        ),
        _revolute(
            dist_name, prox, dist, (0.0, 0.0, l1), _CLOSE, lim[dist_name], velocity=speed[dist_name]
        ),
        # frame 3: x3 along the link (the link's z), y3 towards the pad (the link's y)
        Joint(f"{finger}_frame3", dist, frame3, (0.0, 0.0, 0.0), (0.0, -math.pi / 2, 0.0)),
    ]
    pitch = tactile.texel_pitch_mm * _MM
    # the distal matrix: tangent to the pad at its middle row, centred on it
    d = tactile.distal
    s_mid = tactile.texel_pitch_mm * (d.rows - 1) / 2
    L_mid = pad.pad_base_to_active_mm + pad.sensor_active_length_mm * (
        1.0 - s_mid / (tactile.texel_pitch_mm * (d.rows - 1))
    )
    x3 = x3_from_L(L_mid, pad)
    beta = math.atan(-pad_slope(x3, pad))  # the surface's tilt from the link's axis there
    y3 = pad_y3(x3, pad)
    joints.append(
        _pad_frame(
            f"{finger}_distal_pad", dist, (y3 * _MM, x3 * _MM), beta, d.cols * pitch, d.rows * pitch
        )
    )
    # the proximal matrix (display: its place is not in the model)
    p = tactile.proximal
    z_mid = l1 - (PROXIMAL_ROW0_FROM_DISTAL_MM + tactile.texel_pitch_mm * (p.rows - 1) / 2) * _MM
    y_prox = PROXIMAL_PAD_Y_MM * _MM
    joints.append(
        _pad_frame(
            f"{finger}_proximal_pad", prox, (y_prox, z_mid), 0.0, p.cols * pitch, p.rows * pitch
        )
    )
    w = _LINK_WIDTH_MM * _MM
    py0, py1 = (v * _MM for v in _PROXIMAL_BODY_Y_MM)
    dy0, dy1 = (v * _MM for v in _DISTAL_BODY_Y_MM)
    dz0, dz1 = -_DISTAL_BODY_BEHIND_MM * _MM, l2 - _DISTAL_BODY_SHORT_MM * _MM
    visuals = [
        Visual(knuckle, "box", (w, w, k), (0.0, 0.0, k / 2)),
        Visual(prox, "box", (w, py1 - py0, l1), (0.0, (py0 + py1) / 2, l1 / 2)),
        Visual(dist, "box", (w, dy1 - dy0, dz1 - dz0), (0.0, (dy0 + dy1) / 2, (dz0 + dz1) / 2)),
        _slab(prox, p.cols * pitch, (y_prox, z_mid), 0.0, p.rows * pitch, y_prox - py1),
        *_distal_pad(dist, d.cols * pitch, geom),
    ]
    return [knuckle, prox, dist, frame3, ppad, dpad], joints, visuals


def _pad_frame(
    name: str, link: str, centre_yz: tuple[float, float], beta: float, width: float, length: float
) -> Joint:
    """A pad's grid frame on ``link``: centred at (0, y, z), tilted by β about x, corner origin."""
    yc, zc = centre_yz
    # pad x = link x, pad y = −(surface tangent towards the tip), pad z = outward normal
    ty, tz = -math.sin(beta), math.cos(beta)  # the tangent towards the tip, link (y, z)
    oy = yc + (length / 2) * ty
    oz = zc + (length / 2) * tz
    return Joint(name, link, name, (-width / 2, oy, oz), (beta + _PAD_FRAME_RPY[0], 0.0, 0.0))


def _slab(
    link: str,
    width: float,
    surface_yz: tuple[float, float],
    beta: float,
    length: float,
    t: float,
) -> Visual:
    """A pad strip ``t`` thick under the surface point, tilted by β about x."""
    ys, zs = surface_yz
    ny, nz = math.cos(beta), math.sin(beta)  # the outward normal, link (y, z)
    return Visual(
        link,
        "box",
        (width, t, length),
        (0.0, ys - ny * t / 2, zs - nz * t / 2),
        (beta, 0.0, 0.0),
        "pad",
    )


def _distal_pad(link: str, width: float, geom: HandGeometry) -> list[Visual]:
    """The distal pad's flat part and its arc (as short tangent strips), down to its back."""
    pad = geom.pad
    flat = pad.flat_end_x3_mm - pad.flat_start_x3_mm
    mid = (pad.flat_start_x3_mm + pad.flat_end_x3_mm) / 2
    t = (pad.flat_y3_mm - _PAD_BACK_Y3_MM) * _MM
    out = [_slab(link, width, (pad.flat_y3_mm * _MM, mid * _MM), 0.0, flat * _MM, t)]
    R = pad.arc_radius_mm
    end = math.asin((pad.tip_end_x3_mm - pad.flat_end_x3_mm) / R)
    for i in range(_ARC_SEGMENTS):
        b0, b1 = end * i / _ARC_SEGMENTS, end * (i + 1) / _ARC_SEGMENTS
        bm = (b0 + b1) / 2
        # a tangent strip at the arc's mid angle, as long as the chord's projection on it
        x3 = pad.flat_end_x3_mm + R * math.sin(bm)
        y3 = pad.flat_y3_mm - R + R * math.cos(bm)
        chord = 2 * R * math.sin((b1 - b0) / 2)
        t = (y3 - _PAD_BACK_Y3_MM) / math.cos(bm) * _MM  # along the normal, to the back plane
        out.append(_slab(link, width, (y3 * _MM, x3 * _MM), bm, chord * _MM, t))
    return out


# --- the XML ------------------------------------------------------------------------------------


def _v(v: Vec3) -> str:
    return " ".join(repr(float(x)) for x in v)


def _geometry(parent: ET.Element, vis: Visual) -> None:
    """A visual's ``<origin>`` and ``<geometry>`` under ``parent`` (its visual or collision)."""
    ET.SubElement(parent, "origin", xyz=_v(vis.xyz), rpy=_v(vis.rpy))
    g = ET.SubElement(parent, "geometry")
    if vis.shape == "box":
        ET.SubElement(g, "box", size=_v(vis.size))
    else:
        ET.SubElement(g, "cylinder", radius=repr(vis.size[0]), length=repr(vis.size[1]))


def to_xml(desc: HandDescription, name: str = "sdh2") -> str:
    """The description as URDF text: each visual also as a ``<collision>`` of the same shape
    and place (the pads' strips too); no ``<inertial>`` (no source for the links' masses)."""
    robot = ET.Element("robot", name=name)
    for mat, rgba in ((m, " ".join(f"{c:g}" for c in v)) for m, v in MATERIALS.items()):
        ET.SubElement(ET.SubElement(robot, "material", name=mat), "color", rgba=rgba)
    by_link: dict[str, list[Visual]] = {}
    for vis in desc.visuals:
        by_link.setdefault(vis.link, []).append(vis)
    for link in desc.links:
        el = ET.SubElement(robot, "link", name=link)
        for vis in by_link.get(link, []):
            v = ET.SubElement(el, "visual")
            _geometry(v, vis)
            ET.SubElement(v, "material", name=vis.material)
        for vis in by_link.get(link, []):  # (URDF: a link's visuals, then its collisions)
            _geometry(ET.SubElement(el, "collision"), vis)
    for j in desc.joints:
        el = ET.SubElement(robot, "joint", name=j.name, type=j.kind)
        ET.SubElement(el, "parent", link=j.parent)
        ET.SubElement(el, "child", link=j.child)
        ET.SubElement(el, "origin", xyz=_v(j.xyz), rpy=_v(j.rpy))
        if j.kind == "revolute":
            ET.SubElement(el, "axis", xyz=_v(j.axis))
            ET.SubElement(el, "limit", lower=repr(j.lower), upper=repr(j.upper),
                          effort=repr(EFFORT_PLACEHOLDER), velocity=repr(j.velocity))  # fmt: skip
        if j.mimic:
            ET.SubElement(el, "mimic", joint=j.mimic, multiplier="1.0", offset="0.0")
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def sdh2_urdf(
    geom: HandGeometry, axes: AxisMap, limits: JointLimits, tactile: TactileConfig
) -> str:
    """The SDH2's URDF text from the configuration's sections."""
    return to_xml(describe(geom, axes, limits, tactile))


# --- the joints' transforms (what a FrameTransforms message carries) ----------------------------


def quat_from_rpy(rpy: Vec3) -> Quat:
    """URDF's fixed-axis roll, pitch, yaw as a quaternion (x, y, z, w): R = Rz·Ry·Rx."""
    r, p, y = (a / 2 for a in rpy)
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
    cy, sy = math.cos(y), math.sin(y)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def quat_mul(a: Quat, b: Quat) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_axis_angle(axis: Vec3, angle: float) -> Quat:
    s = math.sin(angle / 2)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


@dataclass(frozen=True, slots=True)
class Transform:
    """A joint's parent → child transform: translation (m) and rotation (x, y, z, w)."""

    parent: str
    child: str
    translation: Vec3
    rotation: Quat


def joint_transforms(desc: HandDescription, angles: Mapping[str, float]) -> list[Transform]:
    """Every joint's transform for the actuated joints' ``angles`` (rad; missing ones at 0)."""
    out = []
    for j in desc.joints:
        q = quat_from_rpy(j.rpy)
        if j.kind == "revolute":
            q = quat_mul(q, quat_axis_angle(j.axis, angles.get(j.mimic or j.name, 0.0)))
        out.append(Transform(j.parent, j.child, j.xyz, q))
    return out


def main(argv: list[str] | None = None) -> None:
    """``python -m sdh2svc.model.urdf [--config FILE] [--set KEY=VALUE …] [-o FILE]``: the
    configuration's URDF, on stdout or written whole to FILE. The configuration is loaded as
    sdh2svc's commands load it (defaults ← ``--config`` ← environment ← ``--set``); a bad one
    or a file that cannot be written is said as they say it, exit 2 or 4, no traceback."""
    import argparse

    from sdh2svc.config import ConfigError, load_config  # the entry point composes
    from sdh2svc.files import whole_file

    p = argparse.ArgumentParser(
        prog="python -m sdh2svc.model.urdf",
        description="Print the SDH2's URDF, generated from the configuration's geometry.",
    )
    p.add_argument("--config", metavar="FILE", help="a TOML file overriding config/default.toml")
    p.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
        help="override one key, e.g. --set limits.max_deg=[90,80,90,90,90,90,90] (repeatable; "
        "beats file and environment)",
    )  # fmt: skip
    p.add_argument("-o", "--output", metavar="FILE",
                   help="write it to FILE (whole, or not at all), not to stdout")  # fmt: skip
    args = p.parse_args(argv)
    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as e:  # as sdh2svc's commands say it: the problems, exit 2
        p.exit(2, f"{p.prog}: {e}\n")
    text = sdh2_urdf(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
    if args.output is None:
        print(text, end="")
        return
    try:
        with whole_file(args.output, binary=False) as out:
            out.write(text)
    except OSError as e:  # as sdh2svc's commands say it: I/O, exit 4
        p.exit(4, f"{p.prog}: cannot write {args.output}: {e.strerror or e}\n")


if __name__ == "__main__":
    main()
