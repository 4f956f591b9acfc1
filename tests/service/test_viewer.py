"""The viser 3-D view (sdh2svc.service.viewer): served, posed like the model, cheap to feed."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import viser
import viser.transforms as vtf
import websockets.asyncio.server
from viser import GuiEvent
from viser_client import PROTOCOL, browser, camera_message, ws_url
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus
from websockets.typing import Origin, Subprotocol

from sdh2svc.config import Settings
from sdh2svc.control.sample import Sample
from sdh2svc.model.geometry import pad_point_from_L, pad_y3
from sdh2svc.model.hand import matrix_shapes
from sdh2svc.model.kinematics import Finger, Point, frame3_axes, pad_point
from sdh2svc.service import telemetry, viewer_proc
from sdh2svc.service import viewer as viewer_module
from sdh2svc.service.app import _start_viewer
from sdh2svc.service.pacing import BURST, MIN_GAP
from sdh2svc.service.replay_feed import Recorded, recorded_iteration
from sdh2svc.service.store import Recorder as RunRecorder
from sdh2svc.service.store import RunStore
from sdh2svc.service.telemetry import (
    Contact,
    SampleMsg,
    SampleView,
    contact_normal,
)
from sdh2svc.service.viewer import (
    BUTTONS,
    GREEN,
    MM,
    NEEDS_TOKEN,
    READ_ONLY_NOTE,
    RED,
    YELLOW,
    Viewer,
    ViewerSecurityError,
    cone_color,
    distal_cells,
    finger_frames,
    origin_allowed,
    start_viser,
    tactile_colors,
)

# The mirror pose of hand-model §6: φ2 = φ4 = −20°, φ3 = φ5 = 30° (wire axes 1, 2, 5, 6).
POSE = [90.0, -20.0, 30.0, -90.0, 0.0, -20.0, 30.0]
SAMPLE = {
    "iteration": 7, "phi2": -20.0, "phi3": 30.0, "phi4": -20.0, "phi5": 30.0,
    "Ay": -8.0, "Az": 140.0, "By": 74.0, "Bz": 140.0, "omega_A": 90.0, "omega_B": 115.0,
}  # fmt: skip


class Recorder:
    """An on_command that records what reached it (on the loop), optionally refusing."""

    def __init__(self, refuse: bool = False) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.refuse = refuse
        self.loops: list[asyncio.AbstractEventLoop] = []

    async def __call__(self, kind: str, args: dict[str, Any]) -> None:
        self.loops.append(asyncio.get_running_loop())
        self.calls.append((kind, args))
        if self.refuse:
            raise RuntimeError("a run is already running")


@pytest.fixture
async def commands() -> Recorder:
    return Recorder()


@contextlib.asynccontextmanager
async def watching(v: Viewer) -> AsyncIterator[None]:
    """A browser on the view: a viser websocket client reading all it is sent. The view draws
    only while someone watches; this waits for the first frame drawn for the watcher."""
    proto = [Subprotocol(f"viser-v{viser.__version__}")]
    url = v.url.replace("http://", "ws://")
    async with connect(url, subprotocols=proto, max_size=2**26) as ws:
        await ws.send(camera_message())

        async def read() -> None:
            with contextlib.suppress(Exception):
                async for _ in ws:
                    pass

        reader = asyncio.create_task(read())
        try:
            await wait_for(lambda: v.watched)
            await wait_for(lambda: not v._dirty)
            yield
        finally:
            reader.cancel()


@pytest.fixture
async def viewer(cfg: Settings, commands: Recorder) -> AsyncIterator[Viewer]:
    v = Viewer(cfg, port=0, on_command=commands)
    await v.start()
    try:
        async with watching(v):
            yield v
    finally:
        await v.stop()


async def next_frame(v: Viewer, after: int, timeout: float = 30.0) -> None:
    """Wait until the render task has drawn a frame beyond ``after``."""
    deadline = time.monotonic() + timeout
    while v.frames <= after:
        assert time.monotonic() < deadline, "the view did not render"
        await asyncio.sleep(0.01)


def world(v: Viewer, frame: str, local: np.ndarray) -> np.ndarray:
    """A point given in a posed scene frame, in scene coordinates (m), from the scene's handles."""
    node = v.nodes[frame]
    R = vtf.SO3(np.asarray(node.wxyz)).as_matrix()
    return np.asarray(node.position) + R @ np.asarray(local)


async def click(handle: Any) -> None:
    """Fire a GUI element's callbacks the way viser does: on a worker thread, with a GuiEvent."""
    for cb in list(handle._impl.update_cb):
        await asyncio.to_thread(cb, GuiEvent(client=None, client_id=None, target=handle))


async def wait_for(pred: Any, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        await asyncio.sleep(0.01)


# --- (a) served --------------------------------------------------------------------------------


async def test_serves_the_viser_client_on_a_free_port(viewer: Viewer) -> None:
    assert viewer.url.startswith("http://127.0.0.1:")
    assert not viewer.url.endswith(":0")

    def get() -> tuple[int, bytes]:
        with urllib.request.urlopen(viewer.url, timeout=10) as r:
            return r.status, r.read()

    status, body = await asyncio.to_thread(get)
    assert status == 200
    assert b"<html" in body.lower()


# --- (b) posed like the planar model -------------------------------------------------------


def test_finger_frames_match_the_planar_model(cfg: Settings) -> None:
    """Fingers 1 and 2 at φ1 = 90° lie in x0 = 0 and follow hand-model §2 to the micrometre."""
    frames = finger_frames(POSE, cfg)
    p2, p3, p4, p5 = (math.radians(v) for v in (-20.0, 30.0, -20.0, 30.0))
    C = (86.5 * math.sin(p2), 86.5 * math.cos(p2))  # hand-model §2, written out
    D = (66.0 - 86.5 * math.sin(p4), 86.5 * math.cos(p4))
    assert np.allclose(frames["/f1/distal"][:3, 3], (0.0, *C), atol=1e-9)
    assert np.allclose(frames["/f2/distal"][:3, 3], (0.0, *D), atol=1e-9)
    psi = p2 + p3  # frame 3's axes (§2): ex3 = (sin ψ, cos ψ), ey3 = (cos ψ, −sin ψ)
    assert np.allclose(frames["/f1/distal"][:3, 0], (0, math.sin(psi), math.cos(psi)))
    assert np.allclose(frames["/f1/distal"][:3, 1], (0, math.cos(psi), -math.sin(psi)))
    x3 = cfg.hand.pad.tip_end_x3_mm
    y3 = pad_y3(x3, cfg.hand.pad)
    for key, f, (a, b) in (("f1", Finger.ONE, (p2, p3)), ("f2", Finger.TWO, (p4, p5))):
        tip = pad_point(f, a, b, x3, y3, cfg.hand)
        assert np.allclose(frames[f"/{key}/tip"][:3, 3], (0.0, tip.y, tip.z), atol=1e-9)
        for link in ("base", "proximal", "distal", "tip"):
            T = frames[f"/{key}/{link}"]
            assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)  # a rotation
            assert abs(T[0, 3]) < 1e-9  # in the plane of work


