"""A recorded run as a Foxglove-native MCAP file: what each channel carries and how it is built.

Channels (log times: the run's start plus each record's own time ``t``):

* ``/samples`` — one JSON message per iteration; its JSON schema is generated from
  :class:`~sdh2svc.control.sample.Sample`'s fields, with units in the descriptions.
* ``/tf`` — ``foxglove.FrameTransforms`` of the URDF's joints from each sample's φ2…φ5 (φ1 and the
  thumb at the run's pre-shape, where a run holds them).
* ``/scene`` — ``foxglove.SceneUpdate``: the hand's links as the URDF draws them
  (``links/<link>``: boxes, and the palm's cylinder, in each link's frame, following ``/tf``: the
  hand shows without a URDF layer), the six pads as boxes in their URDF frames (``pads/<pad>``),
  and in ``frame0`` the contact points A, B, the segment AB and the friction cones of half-angle
  α about each pad's normal, and the object as the recognition reconstructed it, a closed blue
  line, once it has a class (``contacts``); in simulation the object's true outline too
  (``object``: live from the ``sim`` messages, in a file from the truth recorded with each
  iteration), red once it has dropped.
* ``/tactile/<finger>_<proximal|distal>`` — each pad as ``foxglove.Grid`` (raw counts, uint16) in
  its URDF frame, cells of the texel pitch.
* ``/events`` — ``foxglove.Log``, one per run event.

Metadata records ``run``, ``parameters``, ``object`` and ``configuration``; the URDF attached as
``sdh2.urdf``. The Foxglove messages are the SDK's (``foxglove-sdk``: the official protobuf
schemas and encoders); the file is written with ``mcap``'s writer (any binary stream will do).
"""

from __future__ import annotations

import functools
import json
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import IO, Any

import numpy as np
from foxglove import messages as fm
from mcap.writer import Writer

from sdh2svc.config import Settings
from sdh2svc.control.observer import EventKind
from sdh2svc.control.sample import Sample
from sdh2svc.model.geometry import pad_slope
from sdh2svc.model.urdf import (
    FINGERS,
    MATERIALS,
    PADS,
    HandDescription,
    Visual,
    describe,
    joint_transforms,
    pad_matrix,
    quat_from_rpy,
    to_xml,
)
from sdh2svc.service.telemetry import (
    ESTIMATE_PERIOD_S,
    OutlineEvery,
    estimate_outline,
    recorded_truth,
)

Json = dict[str, Any]
_MM = 1e-3
ESTIMATE_RGBA = (0.15, 0.75, 0.92, 1.0)  # the reconstructed outline (the 3-D view's colour)
PAD_BOX_MM = 1.5  # the pads' boxes' thickness (display: under the Grid, which lies at z = 0)

SAMPLE_SCHEMA = "sdh2svc.Sample"  # the /samples channel's schema name
_JSON_TYPES = {int: "integer", float: "number", str: "string", bool: "boolean"}


COLUMNS = Sample.columns()

# The channels, the same in a file and live (foxglove_live.py).
SAMPLES, TF, SCENE, EVENTS = "/samples", "/tf", "/scene", "/events"
PAD_NAMES = tuple(f"{f}_{p}" for f in FINGERS for p in PADS)
#: The joints of the URDF, by AxisMap's names.
JOINTS = ("phi1", "phi2", "phi3", "phi4", "phi5", "thumb_proximal", "thumb_distal")


def pad_topic(pad: str) -> str:
    return f"/tactile/{pad}"


def sample_json(s: Mapping[str, Any]) -> bytes:
    """A ``/samples`` message: the sample's columns that have a value (a non-finite number has
    none): Foxglove's plots take a missing field as a gap."""
    row = {k: v for k in COLUMNS if (v := _finite(s[k])) is not None}
    return json.dumps(row, allow_nan=False).encode()


