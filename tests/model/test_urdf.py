"""The SDH2's URDF: it parses, and its forward kinematics is the model's (hand-model §2)."""

from __future__ import annotations

import io
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yourdfpy

from sdh2svc.config import Settings
from sdh2svc.model.geometry import pad_point_from_L, pad_y3, virtual_joint
from sdh2svc.model.hand import HAND_VELOCITY_LIMIT_DEG_S
from sdh2svc.model.kinematics import Finger, contact_point, distal_joint, pad_point
from sdh2svc.model.urdf import (
    EFFORT_PLACEHOLDER,
    FINGERS,
    PADS,
    describe,
    joint_names,
    joint_transforms,
    main,
    pad_matrix,
    quat_from_rpy,
    sdh2_urdf,
)

MM = 1e-3
TOL_MM = 1e-6
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def text(cfg: Settings) -> str:
    return sdh2_urdf(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)


@pytest.fixture(scope="module")
def robot(text: str) -> yourdfpy.URDF:
    return yourdfpy.URDF.load(
        io.StringIO(text), load_meshes=False, build_collision_scene_graph=False
    )


def _rot(q: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_parses_with_every_finger_pad_and_configured_limit(cfg: Settings, text: str) -> None:
    root = ET.fromstring(text)
    links = {e.get("name") for e in root.iter("link")}
    for f in FINGERS:
        for part in ("knuckle", "proximal", "distal", "frame3", "proximal_pad", "distal_pad"):
            assert f"{f}_{part}" in links
    joints = {e.get("name"): e for e in root.iter("joint")}
    for axis, name in joint_names(cfg.axes).items():
        limit = joints[name].find("limit")
        assert limit is not None and joints[name].get("type") == "revolute"
        assert float(limit.get("lower", "")) == pytest.approx(
            math.radians(cfg.limits.min_deg[axis])
        )
        assert float(limit.get("upper", "")) == pytest.approx(
            math.radians(cfg.limits.max_deg[axis])
        )
    mimic = joints["phi1_finger2"].find("mimic")
    assert mimic is not None and mimic.get("joint") == "phi1"  # φ1 turns both coupled fingers
    # the pads are drawn: the distal one along its flat part and arc on every finger
    pads = [
        v
        for v in describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile).visuals
        if v.material == "pad"
    ]
    assert {v.link for v in pads} == {f"{f}_{p}" for f in FINGERS for p in PADS}
    assert len(pads) > 3 * 2 + 3 * 4
    assert {pad_matrix(cfg.axes, f, p) for f in FINGERS for p in PADS} == set(range(6))


def test_actuated_joints_are_the_seven_axes(cfg: Settings, robot: yourdfpy.URDF) -> None:
    assert set(robot.actuated_joint_names) == set(joint_names(cfg.axes).values())


def _in_frame0(robot: yourdfpy.URDF, frame: str, p: np.ndarray) -> np.ndarray:
    T = robot.get_transform(frame, "frame0")
    return np.asarray(T[:3, :3] @ p + T[:3, 3])


def test_forward_kinematics_matches_the_model_at_random_poses(
    cfg: Settings, robot: yourdfpy.URDF
) -> None:
    rng = np.random.default_rng(18)
    geom = cfg.hand
    lo, hi = np.radians(cfg.limits.min_deg), np.radians(cfg.limits.max_deg)
    names = joint_names(cfg.axes)
    for _ in range(40):
        q = rng.uniform(lo, hi)
        q[cfg.axes.phi1] = math.pi / 2  # the plane of work: the coupled fingers face each other
        robot.update_cfg({names[a]: float(q[a]) for a in range(7)})
        for finger, (pa, da) in (
            (Finger.ONE, (cfg.axes.phi2, cfg.axes.phi3)),
            (Finger.TWO, (cfg.axes.phi4, cfg.axes.phi5)),
        ):
            prox, dist = float(q[pa]), float(q[da])
            frame3 = f"finger{int(finger)}_frame3"
            C = distal_joint(finger, prox, geom)
            got = _in_frame0(robot, frame3, np.zeros(3)) / MM
            assert np.abs(got - [0.0, C.y, C.z]).max() < TOL_MM
            for L in rng.uniform(0.0, geom.pad.max_L_mm, 4):
                x3, y3 = pad_point_from_L(float(L), geom.pad)
                got = _in_frame0(robot, frame3, np.array([x3, y3, 0.0]) * MM) / MM
                P = pad_point(finger, prox, dist, x3, y3, geom)
                assert np.abs(got - [0.0, P.y, P.z]).max() < TOL_MM
                r, theta = virtual_joint(x3, y3)
                A = contact_point(finger, prox, dist, r, theta, geom)
                assert np.abs(got - [0.0, A.y, A.z]).max() < TOL_MM