async def test_scene_fingertips_follow_pose_and_sample(cfg: Settings, viewer: Viewer) -> None:
    n = viewer.frames
    viewer.handle({"type": "pose", "angles_deg": POSE})
    viewer.handle({"type": "sample", "run_id": 1, "sample": SAMPLE})
    await next_frame(viewer, n)
    x3 = cfg.hand.pad.tip_end_x3_mm
    tip_local = np.array([x3, pad_y3(x3, cfg.hand.pad), 0.0]) * MM
    assert np.allclose(viewer.nodes["/f1/distal/tip"].position, tip_local)
    for key, f in (("f1", Finger.ONE), ("f2", Finger.TWO)):
        want = pad_point(f, math.radians(-20), math.radians(30), x3, tip_local[1] / MM, cfg.hand)
        got = world(viewer, f"/{key}/distal", tip_local)
        assert np.allclose(got, np.array([0.0, want.y, want.z]) * MM, atol=1e-9)
    # the contact points and segment AB where the sample puts them (y0z0 plane, mm → m)
    assert np.allclose(viewer.nodes["/contacts/A"].position, np.array([0, -8.0, 140.0]) * MM)
    assert viewer.nodes["/contacts/AB"].visible
    assert np.allclose(viewer.nodes["/contacts/AB"].points[0, 1], np.array([0, 74, 140]) * MM)

    # a later sample moves Finger 1 by φ2, φ3 alone (the pose's other axes stay)
    n = viewer.frames
    viewer.handle({"type": "sample", "sample": {**SAMPLE, "phi2": 0.0, "phi3": 0.0}})
    await next_frame(viewer, n)
    got = world(viewer, "/f1/distal", tip_local)
    assert np.allclose(got, np.array([0.0, tip_local[1] / MM, 86.5 + x3]) * MM, atol=1e-9)


# --- (c) friction cones ----------------------------------------------------------------------


def test_cone_colour_runs_green_to_red(cfg: Settings) -> None:
    alpha = cfg.rolling.alpha_deg
    assert cone_color(0.0, alpha) == GREEN
    assert cone_color(alpha / 2, alpha) == YELLOW
    assert cone_color(alpha, alpha) == RED
    assert cone_color(3 * alpha, alpha) == RED
    assert cone_color(-alpha, alpha) == RED  # |deviation|
    ramp = [cone_color(alpha * k / 10, alpha) for k in range(11)]
    reds, greens = [c[0] for c in ramp], [c[1] for c in ramp]
    assert reds == sorted(reds) and greens == sorted(greens, reverse=True)  # closer → redder


def test_contact_normal_is_the_pad_normal(cfg: Settings) -> None:
    p2, p3 = math.radians(-20.0), math.radians(30.0)
    ex, ey = frame3_axes(Finger.ONE, p2 + p3)
    x3, y3 = pad_point_from_L(8.0, cfg.hand.pad)  # on the flat part: the normal is ey3
    A = pad_point(Finger.ONE, p2, p3, x3, y3, cfg.hand)
    n = contact_normal(Finger.ONE, p2, p3, A, cfg.hand)
    assert math.isclose(n.y, ey.y, abs_tol=1e-9) and math.isclose(n.z, ey.z, abs_tol=1e-9)
    # on the arc it tilts away from ey3 towards −ex3 (the pad curves back), still unit length
    x3, y3 = pad_point_from_L(40.0, cfg.hand.pad)
    A = pad_point(Finger.ONE, p2, p3, x3, y3, cfg.hand)
    n = contact_normal(Finger.ONE, p2, p3, A, cfg.hand)
    assert math.isclose(math.hypot(n.y, n.z), 1.0)
    assert n.y * ex.y + n.z * ex.z > 0.2
    # Finger 2 is the mirror image
    B = pad_point(Finger.TWO, p2, p3, x3, y3, cfg.hand)
    m = contact_normal(Finger.TWO, p2, p3, B, cfg.hand)
    assert math.isclose(m.y, -n.y, abs_tol=1e-9) and math.isclose(m.z, n.z, abs_tol=1e-9)


async def test_cones_sit_at_the_contacts_coloured_by_omega(viewer: Viewer) -> None:
    n = viewer.frames
    viewer.handle({"type": "status", "status": {"params": {"alpha_deg": 25.0}}})
    viewer.handle({"type": "sample", "sample": SAMPLE})  # ωA = 90° (on the normal), ωB = 115°
    await next_frame(viewer, n)
    cone_a, cone_b = viewer.nodes["/contacts/cone_A"], viewer.nodes["/contacts/cone_B"]
    assert cone_a.visible and cone_b.visible
    assert tuple(cone_a.color) == GREEN
    assert tuple(cone_b.color) == RED  # |115° − 90°| = α
    assert np.allclose(cone_a.position, np.array([0, -8.0, 140.0]) * MM)
    r, _, h = cone_a.scale
    assert math.isclose(math.degrees(math.atan2(r, h)), 25.0)  # half-angle α
    axis = vtf.SO3(np.asarray(cone_a.wxyz)).as_matrix()[:, 2]
    p = [math.radians(v) for v in (-20.0, 30.0)]
    normal = contact_normal(Finger.ONE, p[0], p[1], Point(-8.0, 140.0), viewer.settings.hand)
    assert np.allclose(axis, (0.0, normal.y, normal.z))
    # A blue and B red, as on the dashboard, each labelled (a child: it moves and hides with it)
    for name, color in (("A", (31, 119, 180)), ("B", (214, 39, 40))):
        point = viewer.nodes[f"/contacts/{name}"]
        assert point.visible and tuple(point.color) == color
        assert viewer.nodes[f"/contacts/{name}/label"].text == name