def sample_schema() -> Json:
    """The JSON schema of ``/samples``, from :class:`Sample`'s fields and their types: one type
    each (Foxglove's reader of JSON schemas takes no list of types, and refused the whole
    channel for a ``["number", "null"]``); a field that may have no value is not required."""
    hints = typing.get_type_hints(Sample)
    docs = Sample.descriptions()
    props: Json = {}
    required = []
    for f in fields(Sample):
        tp = hints[f.name]
        args = typing.get_args(tp) if isinstance(tp, types.UnionType) else (tp,)
        kinds = [_JSON_TYPES[a] for a in args if a is not type(None)]
        assert len(kinds) == 1, f"{f.name}: one JSON type, not {kinds}"
        props[f.name] = {"type": kinds[0], "description": docs[f.name]}
        if type(None) not in args:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SAMPLE_SCHEMA,
        "description": "One rolling iteration (control/sample.py); frame 0 as in hand-model.md §2",
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def clear_contacts(ns: int) -> fm.SceneUpdate:
    """The scene's contacts (A, B, AB, the cones) taken away: a run has ended."""
    deletion = fm.SceneEntityDeletion(
        timestamp=_ts(ns), type=fm.SceneEntityDeletionType.MatchingId, id="contacts"
    )
    return fm.SceneUpdate(deletions=[deletion])