def test_phi1_zero_turns_the_coupled_fingers_to_face_the_thumb(
    cfg: Settings, robot: yourdfpy.URDF
) -> None:
    closed = {"phi2": 0.5, "phi4": 0.5, "thumb_proximal": 0.5}
    robot.update_cfg({n: closed.get(n, 0.0) for n in robot.actuated_joint_names})
    tip = np.array([0.0, 0.0, cfg.hand.distal_length_mm * MM])
    for f in ("finger1", "finger2", "thumb"):
        T = robot.get_transform(f"{f}_distal", "palm")
        knuckle = robot.get_transform(f"{f}_knuckle", "palm")[:3, 3]
        # closing moves a finger's tip towards the palm's middle along x
        moved = (T[:3, :3] @ tip + T[:3, 3])[0] - knuckle[0]
        assert moved * knuckle[0] < 0


def test_frame0_has_the_thumb_where_the_3d_view_puts_it(
    cfg: Settings, robot: yourdfpy.URDF
) -> None:
    """x0 towards the thumb: its knuckle at (d·√3/2, d/2) in frame 0 (service/viewer.py)."""
    d = cfg.hand.base_offset_mm
    robot.update_cfg({n: 0.0 for n in robot.actuated_joint_names})
    x0, y0, _ = robot.get_transform("thumb_knuckle", "frame0")[:3, 3] / MM
    assert (x0, y0) == pytest.approx((d * math.sqrt(3) / 2, d / 2))


def test_the_transforms_a_recording_carries_are_the_urdfs(
    cfg: Settings, robot: yourdfpy.URDF
) -> None:
    desc = describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
    rng = np.random.default_rng(7)
    angles = {n: float(rng.uniform(-1.0, 1.0)) for n in desc.actuated}
    robot.update_cfg(angles)
    for t in joint_transforms(desc, angles):
        T = robot.get_transform(t.child, t.parent)
        assert np.allclose(T[:3, 3], t.translation, atol=1e-12)
        assert np.allclose(T[:3, :3], _rot(t.rotation), atol=1e-12)


def test_the_distal_grid_is_centred_on_the_pad(cfg: Settings, robot: yourdfpy.URDF) -> None:
    """The tactile grid's middle lies on the pad surface, tangent to it."""
    d, pitch = cfg.tactile.distal, cfg.tactile.texel_pitch_mm
    centre = np.array([d.cols * pitch / 2, d.rows * pitch / 2, 0.0]) * MM
    T = robot.get_transform("finger1_distal_pad", "finger1_frame3")
    x3, y3, z3 = (T[:3, :3] @ centre + T[:3, 3]) / MM
    pad = cfg.hand.pad
    assert z3 == pytest.approx(0.0, abs=1e-9) and y3 == pytest.approx(
        pad_point_from_L(27.5, pad)[1]
    )
    assert x3 == pytest.approx(pad_point_from_L(27.5, pad)[0])
    # the grid's rows run from the fingertip's end (row 0) towards the distal joint
    assert (T[:3, :3] @ [0.0, 1.0, 0.0])[0] < 0