async def test_cones_open_as_wide_as_the_sample_says_the_run_widened_them(viewer: Viewer) -> None:
    """The run's α is 25°, but the sample records cones widened to 35° (what the contacts
    held): the cones open 35°, and ωB 25° off its normal is inside, not red."""
    n = viewer.frames
    viewer.handle({"type": "status", "status": {"params": {"alpha_deg": 25.0}}})
    viewer.handle({"type": "sample", "sample": {**SAMPLE, "alpha": 35.0}})
    await next_frame(viewer, n)
    cone_a, cone_b = viewer.nodes["/contacts/cone_A"], viewer.nodes["/contacts/cone_B"]
    r, _, h = cone_a.scale
    assert math.isclose(math.degrees(math.atan2(r, h)), 35.0)
    assert tuple(cone_b.color) == cone_color(25.0, 35.0) != RED


async def test_cones_follow_the_normals_the_message_brings(viewer: Viewer) -> None:
    """A sample that comes with its view (as from the service's side of the view's process):
    the cones stand on the normals given, nothing is worked out again."""
    tilted = Point(math.sin(0.3), math.cos(0.3))  # not this pose's pad normal: only given
    view = SampleView(
        (-20.0, 30.0, -20.0, 30.0),
        Contact(Point(-8.0, 140.0), tilted, 90.0),
        Contact(Point(74.0, 140.0), None, None),  # no normal: a point without its cone
    )
    n = viewer.frames
    viewer.handle(SampleMsg(1, object(), view))  # type: ignore[arg-type]
    await next_frame(viewer, n)
    cone_a = viewer.nodes["/contacts/cone_A"]
    assert cone_a.visible and not viewer.nodes["/contacts/cone_B"].visible
    assert viewer.nodes["/contacts/B"].visible and viewer.nodes["/contacts/AB"].visible
    axis = vtf.SO3(np.asarray(cone_a.wxyz)).as_matrix()[:, 2]
    assert np.allclose(axis, (0.0, tilted.y, tilted.z))


async def test_contacts_vanish_when_the_run_ends(viewer: Viewer) -> None:
    n = viewer.frames
    viewer.handle({"type": "sample", "sample": SAMPLE})
    viewer.handle({"type": "status", "status": {"run": {"id": 1, "state": "rolling"}}})
    await next_frame(viewer, n)
    assert viewer.nodes["/contacts/A"].visible and viewer.nodes["/contacts/cone_B"].visible
    n = viewer.frames
    viewer.handle({"type": "status", "status": {"run": {"id": 1, "state": "releasing"}}})
    await next_frame(viewer, n)
    assert not viewer.nodes["/contacts/A"].visible
    assert not viewer.nodes["/contacts/cone_B"].visible
    assert not viewer.nodes["/contacts/AB"].visible


# --- pads and object -------------------------------------------------------------------------


def test_distal_cells_sit_where_the_contact_estimate_puts_them(cfg: Settings) -> None:
    pos, rot, idx = distal_cells(cfg)
    assert len(idx) == int(cfg.tactile.distal.valid().sum()) == 70
    assert len(pos) == len(rot) == 70
    row0 = pos[0]  # row 0 at the fingertip's end: L = 49.5 (hand-model §5)
    x3, y3 = pad_point_from_L(49.5, cfg.hand.pad)
    assert math.isclose(row0[0], x3, abs_tol=0.31) and math.isclose(row0[1], y3, abs_tol=0.31)
    last = pos[-1]  # row 12 nearest the distal joint: L = 5.5, on the flat part
    assert math.isclose(last[0], 17.5 + 5.5) and math.isclose(last[1], 15.3)
    # the pad they sit on is the URDF's (tests/model/test_urdf.py: drawn along its profile)


async def test_the_bodies_are_the_urdfs_posed_like_the_frames(
    cfg: Settings, viewer: Viewer
) -> None:
    """The URDF's meshes are in the scene, and its distal link sits where the cells' frame does."""
    assert viewer.urdf is not None and len(viewer.urdf._meshes) > 3 * 3 + 1
    n = viewer.frames
    viewer.handle({"type": "pose", "angles_deg": POSE})
    await next_frame(viewer, n)
    for key, finger in (("f1", "finger1"), ("f2", "finger2"), ("f3", "thumb")):
        T = viewer.urdf._urdf.get_transform(f"{finger}_frame3", "frame0")
        for local in (np.zeros(3), np.array([40.0, 12.0, 5.0]) * MM):
            assert np.allclose(world(viewer, f"/{key}/distal", local), T[:3, :3] @ local + T[:3, 3])


async def test_pads_coloured_from_tactile_frames(cfg: Settings, viewer: Viewer) -> None:
    distal = np.zeros((13, 6))
    distal[12, 0] = 4095  # row 12, column 0: a real cell, full scale
    mats = [np.zeros((14, 6)).tolist()] * 6
    mats[cfg.axes.finger1_distal_matrix] = distal.tolist()
    n = viewer.frames
    viewer.handle({"type": "tactile", "seq": 1, "t": 0.0, "matrices": mats})
    await next_frame(viewer, n)
    colors = np.asarray(viewer.nodes["/f1/distal/cells"].batched_colors)
    assert colors.shape == (70, 3)
    assert tuple(colors[-6]) == tuple(tactile_colors(np.array([4095]))[0])
    assert tuple(colors[0]) == tuple(tactile_colors(np.array([0]))[0])
    others = np.asarray(viewer.nodes["/f2/distal/cells"].batched_colors)
    assert (others == tactile_colors(np.array([0]))[0]).all()