def _finite(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _ts(ns: int) -> fm.Timestamp:
    return fm.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _v3(x: float, y: float, z: float) -> fm.Vector3:
    return fm.Vector3(x=x, y=y, z=z)


def _rgba(r: float, g: float, b: float, a: float) -> fm.Color:
    return fm.Color(r=r, g=g, b=b, a=a)


@dataclass(frozen=True, slots=True)
class HandFrames:
    """What a run's recording needs of the configuration, gathered once."""

    cfg: Settings
    desc: HandDescription
    held: Mapping[str, float]  # the joints a sample does not carry (φ1, thumb), rad
    # a sample's reconstructed outline (telemetry.estimate_outline, or one made less often)
    estimate: Callable[[Mapping[str, Any]], np.ndarray] = estimate_outline

    @classmethod
    def of(
        cls, cfg: Settings, estimate: Callable[[Mapping[str, Any]], np.ndarray] = estimate_outline
    ) -> HandFrames:
        desc = describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
        pre = cfg.run.preshape_deg
        ax = cfg.axes
        held = {
            "phi1": pre[ax.phi1],
            "thumb_proximal": pre[ax.thumb_proximal],
            "thumb_distal": pre[ax.thumb_distal],
        }
        return cls(cfg, desc, {k: math.radians(v) for k, v in held.items()}, estimate)

    def transforms(self, s: Mapping[str, Any], ns: int) -> fm.FrameTransforms:
        """The links at a sample's φ2…φ5 (the other joints held)."""
        angles = {**self.held, **{k: math.radians(s[k]) for k in ("phi2", "phi3", "phi4", "phi5")}}
        return self.joint_frames(angles, ns)

    def pose_transforms(self, angles_deg: Sequence[float], ns: int) -> fm.FrameTransforms:
        """The links at the hand's actual angles (degrees, one per wire axis)."""
        ax = self.cfg.axes
        return self.joint_frames({n: math.radians(angles_deg[getattr(ax, n)]) for n in JOINTS}, ns)

    def joint_frames(self, angles: Mapping[str, float], ns: int) -> fm.FrameTransforms:
        """The URDF's joint transforms at ``angles`` (rad, by AxisMap's joint names)."""
        ts = _ts(ns)
        return fm.FrameTransforms(
            transforms=[
                fm.FrameTransform(
                    timestamp=ts,
                    parent_frame_id=t.parent,
                    child_frame_id=t.child,
                    translation=_v3(*t.translation),
                    rotation=fm.Quaternion(
                        x=t.rotation[0], y=t.rotation[1], z=t.rotation[2], w=t.rotation[3]
                    ),
                )
                for t in joint_transforms(self.desc, angles)
            ]
        )

    def scene(
        self,
        s: Mapping[str, Any] | None,
        ns: int,
        alpha: float,
        truth: Mapping[str, Any] | None = None,
    ) -> fm.SceneUpdate:
        """The pads, and a sample's contacts (``s``), and the simulation's object (``truth``: a
        ``sim`` message's, :meth:`sdh2svc.sim.hand.Truth.scene`); what is not given is left as
        it was drawn."""
        entities = [*self.links(ns), *self.pads(ns)]
        if s is not None:
            entities.append(self.contacts(s, ns, sample_alpha(s, alpha)))
        if truth is not None and (obj := object_entity(truth, ns)) is not None:
            entities.append(obj)
        return fm.SceneUpdate(entities=entities)

    def links(self, ns: int) -> list[fm.SceneEntity]:
        """The hand's links as the URDF's visuals draw them, each in its link's frame (it follows
        ``/tf``); the pads are :meth:`pads`, under their grids."""
        ts = _ts(ns)
        return [
            fm.SceneEntity(
                timestamp=ts,
                frame_id=link,
                id=f"links/{link}",
                frame_locked=True,
                cubes=list(cubes),
                cylinders=list(cylinders),
            )
            for link, cubes, cylinders in _link_shells(self.desc)
        ]

    def pads(self, ns: int) -> list[fm.SceneEntity]:
        """Each tactile matrix as a box under its Grid, in the pad's frame (it follows ``/tf``)."""
        tac, ts = self.cfg.tactile, _ts(ns)
        pitch, t = tac.texel_pitch_mm * _MM, PAD_BOX_MM * _MM
        out = []
        for finger in FINGERS:
            for part in PADS:
                lay = tac.proximal if part == "proximal" else tac.distal
                w, h = lay.cols * pitch, lay.rows * pitch
                cube = fm.CubePrimitive(
                    pose=_pose(np.array([w / 2, h / 2, -t / 2])),
                    size=_v3(w, h, t),
                    color=_rgba(0.15, 0.15, 0.15, 1.0),
                )
                out.append(
                    fm.SceneEntity(
                        timestamp=ts,
                        frame_id=f"{finger}_{part}_pad",
                        id=f"pads/{finger}_{part}",
                        frame_locked=True,
                        cubes=[cube],
                    )
                )
        return out

    def contacts(self, s: Mapping[str, Any], ns: int, alpha: float) -> fm.SceneEntity:
        """A, B, the segment AB, the friction cones and the reconstructed outline
        (:attr:`estimate`), in frame 0 (metres)."""
        spheres, lines, cones = [], [], []
        pts = {}
        for name, finger, (py, pz), (cy, cz), psi in (
            ("A", 1, ("Ay", "Az"), ("Cy", "Cz"), ("phi2", "phi3")),
            ("B", 2, ("By", "Bz"), ("Dy", "Dz"), ("phi4", "phi5")),
        ):
            if s[py] is None or s[cy] is None:
                continue
            p = np.array([0.0, s[py], s[pz]]) * _MM
            pts[name] = p
            n = self._normal(
                finger, (s[py] - s[cy], s[pz] - s[cz]), math.radians(s[psi[0]] + s[psi[1]])
            )
            d = 6.0 * _MM  # the contact marker's diameter
            spheres.append(
                fm.SpherePrimitive(
                    pose=_pose(p), size=_v3(d, d, d), color=_rgba(0.9, 0.2, 0.2, 1.0)
                )
            )
            cones.append(_cone(p, n, alpha, 25.0 * _MM))
        if len(pts) == 2:
            lines.append(
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineStrip,
                    thickness=1.0 * _MM,
                    points=[
                        fm.Point3(x=float(q[0]), y=float(q[1]), z=float(q[2]))
                        for q in (pts["A"], pts["B"])
                    ],
                    color=_rgba(1.0, 0.8, 0.1, 1.0),
                )
            )
        est = self.estimate(s)
        if len(est) >= 2:
            lines.append(
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineLoop,
                    thickness=1.2 * _MM,
                    points=[fm.Point3(x=0.0, y=y * _MM, z=z * _MM) for y, z in est.tolist()],
                    color=_rgba(*ESTIMATE_RGBA),
                )
            )
        return fm.SceneEntity(
            timestamp=_ts(ns),
            frame_id="frame0",
            id="contacts",
            spheres=spheres,
            lines=lines,
            cylinders=cones,
        )

    def _normal(self, finger: int, ca: tuple[float, float], psi: float) -> np.ndarray:
        """The pad's outward normal (frame 0: x, y, z) at the contact C→A = ``ca`` (mm)."""
        s, c = math.sin(psi), math.cos(psi)
        ex, ey = ((s, c), (c, -s)) if finger == 1 else ((-s, c), (-c, -s))
        x3 = ca[0] * ex[0] + ca[1] * ex[1]
        k = pad_slope(x3, self.cfg.hand.pad)
        ny, nz = -k * ex[0] + ey[0], -k * ex[1] + ey[1]
        norm = math.hypot(ny, nz)
        return np.array([0.0, ny / norm, nz / norm])

    def grids(self, texels: np.ndarray, ns: int) -> dict[str, fm.Grid]:
        """Each pad's matrix of one flat frame (matrices in index order) as a Grid."""
        tac, mats, start = self.cfg.tactile, [], 0
        counts = np.asarray(texels)
        for _finger, part in self._by_matrix():
            lay = tac.proximal if part == "proximal" else tac.distal
            n = lay.rows * lay.cols
            mats.append(counts[start : start + n].reshape(lay.rows, lay.cols))
            start += n
        return self.pad_grids(mats, ns)

    def pad_grids(self, matrices: Sequence[np.ndarray], ns: int) -> dict[str, fm.Grid]:
        """Each pad's matrix (rows × columns of raw counts, in matrix index order) as a Grid in
        its URDF frame, keyed by pad name."""
        pitch = self.cfg.tactile.texel_pitch_mm * _MM
        out = {}
        for (finger, part), mat in zip(self._by_matrix(), matrices, strict=True):
            cells = np.ascontiguousarray(mat, dtype="<u2")
            cols = cells.shape[1]
            out[f"{finger}_{part}"] = fm.Grid(
                timestamp=_ts(ns),
                frame_id=f"{finger}_{part}_pad",
                column_count=cols,
                cell_size=fm.Vector2(x=pitch, y=pitch),
                row_stride=2 * cols,
                cell_stride=2,
                fields=[
                    fm.PackedElementField(
                        name="counts", offset=0, type=fm.PackedElementFieldNumericType.Uint16
                    )
                ],
                data=cells.tobytes(),
            )
        return out

    def _by_matrix(self) -> list[tuple[str, str]]:
        """(finger, pad) of each matrix index, in index order."""
        ax = self.cfg.axes
        by_index = {pad_matrix(ax, f, p): (f, p) for f in FINGERS for p in PADS}
        return [by_index[m] for m in range(len(by_index))]