def test_the_distal_pad_is_drawn_along_its_profile(cfg: Settings) -> None:
    """Every strip of the distal pad touches the flat-and-arc profile of hand-model §3."""
    pad = cfg.hand.pad
    strips = [
        v
        for v in describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile).visuals
        if v.link == "finger1_distal" and v.material == "pad"
    ]
    reach = []
    for v in strips:
        a = v.rpy[0]  # the strip's tilt about x; its y axis is the outward normal
        y = v.xyz[1] + math.cos(a) * v.size[1] / 2
        z = v.xyz[2] + math.sin(a) * v.size[1] / 2
        x3, y3 = z / MM, y / MM
        assert y3 == pytest.approx(pad_y3(x3, pad), abs=1e-9)
        reach += [x3 - math.cos(a) * v.size[2] / 2 / MM, x3 + math.cos(a) * v.size[2] / 2 / MM]
    assert min(reach) == pytest.approx(pad.flat_start_x3_mm)
    assert max(reach) == pytest.approx(pad.tip_end_x3_mm, abs=0.1)


def test_rpy_quaternion_is_urdfs_convention() -> None:
    r = _rot(quat_from_rpy((0.3, -0.2, 1.1)))
    c = [math.cos(a) for a in (0.3, -0.2, 1.1)]
    s = [math.sin(a) for a in (0.3, -0.2, 1.1)]
    Rx = np.array([[1, 0, 0], [0, c[0], -s[0]], [0, s[0], c[0]]])
    Ry = np.array([[c[1], 0, s[1]], [0, 1, 0], [-s[1], 0, c[1]]])
    Rz = np.array([[c[2], -s[2], 0], [s[2], c[2], 0], [0, 0, 1]])
    assert np.allclose(r, Rz @ Ry @ Rx)