async def test_sim_outline(viewer: Viewer) -> None:
    outline = [[20.0 + 15 * math.cos(t), 140.0 + 20 * math.sin(t)] for t in np.linspace(0, 6, 24)]
    n = viewer.frames
    viewer.handle({"type": "sim", "truth": {"held": True, "dropped": False, "outline": outline}})
    await next_frame(viewer, n)
    node = viewer.nodes["/object/outline"]
    assert node.visible
    assert node.points.shape == (24, 2, 3)
    assert np.allclose(node.points[:, 0, 1:], np.array(outline) * MM, atol=1e-6)
    assert np.allclose(node.points[:, :, 0], 0.0)
    assert tuple(np.asarray(node.colors).reshape(-1, 3)[0]) == (255, 150, 40)  # held


async def test_a_released_object_is_not_drawn_as_dropped(viewer: Viewer) -> None:
    """The sim's truth says ``dropped`` when the fingers open at a run's end as when the object
    slips out: red only for a drop (as the dashboard tells them apart)."""
    outline = [[20.0 + 15 * math.cos(t), 140.0 + 20 * math.sin(t)] for t in np.linspace(0, 6, 24)]
    node = viewer.nodes["/object/outline"]

    async def show(run_state: str, dropped: bool, **status: Any) -> tuple[int, ...]:
        n = viewer.frames
        viewer.handle({"type": "status", "status": {"run": {"state": run_state}, **status}})
        viewer.handle({"type": "sim", "truth": {"dropped": dropped, "outline": outline}})
        await next_frame(viewer, n)
        return tuple(int(c) for c in np.asarray(node.colors).reshape(-1, 3)[0])

    held, red, grey = (255, 150, 40), (230, 40, 40), (150, 150, 150)
    assert await show("rolling", False) == held
    assert await show("releasing", True) == grey  # fell as the fingers let go
    assert await show("done", True) == grey  # and stays released
    assert await show("done", True, replay={"run_id": 1, "iteration": 5}) == red  # mid-roll
    assert await show("idle", False) == held  # placed again for the next run
    assert await show("rolling", True) == red  # slipped out mid-roll
    assert await show("done", True) == red  # still the drop it was


def _ring(rec: Any, a: tuple[float, float], b: tuple[float, float], n: int = 64) -> np.ndarray:
    """A stand-in for recognition.outline: a circle of radius size_a through A and B's middle."""
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    c = ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
    return np.column_stack([c[0] + rec.size_a * np.cos(t), c[1] + rec.size_a * np.sin(t)])