def _pose(p: np.ndarray, q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> fm.Pose:
    return fm.Pose(
        position=_v3(float(p[0]), float(p[1]), float(p[2])),
        orientation=fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )


@functools.cache
def _link_shells(
    desc: HandDescription,
) -> tuple[tuple[str, tuple[fm.CubePrimitive, ...], tuple[fm.CylinderPrimitive, ...]], ...]:
    """Each link's shell visuals (not its pad strips) as Foxglove's primitives, made once."""
    out = []
    for link in desc.links:
        shell = [v for v in desc.visuals if v.link == link and v.material == "shell"]
        if shell:
            cubes = tuple(_cube(v) for v in shell if v.shape == "box")
            out.append((link, cubes, tuple(_cylinder(v) for v in shell if v.shape == "cylinder")))
    return tuple(out)


def _visual_pose(v: Visual) -> fm.Pose:
    return _pose(np.array(v.xyz), quat_from_rpy(v.rpy))


def _cube(v: Visual) -> fm.CubePrimitive:
    """A URDF box (sizes x, y, z) as Foxglove draws it."""
    return fm.CubePrimitive(
        pose=_visual_pose(v), size=_v3(*v.size), color=_rgba(*MATERIALS[v.material])
    )


def _cylinder(v: Visual) -> fm.CylinderPrimitive:
    """A URDF cylinder (radius, length along its z) as Foxglove's (diameters x, y; height z)."""
    d = 2.0 * v.size[0]
    return fm.CylinderPrimitive(
        pose=_visual_pose(v), size=_v3(d, d, v.size[1]), color=_rgba(*MATERIALS[v.material])
    )


def object_entity(truth: Mapping[str, Any], ns: int) -> fm.SceneEntity | None:
    """The simulated object's true outline (frame 0's y, z in mm), a closed line in frame 0;
    red once it has dropped. None without an outline."""
    pts = [(float(y), float(z)) for y, z in truth.get("outline") or ()]
    if len(pts) < 2:
        return None
    color = _rgba(0.9, 0.2, 0.2, 1.0) if truth.get("dropped") else _rgba(0.2, 0.8, 0.3, 1.0)
    line = fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineLoop,
        thickness=1.0 * _MM,
        points=[fm.Point3(x=0.0, y=y * _MM, z=z * _MM) for y, z in pts],
        color=color,
    )
    return fm.SceneEntity(timestamp=_ts(ns), frame_id="frame0", id="object", lines=[line])