def test_the_entry_point_prints_the_configurations_urdf(
    text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    main([])
    assert capsys.readouterr().out == text


def test_the_entry_point_names_a_bad_configuration_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for config in (tmp_path / "missing.toml", tmp_path / "typo.toml"):
        if config.name == "typo.toml":
            config.write_text("[limits]\nmax_deg = [90, -80, 90, 90, 90, 90, 90]\n")
        with pytest.raises(SystemExit) as ended:
            main(["--config", str(config)])
        assert ended.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("python -m sdh2svc.model.urdf: invalid configuration")
        assert "Traceback" not in err and len(err.splitlines()) == 1, err


def _shapes(el: ET.Element, tag: str) -> list[tuple[str, ...]]:
    """Each ``tag`` child's origin and geometry, as text."""
    out = []
    for body in el.findall(tag):
        origin, geometry = body.find("origin"), body.find("geometry")
        assert origin is not None and geometry is not None and len(geometry) == 1
        shape = geometry[0]
        out.append((origin.get("xyz", ""), origin.get("rpy", ""), shape.tag,
                    *(f"{k}={v}" for k, v in sorted(shape.attrib.items()))))  # fmt: skip
    return out


def test_every_visual_is_a_collision_body_of_the_same_shape_and_place(
    cfg: Settings, text: str
) -> None:
    """Simulators and planners see the hand's volume: each link's visuals, the pads' strips
    too, are its collisions, and nothing else is."""
    root = ET.fromstring(text)
    visuals = 0
    for link in root.iter("link"):
        drawn = _shapes(link, "visual")
        assert _shapes(link, "collision") == drawn, link.get("name")
        visuals += len(drawn)
    desc = describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
    assert visuals == len(desc.visuals)
    # a URDF reader builds them: every pad strip a collision box on its link
    robot = yourdfpy.URDF.load(io.StringIO(text), load_meshes=False)
    for f in FINGERS:
        for part in ("proximal", "distal"):
            link = robot.link_map[f"{f}_{part}"]
            assert len(link.collisions) == len(link.visuals) > 1
    # no inertial: no source gives the links' masses (docs/foxglove.md, the URDF paragraph)
    assert root.find(".//inertial") is None


def test_joint_velocity_limits_are_the_sdh2s_own(cfg: Settings, text: str) -> None:
    """Each joint's velocity limit is its wire axis's (SDHLibrary-CPP's fixed limits, as
    protocols.md §2.2 quotes them), in rad/s; φ1's mimic moves as fast as φ1; the effort is
    the placeholder."""
    quoted = re.search(r"library fallback for very old firmware: ([\d., ]+) deg/s",
                       (ROOT / "docs" / "protocols.md").read_text())  # fmt: skip
    assert quoted is not None
    assert HAND_VELOCITY_LIMIT_DEG_S == tuple(float(v) for v in quoted[1].split(","))
    joints = {e.get("name"): e for e in ET.fromstring(text).iter("joint")}
    for axis, name in joint_names(cfg.axes).items():
        limit = joints[name].find("limit")
        assert limit is not None
        velocity = float(limit.get("velocity", ""))
        assert velocity == pytest.approx(math.radians(HAND_VELOCITY_LIMIT_DEG_S[axis]))
        assert float(limit.get("effort", "")) == EFFORT_PLACEHOLDER
    mimic = joints["phi1_finger2"].find("limit")
    assert mimic is not None
    assert float(mimic.get("velocity", "")) == pytest.approx(math.radians(85.7))
    # by wire axis, not by role: a hand wired otherwise keeps each axis's own limit
    swapped = cfg.axes.model_copy(update={"phi2": cfg.axes.phi3, "phi3": cfg.axes.phi2})
    desc = describe(cfg.hand, swapped, cfg.limits, cfg.tactile)
    got = {j.name: j.velocity for j in desc.joints if j.kind == "revolute"}
    assert got["phi2"] == pytest.approx(math.radians(HAND_VELOCITY_LIMIT_DEG_S[swapped.phi2]))


def _limits(urdf: str) -> dict[str, tuple[float, float]]:
    out = {}
    for joint in ET.fromstring(urdf).iter("joint"):
        if (limit := joint.find("limit")) is not None:
            out[joint.get("name", "")] = (float(limit.get("lower", "")),
                                          float(limit.get("upper", "")))  # fmt: skip
    return out


def test_the_entry_point_takes_set_as_the_cli_does_and_writes_the_file_whole(
    cfg: Settings, text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sdh2.urdf"
    main(["-o", str(out)])
    assert out.read_text() == text and capsys.readouterr().out == ""
    # --set, repeatable, laid over the file as sdh2svc's commands lay it
    config = tmp_path / "narrow.toml"
    config.write_text("[limits]\nmax_deg = [90, 70, 90, 90, 90, 90, 90]\n")
    main(["--config", str(config),
          "--set", "limits.max_deg=[90, 80, 90, 90, 90, 90, 90]",
          "--set", "limits.min_deg=[0, -90, -60, -90, -90, -90, -90]",
          "--output", str(out)])  # fmt: skip
    got = _limits(out.read_text())
    phi2, phi3 = joint_names(cfg.axes)[1], joint_names(cfg.axes)[2]
    assert got[phi2][1] == pytest.approx(math.radians(80.0))
    assert got[phi3][0] == pytest.approx(math.radians(-60.0))
    assert set(tmp_path.iterdir()) == {config, out}  # replaced in place, nothing beside it


def test_the_entry_point_says_a_bad_set_or_an_unwritable_file_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for argv, code, said in (
        (["--set", "limits.max_deg=[90, 80]"], 2, "(--set limits.max_deg=[90, 80])"),
        (["--set", "limits"], 2, "must look like section.key=value"),
        (["-o", str(tmp_path / "no-such-dir" / "sdh2.urdf")], 4, "cannot write"),
    ):
        with pytest.raises(SystemExit) as ended:
            main(argv)
        assert ended.value.code == code
        err = capsys.readouterr().err
        assert err.startswith("python -m sdh2svc.model.urdf: ") and said in err, err
        assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert not any(tmp_path.iterdir())  # nothing half-written