async def test_the_reconstructed_outline_is_drawn_while_a_class_is_known(
    viewer: Viewer, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(telemetry, "outline", _ring)
    monkeypatch.setattr(telemetry, "live_outline", telemetry.OutlineEvery(0.1))
    est = {"object_class": "circle", "class_confidence": 0.9, "size_a": 30.0, "rotation_est": 4.0}
    n = viewer.frames
    viewer.handle({"type": "sample", "sample": {**SAMPLE, **est}})
    await next_frame(viewer, n)
    node = viewer.nodes["/object/estimate"]
    assert node.visible and node.points.shape == (telemetry.ESTIMATE_POINTS, 2, 3)
    assert np.allclose(node.points[:, 0, 1:], _ring(SimpleNamespace(size_a=30.0), (-8.0, 140.0),
                       (74.0, 140.0), telemetry.ESTIMATE_POINTS) * MM, atol=1e-5)  # fmt: skip
    assert tuple(np.asarray(node.colors).ravel()[:3]) == viewer_module.ESTIMATE
    n = viewer.frames
    viewer.handle({"type": "sample", "sample": {**SAMPLE, **est, "object_class": None}})
    await next_frame(viewer, n)
    assert not node.visible  # no class: nothing reconstructed

    # a replayed iteration shows the outline recorded with it (its own, not the live one's)
    values: dict[str, Any] = dict.fromkeys(Sample.columns())
    values.update({**SAMPLE, **est, "size_a": 12.0, "t": 0.5, "iteration": 3})
    store = RunStore(tmp_path / "runs.db")
    run_id = store.create_run({})
    rec = RunRecorder(store.path, run_id)
    rec.sample(Sample(**values))
    rec.close()
    recorded = recorded_iteration(store, viewer.settings, run_id, 3)
    store.close()
    assert recorded is not None
    n = viewer.frames
    viewer.replay.show(recorded)
    await next_frame(viewer, n)
    assert node.visible
    radius = np.ptp(node.points[:, 0, 1]) / 2 / MM
    assert radius == pytest.approx(12.0, abs=0.2)
    viewer.replay.end()


# --- (d) GUI → on_command --------------------------------------------------------------------


async def _show(viewer: Viewer, status: dict[str, Any]) -> None:
    """The panel redrawn for ``status``."""
    n = viewer.frames
    viewer.handle({"type": "status", "status": status})
    await next_frame(viewer, n)


async def test_buttons_and_sliders_reach_on_command(viewer: Viewer, commands: Recorder) -> None:
    for kind, status in (("start", IDLE), ("stop", ROLLING), ("open", IDLE), ("estop", IDLE),
                         ("release", {**IDLE, "estopped": True})):  # fmt: skip
        await _show(viewer, status)  # each when it may be sent
        await click(viewer.buttons[kind])
    slider = viewer.sliders["k"]
    slider._impl.value = 3.5  # what viser does with a client's update, then the callbacks
    await click(slider)
    await wait_for(lambda: len(commands.calls) == 6)
    assert commands.calls == [
        ("start", {}), ("stop", {}), ("open", {}), ("estop", {}), ("release", {}),
        ("params", {"k": 3.5}),
    ]  # fmt: skip
    assert set(commands.loops) == {asyncio.get_running_loop()}  # awaited on the service's loop


async def test_a_dragged_slider_sends_its_value_once(viewer: Viewer, commands: Recorder) -> None:
    """viser's client reports every step of a drag; the view sends the value it rests at, once
    (each one sent was logged and, in a run, applied and recorded as an event)."""
    slider = viewer.sliders["alpha_deg"]
    for value in (22.5, 23.0, 23.5, 24.0, 30.0):  # one drag: the steps, all on this loop's turn
        slider._impl.value = value
        for cb in list(slider._impl.update_cb):
            cb(GuiEvent(client=None, client_id=None, target=slider))
    await wait_for(lambda: len(commands.calls) == 1 and not viewer._settling)
    assert commands.calls == [("params", {"alpha_deg": 30.0})]


async def test_sliders_follow_status_without_echo(viewer: Viewer, commands: Recorder) -> None:
    assert viewer.sliders["lambda_gain"].value == viewer.settings.rolling.lambda_gain
    n = viewer.frames
    params = {"delta_phi_deg": -0.5, "k": 4.0, "lambda_gain": 3.0, "alpha_deg": 20.0}
    viewer.handle({"type": "status", "status": {"params": params, "run": None}})
    await next_frame(viewer, n)
    assert {f: s.value for f, s in viewer.sliders.items()} == params
    await asyncio.sleep(0.05)
    assert commands.calls == []  # following the service is not a user's change


async def test_refused_command_shows_in_the_panel(cfg: Settings) -> None:
    v = Viewer(cfg, port=0, on_command=Recorder(refuse=True))
    await v.start()
    try:
        async with watching(v):
            await _show(v, ROLLING)
            await click(v.buttons["stop"])
            await wait_for(lambda: "already running" in v.nodes["gui/state"].content)
    finally:
        await v.stop()


# --- (f) authority: read-only with a token, every control checked server-side -------------------

IDLE = {"auth_required": False, "estopped": False, "run": None, "hand": {"opening": False}}
ROLLING = {**IDLE, "run": {"id": 1, "state": "rolling"}}


def enabled(v: Viewer) -> set[str]:
    """The controls the panel shows enabled (buttons by kind, sliders by field)."""
    controls = {**v.buttons, **v.sliders}
    return {name for name, handle in controls.items() if not handle.disabled}


async def test_read_only_view_only_stops(cfg: Settings) -> None:
    """With a token every control but E-STOP is disabled with a hint, and a click on one that
    arrives anyway — over viser's websocket, as a hostile page's script sends it — is refused by
    our callback: nothing reaches on_command, the panel says why. E-STOP works."""
    commands = Recorder()
    v = Viewer(cfg, port=0, on_command=commands, read_only=True)
    await v.start()
    try:
        assert enabled(v) == {"estop"}
        assert v.buttons["start"].hint == v.sliders["k"].hint == NEEDS_TOKEN
        async with browser(v.url) as b:
            await wait_for(lambda: v.watched)
            n = v.frames
            v.handle({"type": "status", "status": IDLE})  # a status cannot enable them
            await next_frame(v, n)
            assert enabled(v) == {"estop"}
            # said in the panel: viser shows no hint on a disabled control
            assert READ_ONLY_NOTE in v.nodes["gui/state"].content
            note = lambda: v.nodes["gui/state"].content  # noqa: E731
            for kind in ("start", "stop", "open", "release"):
                await b.send_gui(v.buttons[kind]._impl.uuid, True)
                await wait_for(lambda k=kind: f"{k}: {NEEDS_TOKEN}" in note())
            # a hostile update may also overwrite the handle's state: still refused
            await b.send_gui(v.buttons["start"]._impl.uuid, True, props={"disabled": False})
            await wait_for(lambda: f"start: {NEEDS_TOKEN}" in note())
            await b.send_gui(v.sliders["k"]._impl.uuid, 3.5)
            await wait_for(lambda: f"params: {NEEDS_TOKEN}" in note())
            await wait_for(lambda: v.sliders["k"].value == cfg.rolling.k)  # put back
            assert commands.calls == []
            await b.send_gui(v.buttons["estop"]._impl.uuid, True)
            await wait_for(lambda: len(commands.calls) == 1)
            assert commands.calls == [("estop", {})]
    finally:
        await v.stop()


async def test_controls_follow_token_estop_and_run(viewer: Viewer, commands: Recorder) -> None:
    """As on the dashboard: Grasp & roll and Open hand only with no run, no e-stop latched, no
    opening and a known status; Stop only with a run or an opening to stop; Release only with
    the e-stop latched; a token reported by the status disables all but E-STOP; every state
    change redraws the panel, and a click on a control disabled at that moment is refused, not
    sent."""
    sliders = set(viewer.sliders)
    assert enabled(viewer) == {"estop", *sliders}  # no status yet: the others wait for one
    assert viewer.buttons["open"].hint == "waiting for the service's status"
    rest = {"estop", *sliders}
    states = [
        (IDLE, rest | {"start", "open"}, None),
        ({**IDLE, "estopped": True}, rest | {"release"}, "the e-stop is latched"),
        (ROLLING, rest | {"stop"}, "a run is running"),
        ({**IDLE, "run": {"id": 2, "state": "idle"}}, rest | {"stop"}, "a run is running"),
        ({**IDLE, "hand": {"opening": True}}, rest | {"stop"}, "the hand is opening"),
        ({**IDLE, "run": {"id": 1, "state": "done"}}, rest | {"start", "open"}, None),
        ({**IDLE, "auth_required": True}, {"estop"}, NEEDS_TOKEN),
        (IDLE, rest | {"start", "open"}, None),
    ]
    async with browser(viewer.url) as b:
        await wait_for(lambda: viewer.watched)
        for status, want, why in states:
            n = viewer.frames
            viewer.handle({"type": "status", "status": status})
            await next_frame(viewer, n)
            assert enabled(viewer) == want, status
            for kind in ("open", "start"):
                hint = viewer.buttons[kind].hint
                assert (why is None and hint == BUTTONS[kind][2]) or (why and why in hint), hint
            if why is not None:
                await b.send_gui(viewer.buttons["open"]._impl.uuid, True)
                await wait_for(lambda w=why: f"open: {w}" in viewer.nodes["gui/state"].content)
        await b.send_gui(viewer.buttons["release"]._impl.uuid, True)  # nothing latched
        await wait_for(
            lambda: "release: the e-stop is not latched" in viewer.nodes["gui/state"].content
        )
        assert commands.calls == []
        await b.send_gui(viewer.buttons["open"]._impl.uuid, True)
        await wait_for(lambda: commands.calls == [("open", {})])
        # the refusal shown goes after NOTE_S, not left for the next visitor
        assert "release:" in viewer.nodes["gui/state"].content
        viewer._note_at -= viewer_module.NOTE_S
        n = viewer.frames
        viewer.handle({"type": "status", "status": IDLE})
        await next_frame(viewer, n)
        assert "release:" not in viewer.nodes["gui/state"].content


async def test_websocket_refuses_other_sites(cfg: Settings) -> None:
    """In the service's process too (service.viewer_process = false): a page of another site
    cannot open the view's websocket (403); the view's own, a script's (no Origin) can."""
    v = Viewer(cfg, port=0)
    await v.start()
    try:
        port = int(v.url.rsplit(":", 1)[1])
        for origin in ("http://evil.example", f"http://evil.example:{port}"):
            with pytest.raises(InvalidStatus) as refused:
                async with connect(ws_url(v.url), subprotocols=PROTOCOL, origin=Origin(origin)):
                    pass
            assert refused.value.response.status_code == 403
        for origin in (f"http://localhost:{port}", f"http://127.0.0.1:{port}", None):
            async with browser(v.url, origin=origin):
                await wait_for(lambda: v.watched)
            await wait_for(lambda: not v.watched)
        # …nor frame the view's page, where a click it lured would pass that check
        page = await asyncio.to_thread(urllib.request.urlopen, v.url, timeout=10)
        with page:
            policy = page.headers["Content-Security-Policy"]
        assert policy == f"frame-ancestors {viewer_module.frame_ancestors(cfg)}", policy
    finally:
        await v.stop()


def test_origin_policy(cfg: Settings) -> None:
    """Loopback, service.host and service.allowed_hosts at the view's or the dashboard's port,
    plus service.allowed_origins; nothing else."""
    svc = cfg.service.model_copy(update={
        "host": "192.168.1.42", "port": 8000, "allowed_hosts": ("Lab-PC.local",),
        "allowed_origins": ("https://ops.example:9443",),
    })  # fmt: skip
    s = cfg.model_copy(update={"service": svc})
    for origin in (
        "http://127.0.0.1:8080", "http://localhost:8080", "http://[::1]:8080",
        "https://localhost:8080", "http://127.0.0.1:8000", "http://192.168.1.42:8080",
        "http://lab-pc.local:8080", "http://LAB-PC.local:8000", "https://ops.example:9443",
    ):  # fmt: skip
        assert origin_allowed(origin, s, 8080), origin
    for origin in (
        "http://evil.example:8080", "http://127.0.0.1:9999", "http://localhost", "null", "",
        "file://", "http://127.0.0.1:8080/path", "http://user@localhost:8080",
        "https://ops.example", "ws://localhost:8080", "http://localhost:bad",
    ):  # fmt: skip
        assert not origin_allowed(origin, s, 8080), origin
    assert origin_allowed("http://localhost", s, 80)  # the scheme's default port
    unknown = cfg.model_copy(update={"service": svc.model_copy(update={"port": 0})})
    assert not origin_allowed("http://localhost:0", unknown, 8080)
    # the pages that may frame the view: itself, the dashboard (any port while unknown)
    pages = viewer_module.frame_ancestors(s).split()
    assert pages[0] == "'self'" and "https://ops.example:9443" in pages
    for page in ("http://127.0.0.1:8000", "https://localhost:8000", "http://lab-pc.local:8000",
                 "http://192.168.1.42:8000"):  # fmt: skip
        assert page in pages, pages
    assert not any("evil" in p or "::1" in p or ":8080" in p for p in pages), pages
    assert "http://127.0.0.1:*" in viewer_module.frame_ancestors(unknown).split()


def test_an_allowed_host_with_a_port_is_a_page_at_that_port(cfg: Settings) -> None:
    """``allowed_hosts = ["proxy:8443"]`` lets the guard answer the dashboard at proxy:8443;
    the view refused that page's handshake and framing (it compared "proxy:8443" as a name)."""
    svc = cfg.service.model_copy(update={"port": 8000, "allowed_hosts": ("Proxy:8443",)})
    s = cfg.model_copy(update={"service": svc})
    assert origin_allowed("http://proxy:8443", s, 8080)
    assert origin_allowed("https://PROXY:8443", s, 8080)
    for origin in ("http://proxy:8080", "http://proxy:8000", "http://proxy"):
        assert not origin_allowed(origin, s, 8080), origin
    pages = viewer_module.frame_ancestors(s).split()
    assert "http://proxy:8443" in pages and "http://proxy:8000" not in pages, pages


async def test_unguarded_viser_is_not_served(monkeypatch: pytest.MonkeyPatch) -> None:
    """Should viser serve its websocket otherwise than 1.1.1 does, the Origin check would not be
    installed: the view refuses to start rather than serve unguarded."""

    def as_is(self: Any, handler: Any, *args: Any, **kwargs: Any) -> None:
        super(viewer_module._GuardedServe, self).__init__(handler, *args, **kwargs)

    monkeypatch.setattr(viewer_module._GuardedServe, "__init__", as_is)
    with pytest.raises(ViewerSecurityError, match="Origin check"):
        await asyncio.to_thread(start_viser, "127.0.0.1", 0, lambda _o, _p: True)
    assert websockets.asyncio.server.serve is not viewer_module._GuardedServe  # restored


@pytest.mark.parametrize("token", ["", "s3cret"])
async def test_the_view_binds_loopback_without_a_token(
    cfg: Settings, monkeypatch: pytest.MonkeyPatch, token: str
) -> None:
    """No token: the view listens on loopback, whatever service.host says; with one it listens
    where the service does, read-only."""
    made: list[dict[str, Any]] = []

    class Made:
        url = "http://example:1"

        def __init__(self, _cfg: Settings, **kwargs: Any) -> None:
            made.append(kwargs)

        async def start(self) -> None:
            pass

        def handle(self, _msg: dict[str, Any]) -> None:
            pass

    svc = cfg.service.model_copy(update={"host": "0.0.0.0", "token": token})
    for process in (True, False):
        s = cfg.model_copy(update={"service": svc.model_copy(update={"viewer_process": process})})
        monkeypatch.setattr(viewer_module, "Viewer", Made)
        monkeypatch.setattr(viewer_proc, "ViewerProcess", Made)
        station = SimpleNamespace(command=Recorder())
        hub = SimpleNamespace(add_listener=lambda _fn: None)
        await _start_viewer(s, station, hub)  # type: ignore[arg-type]
    want = ("0.0.0.0", True) if token else ("127.0.0.1", False)
    assert [(m["host"], m["read_only"]) for m in made] == [want, want]


# --- (e) handle() only stores; rendering is rate-limited and on change only ------------------


async def test_handle_only_stores(cfg: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    v = Viewer(cfg, port=0, max_hz=10.0)
    await v.start()
    try:
        async with watching(v):
            await _rate_limited(v, monkeypatch)
    finally:
        await v.stop()


async def _rate_limited(v: Viewer, monkeypatch: pytest.MonkeyPatch) -> None:
    """5000 messages make one frame; a steady feed at most max_hz; no change, no frame. Every
    wait is for an event, so a loaded machine only makes the test slower: handle() draws
    nothing (the frames come from the render task), and frames keep max_hz on average, two
    never closer than MIN_GAP periods, however late either came (pacing.paced)."""
    await next_frame(v, 0)  # the initial frame
    renders: list[float] = []
    real = v.render
    monkeypatch.setattr(v, "render", lambda: (renders.append(time.monotonic()), real()))
    before = np.array(v.nodes["/f1/distal"].position)
    msgs = [{"type": "sample", "sample": {**SAMPLE, "phi2": -20 + i * 1e-3}} for i in range(5000)]
    for m in msgs:
        v.handle(m)
    assert renders == [] and np.array_equal(v.nodes["/f1/distal"].position, before)
    assert v._latest["sample"] is msgs[-1]["sample"]  # the latest, stored as is

    await wait_for(lambda: len(renders) == 1)  # 5000 messages → one frame
    # fed for 0.5 s at 200 Hz: at most 10 frames a second
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        v.handle(msgs[0])
        await asyncio.sleep(0.005)
    await wait_for(lambda: not v._dirty)  # the last change drawn
    gaps, hz = np.diff(renders), 10.0
    assert len(renders) >= 2 and gaps.min() >= MIN_GAP / hz - 1e-3  # the feed was drawn
    assert len(renders) - 1 <= (renders[-1] - renders[0]) * hz + BURST  # at most max_hz
    idle = len(renders)
    await asyncio.sleep(0.3)
    assert len(renders) == idle  # nothing changed: nothing drawn


async def test_draws_only_while_watched(cfg: Settings) -> None:
    """Nobody watching: messages are kept, nothing is drawn; a browser that connects is drawn
    the latest state at once."""
    v = Viewer(cfg, port=0)
    await v.start()
    try:
        v.handle({"type": "pose", "angles_deg": [90.0, 0.0, 0.0, -90.0, 0.0, 0.0, 0.0]})
        v.handle({"type": "sample", "sample": SAMPLE})
        await asyncio.sleep(0.2)
        assert v.frames == 0 and not v.watched
        async with watching(v):
            assert v.frames == 1
            assert v.nodes["/contacts/A"].visible
            got = world(v, "/f1/distal", np.zeros(3))
            C = pad_point(Finger.ONE, math.radians(-20), math.radians(30), 0.0, 0.0, cfg.hand)
            assert np.allclose(got[1:], np.array([C.y, C.z]) * MM, atol=1e-6)
    finally:
        await v.stop()


async def test_unknown_and_malformed_messages_are_harmless(viewer: Viewer) -> None:
    n = viewer.frames
    viewer.handle({"type": "event", "kind": "reversal"})
    viewer.handle({"type": "dropped", "count": 3})
    assert viewer._dirty == set()
    viewer.handle({"type": "tactile", "matrices": [[[1, 2]]]})  # wrong shape: kept as it was
    viewer.handle({"type": "sample", "sample": {"Ay": None, "phi2": None}})
    viewer.handle({"type": "sim", "truth": {"outline": []}})
    await next_frame(viewer, n)
    assert not viewer.nodes["/contacts/A"].visible
    assert not viewer.nodes["/object/outline"].visible
    # a ragged tactile frame spoils its own part of the frame only: the pose still lands
    n = viewer.frames
    viewer.handle({"type": "tactile", "matrices": [[[1, 2], [3]]] * 6})
    viewer.handle({"type": "pose", "angles_deg": [90.0, 0.0, 0.0, -90.0, 0.0, 0.0, 0.0]})
    await next_frame(viewer, n)
    assert np.allclose(viewer.nodes["/f1/distal"].position, (0.0, 0.0, 86.5 * MM))


# --- following the dashboard's replay ----------------------------------------------------------


async def test_a_replayed_iteration_reaches_the_view_then_live_again(
    cfg: Settings, viewer: Viewer, tmp_path: Path
) -> None:
    # one recorded iteration: Finger 1 straight, one full-scale cell on its distal pad
    values: dict[str, Any] = dict.fromkeys(Sample.columns())
    values.update({**SAMPLE, "phi2": 0.0, "phi3": 0.0, "t": 0.5, "iteration": 3})
    store = RunStore(tmp_path / "runs.db")
    run_id = store.create_run({})
    rec = RunRecorder(store.path, run_id)
    rec.sample(Sample(**values))
    mats = [np.zeros(shape, dtype=np.uint16) for shape in matrix_shapes(cfg.tactile, cfg.axes)]
    mats[cfg.axes.finger1_distal_matrix][12, 0] = 4095
    rec.frame(0.5, 3, 0, np.concatenate([m.ravel() for m in mats]))
    rec.close()
    recorded = recorded_iteration(store, cfg, run_id, 3)
    assert recorded is not None

    x3 = cfg.hand.pad.tip_end_x3_mm
    tip_local = np.array([x3, pad_y3(x3, cfg.hand.pad), 0.0]) * MM
    straight = np.array([0.0, tip_local[1] / MM, 86.5 + x3]) * MM
    status = {"type": "status", "status": {"run": None, "estopped": False}}
    n = viewer.frames
    viewer.handle({"type": "pose", "angles_deg": POSE})
    viewer.handle({"type": "sample", "run_id": 1, "sample": SAMPLE})
    viewer.handle(status)
    await next_frame(viewer, n)
    live_tip = world(viewer, "/f1/distal", tip_local)
    assert not np.allclose(live_tip, straight, atol=1e-6)

    n = viewer.frames
    viewer.replay.show(recorded)
    await next_frame(viewer, n)
    assert np.allclose(world(viewer, "/f1/distal", tip_local), straight, atol=1e-9)
    colors = np.asarray(viewer.nodes["/f1/distal/cells"].batched_colors)
    assert tuple(colors[-6]) == tuple(tactile_colors(np.array([4095]))[0])
    assert viewer.nodes["/contacts/A"].visible  # a replay's contacts stay, whatever the run
    state = viewer.nodes["gui/state"].content
    # the replay first; the hand's own state beside it says it is live (not the iteration's)
    assert state.startswith(f"replay of run {run_id}, it 3 · live: **idle**"), state

    # live telemetry meanwhile does not move the replayed hand
    n = viewer.frames
    viewer.handle({"type": "sample", "run_id": 1, "sample": {**SAMPLE, "phi2": -10.0}})
    viewer.handle(status)
    await next_frame(viewer, n)
    assert np.allclose(world(viewer, "/f1/distal", tip_local), straight, atol=1e-9)

    # live again: the latest live sample (φ2 = −10°) and pads, no replay in the panel
    n = viewer.frames
    viewer.replay.end()
    await next_frame(viewer, n)
    tip = world(viewer, "/f1/distal", tip_local)
    assert not np.allclose(tip, straight, atol=1e-6) and not np.allclose(tip, live_tip, atol=1e-6)
    assert "replay" not in viewer.nodes["gui/state"].content
    store.close()


def _recorded_sample(cfg: Settings, tmp_path: Path, meta: dict[str, Any]) -> Recorded:
    """Iteration 3 of a run recorded with ``meta`` (one sample: SAMPLE's), as a replay gets it."""
    values: dict[str, Any] = dict.fromkeys(Sample.columns())
    values.update({**SAMPLE, "t": 0.5, "iteration": 3})
    store = RunStore(tmp_path / "runs.db")
    try:
        run_id = store.create_run(meta)
        rec = RunRecorder(store.path, run_id)
        rec.sample(Sample(**values))
        rec.close()
        recorded = recorded_iteration(store, cfg, run_id, 3)
    finally:
        store.close()
    assert recorded is not None
    return recorded


async def _replay_on_a_hand_at_rest(viewer: Viewer, recorded: Recorded) -> None:
    """A fresh service's view (the hand at rest, φ1 = 0; no run yet) shows ``recorded``."""
    n = viewer.frames
    viewer.handle({"type": "pose", "angles_deg": [0.0, 0.0, 0.0, -90.0, 0.0, 0.0, 0.0]})
    viewer.handle({"type": "status", "status": {"run": None, "estopped": False}})
    await next_frame(viewer, n)
    n = viewer.frames
    viewer.replay.show(recorded)
    await next_frame(viewer, n)


async def test_a_replay_poses_phi1_and_the_thumb_as_the_run_held_them(
    cfg: Settings, viewer: Viewer, tmp_path: Path
) -> None:
    """A sample carries φ2…φ5 only. The live hand at rest (a fresh service: φ1 = 0) must not
    turn the replayed fingers out of the y0z0 plane, where the contacts and cones are drawn:
    φ1 and the thumb are the recorded pre-shape's."""
    recorded = _recorded_sample(cfg, tmp_path, {"configuration": cfg.recorded()})
    await _replay_on_a_hand_at_rest(viewer, recorded)

    x3 = cfg.hand.pad.tip_end_x3_mm
    tip_local = np.array([x3, pad_y3(x3, cfg.hand.pad), 0.0]) * MM
    expected = finger_frames(POSE, cfg)  # SAMPLE's φ2…φ5 at the pre-shape's φ1 = 90°
    for f in ("f1", "f2"):
        tip = world(viewer, f"/{f}/distal", tip_local)
        want = (expected[f"/{f}/distal"] @ np.append(tip_local / MM, 1.0))[:3] * MM
        assert abs(tip[0]) < 1e-9  # in the y0z0 plane, with the contacts
        assert np.allclose(tip, want, atol=1e-9)
    assert viewer.nodes["/contacts/A"].position[0] == 0.0


async def test_a_replay_leaves_nothing_behind_on_a_service_without_runs(
    cfg: Settings, viewer: Viewer, tmp_path: Path
) -> None:
    """A fresh service (no run yet, so no live sample to put back): once the replay ends, its
    contacts, cones, AB and reconstructed outline go."""
    recorded = _recorded_sample(cfg, tmp_path, {})
    parts = ("/contacts/A", "/contacts/B", "/contacts/cone_A", "/contacts/AB")
    await _replay_on_a_hand_at_rest(viewer, recorded)
    assert all(viewer.nodes[p].visible for p in parts)
    n = viewer.frames
    viewer.replay.end()
    await next_frame(viewer, n)
    assert not any(viewer.nodes[p].visible for p in parts)
    assert "replay" not in viewer.nodes["gui/state"].content


async def test_the_view_offers_no_share_button(
    cfg: Settings, commands: Recorder, monkeypatch: pytest.MonkeyPatch
) -> None:
    """viser's "Share" asks its public tunnel for an internet URL to this view: not on a lab PC
    next to a hand (and nothing here reaches the internet)."""
    from viser._gui_api import GuiApi

    themes: list[dict[str, Any]] = []
    configure = GuiApi.configure_theme

    def spy(self: GuiApi, **kw: Any) -> None:
        themes.append(kw)
        configure(self, **kw)

    monkeypatch.setattr(GuiApi, "configure_theme", spy)
    v = Viewer(cfg, port=0, on_command=commands)
    await v.start()
    try:
        assert themes and all(t.get("show_share_button") is False for t in themes), themes
    finally:
        await v.stop()