def sample_alpha(s: Mapping[str, Any], alpha: float) -> float:
    """The cones' half-angle (rad) to draw for sample ``s``: the one it recorded (``alpha``,
    degrees: α widened to what the grasp and the contacts held), else ``alpha``."""
    a = s.get("alpha")
    return math.radians(a) if isinstance(a, int | float) and a > 0.0 else alpha


def _cone(apex: np.ndarray, n: np.ndarray, alpha: float, height: float) -> fm.CylinderPrimitive:
    """A friction cone: apex at the contact, axis along the pad's normal n (in the yz plane)."""
    a = math.atan2(-n[1], n[2])  # Rx(a) turns z onto n
    q = (math.sin(a / 2), 0.0, 0.0, math.cos(a / 2))
    d = 2.0 * height * math.tan(alpha)
    return fm.CylinderPrimitive(
        pose=_pose(apex + n * height / 2, q),
        size=_v3(d, d, height),
        bottom_scale=0.0,
        top_scale=1.0,
        color=_rgba(0.2, 0.6, 1.0, 0.25),
    )


_LEVELS = {"fault": fm.LogLevel.Error, "estop": fm.LogLevel.Error, "reversal": fm.LogLevel.Info}


def log_message(e: Mapping[str, Any], ns: int) -> fm.Log:
    """A run event as a Log line: its kind as the name, the detail as the text."""
    detail = json.dumps(e["detail"], ensure_ascii=False, sort_keys=True)
    it = e["iteration"]
    text = f"{e['kind']}{'' if it is None else f' at iteration {it}'}: {detail}"
    return fm.Log(
        timestamp=_ts(ns),
        level=_LEVELS.get(e["kind"], fm.LogLevel.Info),
        message=text,
        name=e["kind"],
    )


NOT_RECORDED = "none: a run of an older version, drawn with the exporting configuration"
NOT_RECORDED_SOFTWARE = "none: a run of a version older than the record"


def _strings(d: Any, key: str = "value") -> dict[str, str]:
    """A metadata record's values: strings as they are, anything else as JSON (a value that is
    not a mapping becomes one entry, ``key``)."""
    items = d.items() if isinstance(d, Mapping) else [(key, d)]
    return {k: v if isinstance(v, str) else json.dumps(v) for k, v in items}


Frame = tuple[float, int | None, int, np.ndarray]


def write_mcap(
    out: IO[bytes],
    cfg: Settings,
    run: Mapping[str, Any],
    t0_ns: int,
    samples: Iterable[Mapping[str, Any]],
    events: Iterable[Mapping[str, Any]],
    frames: Iterable[Frame],
    outline: Mapping[str, Any] | None = None,
    truth: Iterable[Mapping[str, Any]] = (),
) -> int:
    """Write one run (its row, samples, events, frames) to ``out``; returns the message count.

    ``samples`` and ``truth`` in iteration order, iterated once, so a run need not be held whole
    (``RunStore.each_sample``, ``RunStore.each_truth``). ``outline`` and ``truth``: the simulated
    object's (``RunStore.outline``), drawn in each iteration's scene where recorded. The
    reconstructed outline is drawn at most every
    :data:`~sdh2svc.service.telemetry.ESTIMATE_PERIOD_S` of the run (it costs milliseconds)."""
    hand = HandFrames.of(cfg, OutlineEvery(ESTIMATE_PERIOD_S))
    meta = run.get("meta") or {}
    alpha = math.radians((meta.get("params") or {}).get("alpha_deg", cfg.rolling.alpha_deg))
    w = Writer(out)
    w.start(profile="", library="sdh2svc")

    def channel(topic: str, name: str, encoding: str, data: bytes, msg_enc: str) -> int:
        sid = w.register_schema(name=name, encoding=encoding, data=data)
        return w.register_channel(topic=topic, message_encoding=msg_enc, schema_id=sid)

    def typed(topic: str, msg: type[Any]) -> int:
        s = msg.get_schema()
        return channel(topic, s.name, s.encoding, s.data, s.encoding)

    ch_samples = channel(
        SAMPLES, SAMPLE_SCHEMA, "jsonschema", json.dumps(sample_schema()).encode(), "json"
    )
    ch_tf, ch_scene = typed(TF, fm.FrameTransforms), typed(SCENE, fm.SceneUpdate)
    ch_log = typed(EVENTS, fm.Log)
    ch_pads = {pad: typed(pad_topic(pad), fm.Grid) for pad in PAD_NAMES}
    n = 0

    def put(ch: int, ns: int, data: bytes) -> None:
        nonlocal n
        w.add_message(ch, log_time=ns, publish_time=ns, data=data, sequence=n)
        n += 1

    rows = _Aligned(truth if outline is not None else ())
    for s in samples:
        ns = t0_ns + round(s["t"] * 1e9)
        put(ch_samples, ns, sample_json(s))
        put(ch_tf, ns, hand.transforms(s, ns).encode())
        row = rows.at(s["iteration"])
        obj = recorded_truth(outline, row) if outline is not None and row is not None else None
        put(ch_scene, ns, hand.scene(s, ns, alpha, obj).encode())
    for e in events:
        ns = t0_ns + round(e["t"] * 1e9)
        put(ch_log, ns, log_message(e, ns).encode())
        if e.get("kind") == EventKind.END:  # as live: no contacts once the run has ended
            put(ch_scene, ns, clear_contacts(ns).encode())
    for t, _it, _stamp, texels in frames:
        ns = t0_ns + round(t * 1e9)
        for pad, grid in hand.grids(texels, ns).items():
            put(ch_pads[pad], ns, grid.encode())
    _write_records(w, run, hand.desc, t0_ns)
    w.finish()  # type: ignore[no-untyped-call]
    return n


class _Aligned:
    """Truth rows in iteration order, met one sample at a time (samples in iteration order too):
    a run of hours is read once, never held whole."""

    def __init__(self, rows: Iterable[Mapping[str, Any]]) -> None:
        self._rows = iter(rows)
        self._next = next(self._rows, None)

    def at(self, iteration: int) -> Mapping[str, Any] | None:
        """The row of ``iteration``, or None (none recorded); rows before it are passed."""
        while self._next is not None and self._next["iteration"] < iteration:
            self._next = next(self._rows, None)
        row = self._next
        return row if row is not None and row["iteration"] == iteration else None


def _as_recorded(meta: Mapping[str, Any], key: str, missing: str) -> Mapping[str, Any]:
    """The run's own ``key`` record, or one that says it has none (``missing``)."""
    value = meta.get(key)
    return value if isinstance(value, Mapping) else {"recorded": missing}


def _write_records(w: Writer, run: Mapping[str, Any], desc: HandDescription, t0_ns: int) -> None:
    meta = run.get("meta") or {}
    own = ("params", "object", "configuration", "software")
    rest = {k: v for k, v in meta.items() if k not in own}
    info = {k: run.get(k) for k in ("id", "started_at", "ended_at", "status", "summary")}
    w.add_metadata("run", _strings(info))
    w.add_metadata("parameters", _strings(meta.get("params")))
    w.add_metadata("object", _strings(meta.get("object") or "none (a real hand)", "name"))
    # the configuration the run recorded, as it stored it (the drawing takes its hand from it:
    # Settings.as_recorded); a run of a version that recorded none says so, never passing the
    # exporting process's configuration off as the run's
    conf = _as_recorded(meta, "configuration", NOT_RECORDED)
    w.add_metadata("configuration", _strings({**rest, **conf}))
    # which sdh2svc recorded the run (provenance.code_version)
    w.add_metadata("software", _strings(_as_recorded(meta, "software", NOT_RECORDED_SOFTWARE)))
    w.add_attachment(
        create_time=t0_ns,
        log_time=t0_ns,
        name="sdh2.urdf",
        media_type="application/xml",
        data=to_xml(desc).encode(),
    )
