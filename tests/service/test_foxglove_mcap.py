"""The Foxglove-native MCAP export: every message valid against its schema, every channel there."""

from __future__ import annotations

import base64
import io
import json
import math
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from foxglove import messages as fm
from mcap_check import Recording, _no_unknown_fields, _proto_class, read
from test_store import _frame, _samples

from sdh2svc import __version__
from sdh2svc.config import ConfigError, Settings
from sdh2svc.control.sample import Sample
from sdh2svc.model.urdf import FINGERS, PADS, describe
from sdh2svc.provenance import code_version
from sdh2svc.service.foxglove_mcap import HandFrames, sample_schema
from sdh2svc.service.store import Recorder, RunStore

N = 30


@pytest.fixture(scope="module")
def recorded(cfg: Settings, tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Sample], Any]:
    db = tmp_path_factory.mktemp("fox") / "runs.sqlite"
    store = RunStore(db)
    obj = {"name": "egg", "shape": "ellipsoid", "size_mm": [53.0, 39.0, 39.0]}
    run_id = store.create_run({"params": cfg.rolling.model_dump(), "object": obj, "sim": True,
                               "configuration": cfg.recorded(),
                               "software": code_version()})  # fmt: skip
    rec = Recorder(db, run_id)
    samples = _samples(cfg, N)
    for s in samples:
        rec.sample(s)
    rec.event(0.0, None, "phase", {"phase": "rolling"})
    rec.event(0.5, 15, "reversal", {"reason": "cone_A"})
    rec.event(0.9, None, "fault", {"fault": "stale_frame", "message": "no frame for 0.2 s"})
    distal = _frame(20.0)
    for i in range(3):  # the six matrices of a frame, in wire order: proximal 6×14, distal 6×13
        parts = [np.full(84, i, np.uint16) if m % 2 == 0 else distal.ravel() for m in range(6)]
        rec.frame(0.1 * i, None, 1000 + 33 * i, np.concatenate(parts))
    rec.close()
    store.finish_run(run_id, "completed", {"strokes": 3})
    raw = io.BytesIO()
    n = store.export_mcap(run_id, raw, cfg)
    store.close()
    rec_ = read(raw.getvalue())
    assert n == sum(len(v) for v in rec_.messages.values()) == 3 * N + 3 + 3 * 6
    return samples, rec_


def test_channels_and_their_schemas(recorded: tuple[list[Sample], Recording]) -> None:
    _, rec = recorded
    want = {
        "/samples": ("sdh2svc.Sample", "jsonschema"),
        "/tf": ("foxglove.FrameTransforms", "protobuf"),
        "/scene": ("foxglove.SceneUpdate", "protobuf"),
        "/events": ("foxglove.Log", "protobuf"),
        **{f"/tactile/{f}_{p}": ("foxglove.Grid", "protobuf") for f in FINGERS for p in PADS},
    }
    assert rec.schemas == want


def test_the_sample_schema_is_the_sample(recorded: tuple[list[Sample], Recording]) -> None:
    samples, rec = recorded
    schema = sample_schema()
    assert list(schema["properties"]) == list(Sample.columns())
    # one type each, as Foxglove's JSON-schema reader takes them (a list of types refused the
    # channel); a field that may have no value is not required, and left out when it has none
    assert {p["type"] for p in schema["properties"].values()} <= {"number", "integer",
                                                                   "string", "boolean"}  # fmt: skip
    assert schema["properties"]["S1"]["type"] == "number" and "S1" not in schema["required"]
    assert schema["properties"]["iteration"]["type"] == "integer"
    assert "iteration" in schema["required"] and "reversal" not in schema["required"]
    for name in ("t", "phi2", "S1", "Lambda", "sigma", "Ay", "frame_age_ms"):  # units stated
        assert schema["properties"][name]["description"].endswith((", s", ", deg", ", mm", ", ms"))
    got = rec.messages["/samples"]
    assert [m["iteration"] for m in got] == [s.iteration for s in samples]
    values = {f.name: getattr(samples[7], f.name) for f in fields(Sample)}
    assert got[7] == {k: v for k, v in values.items() if v is not None}
    assert any(v is None for v in values.values())  # (one left out)


def test_the_csv_header_carries_the_units() -> None:
    """``name [unit]`` from the Sample's fields, the same unit as the schema's description."""
    header = Sample.csv_header()
    assert header[:3] == ("iteration", "t [s]", "phi2 [deg]")
    assert {"S1 [mm]", "F [library force units]", "latency_ms [ms]", "reversal"} <= set(header)
    docs = Sample.descriptions()
    for name, col in zip(Sample.columns(), header, strict=True):
        unit = Sample.units()[name]
        assert col == (name if unit is None else f"{name} [{unit}]")
        assert unit is None or docs[name].endswith(f", {unit}")


def test_log_times_are_the_records_own(recorded: tuple[list[Sample], Recording]) -> None:
    samples, rec = recorded
    t = rec.log_times
    t0 = t["/samples"][0] - round(samples[0].t * 1e9)
    assert [x - t0 for x in t["/samples"]] == [round(s.t * 1e9) for s in samples]
    assert t["/tf"] == t["/scene"] == t["/samples"]
    assert [x - t0 for x in t["/events"]] == [0, 500_000_000, 900_000_000]
    assert [x - t0 for x in t["/tactile/finger1_distal"]] == [0, 100_000_000, 200_000_000]
    for topic in ("/tf", "/scene", "/events", "/tactile/thumb_proximal"):
        raw = rec.messages[topic][-1]["_raw"]
        stamped = raw.transforms if topic == "/tf" else raw.entities if topic == "/scene" else [raw]
        assert {x.timestamp.ToNanoseconds() for x in stamped} == {t[topic][-1]}


def test_transforms_follow_the_recorded_angles(
    cfg: Settings, recorded: tuple[list[Sample], Recording]
) -> None:
    samples, rec = recorded
    desc = describe(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
    links = set(desc.links)
    for msg in rec.messages["/tf"]:
        tfs = msg["transforms"]
        assert len(tfs) == len(desc.joints)
        assert all(t["parent_frame_id"] in links and t["child_frame_id"] in links for t in tfs)
    # φ2 of sample 5: the proximal joint's rotation about −x by φ2
    (t,) = [
        t for t in rec.messages["/tf"][5]["transforms"] if t["child_frame_id"] == "finger1_proximal"
    ]
    q = t["rotation"]
    assert -2 * math.atan2(q.get("x", 0.0), q["w"]) == pytest.approx(math.radians(samples[5].phi2))


def test_contacts_segment_and_cones(
    cfg: Settings, recorded: tuple[list[Sample], Recording]
) -> None:
    samples, rec = recorded
    s, msg = samples[4], rec.messages["/scene"][4]
    (entity,) = [e for e in msg["entities"] if e["id"] == "contacts"]
    assert entity["frame_id"] == "frame0"
    A = entity["spheres"][0]["pose"]["position"]
    assert (A.get("y", 0.0) * 1e3, A["z"] * 1e3) == pytest.approx((s.Ay, s.Az))
    pts = entity["lines"][0]["points"]
    got = [c for p in pts for c in (p.get("y", 0.0) * 1e3, p["z"] * 1e3)]
    assert got == pytest.approx([s.Ay, s.Az, s.By, s.Bz])
    cones = entity["cylinders"]
    assert len(cones) == 2 and all(c.get("bottom_scale", 0.0) == 0.0 for c in cones)
    # the cone's opening: diameter / height = 2 tan α
    c = cones[0]["size"]
    assert c["x"] / c["z"] == pytest.approx(2 * math.tan(math.radians(cfg.rolling.alpha_deg)))
    # the cone's axis leaves A towards the other finger (+y for Finger 1 in a mirror pose)
    centres = [c["pose"]["position"].get("y", 0.0) * 1e3 for c in cones]
    assert centres[0] > s.Ay and centres[1] < s.By


def test_pads_as_boxes_in_their_frames(
    cfg: Settings, recorded: tuple[list[Sample], Recording]
) -> None:
    """Each pad a box under its Grid, in the pad's frame of /tf, following it."""
    _, rec = recorded
    frames = {t["child_frame_id"] for t in rec.messages["/tf"][0]["transforms"]}
    assert "frame0" in frames  # the contacts' frame
    pitch = cfg.tactile.texel_pitch_mm * 1e-3
    entities = rec.messages["/scene"][3]["entities"]
    pads = {e["id"]: e for e in entities if e["id"].startswith("pads/")}
    assert set(pads) == {f"pads/{f}_{p}" for f in FINGERS for p in PADS}
    for f in FINGERS:
        for p in PADS:
            e = pads[f"pads/{f}_{p}"]
            assert e["frame_id"] == f"{f}_{p}_pad" and e["frame_id"] in frames
            assert e["frame_locked"] is True
            (cube,) = e["cubes"]
            lay = cfg.tactile.proximal if p == "proximal" else cfg.tactile.distal
            w, h = lay.cols * pitch, lay.rows * pitch
            assert (cube["size"]["x"], cube["size"]["y"]) == pytest.approx((w, h))
            c = cube["pose"]["position"]
            assert (c["x"], c["y"]) == pytest.approx((w / 2, h / 2)) and c["z"] < 0  # below


def _xyz(v: dict[str, float]) -> dict[str, float]:
    """A decoded Vector3 (protobuf leaves out its zeros) whole."""
    return {k: v.get(k, 0.0) for k in "xyz"}


def test_the_links_as_the_urdf_draws_them(
    cfg: Settings, recorded: tuple[list[Sample], Recording]
) -> None:
    """Foxglove's 3-D panel reads no attachment: /scene draws each link's shell (the URDF's
    boxes and cylinder, same sizes and origins) in the link's frame of /tf, so the hand shows
    without a URDF layer."""
    import xml.etree.ElementTree as ET

    _, rec = recorded
    tf = rec.messages["/tf"][0]["transforms"]
    frames = {t["child_frame_id"] for t in tf} | {t["parent_frame_id"] for t in tf}
    urdf = ET.fromstring(rec.attachments["sdh2.urdf"][1])
    shells: dict[str, list[ET.Element]] = {}
    for link in urdf.iter("link"):
        for vis in link.iter("visual"):
            if vis.find("material").get("name") == "shell":  # type: ignore[union-attr]
                shells.setdefault(link.get("name", ""), []).append(vis)
    assert {"palm", "finger1_proximal", "finger2_distal", "thumb_knuckle"} <= set(shells)
    for scene in (rec.messages["/scene"][0], rec.messages["/scene"][-1]):  # with every update
        links = {e["id"]: e for e in scene["entities"] if e["id"].startswith("links/")}
        assert set(links) == {f"links/{name}" for name in shells}
        for name, visuals in shells.items():
            e = links[f"links/{name}"]
            assert e["frame_id"] == name and name in frames and e["frame_locked"] is True
            drawn = [(_xyz(c["size"]), _xyz(c["pose"]["position"])) for c in e.get("cubes", [])]
            drawn += [
                ({"r": c["size"]["x"] / 2, "length": c["size"]["z"]}, _xyz(c["pose"]["position"]))
                for c in e.get("cylinders", [])
            ]
            want = []
            for vis in visuals:
                geom = vis.find("geometry")[0]  # type: ignore[index]
                xyz = [float(v) for v in vis.find("origin").get("xyz", "").split()]  # type: ignore[union-attr]
                if geom.tag == "box":
                    x, y, z = (float(v) for v in geom.get("size", "").split())
                    size: dict[str, float] = {"x": x, "y": y, "z": z}
                else:
                    size = {
                        "r": float(geom.get("radius", "")),
                        "length": float(geom.get("length", "")),
                    }
                want.append((size, dict(zip("xyz", xyz, strict=True))))
            assert len(drawn) == len(want)
            for (got_size, got_at), (size, at) in zip(drawn, want, strict=True):
                assert got_size == pytest.approx(size) and got_at == pytest.approx(at)


def test_the_objects_true_outline(cfg: Settings) -> None:
    """In simulation (a ``sim`` message's truth): a closed line in frame 0, red once dropped."""
    hand = HandFrames.of(cfg)
    ring = [(30 * math.cos(a), 120 + 20 * math.sin(a)) for a in np.linspace(0, 6.2, 90)]
    scene_cls = _proto_class("foxglove.SceneUpdate", fm.SceneUpdate.get_schema().data)
    for dropped, red in ((False, 0.0), (True, 0.9)):
        truth = {"outline": ring, "dropped": dropped}
        msg = scene_cls.FromString(hand.scene(None, 7, 0.4, truth).encode())
        _no_unknown_fields(msg)
        (obj,) = [e for e in msg.entities if e.id == "object"]
        assert obj.frame_id == "frame0" and obj.timestamp.ToNanoseconds() == 7
        (line,) = obj.lines
        assert line.type == 1  # LINE_LOOP: the outline closed
        pts = [c for p in line.points for c in (p.x, p.y * 1e3, p.z * 1e3)]
        assert pts == pytest.approx([c for y, z in ring for c in (0.0, y, z)])
        assert line.color.r == pytest.approx(red, abs=0.2)
        assert all(e.id != "contacts" for e in msg.entities)  # no sample: none drawn
    no_outline = scene_cls.FromString(hand.scene(None, 7, 0.4, {"outline": []}).encode())
    assert [e.id for e in no_outline.entities if e.id == "object"] == []


def test_pads_as_grids(cfg: Settings, recorded: tuple[list[Sample], Recording]) -> None:
    _, rec = recorded
    pitch = cfg.tactile.texel_pitch_mm * 1e-3
    for f in FINGERS:
        for p in PADS:
            g = rec.messages[f"/tactile/{f}_{p}"][2]
            lay = cfg.tactile.proximal if p == "proximal" else cfg.tactile.distal
            assert g["frame_id"] == f"{f}_{p}_pad" and g["column_count"] == lay.cols
            assert g["cell_size"] == {"x": pytest.approx(pitch), "y": pytest.approx(pitch)}
            assert g["row_stride"] == 2 * lay.cols and g["cell_stride"] == 2
            assert g["fields"] == [{"name": "counts", "type": "UINT16"}]
            data = np.frombuffer(base64.b64decode(g["data"]), "<u2")
            assert data.size == lay.rows * lay.cols
            if p == "proximal":
                assert (data == 2).all()
            else:
                assert np.array_equal(data.reshape(lay.rows, lay.cols), _frame(20.0))


def test_events_as_logs(recorded: tuple[list[Sample], Recording]) -> None:
    _, rec = recorded
    logs = rec.messages["/events"]
    assert [m["name"] for m in logs] == ["phase", "reversal", "fault"]
    assert [m["level"] for m in logs] == ["INFO", "INFO", "ERROR"]
    assert logs[1]["message"] == 'reversal at iteration 15: {"reason": "cone_A"}'


def test_metadata_and_the_urdf(cfg: Settings, recorded: tuple[list[Sample], Recording]) -> None:
    _, rec = recorded
    md = rec.metadata
    assert set(md) == {"run", "parameters", "object", "configuration", "software"}
    assert md["software"]["version"] == __version__ and len(md["software"]["source"]) == 64
    assert "software" not in md["configuration"]
    assert md["run"]["status"] == "completed" and json.loads(md["run"]["summary"]) == {"strokes": 3}
    assert json.loads(md["parameters"]["alpha_deg"]) == cfg.rolling.alpha_deg
    assert set(md["parameters"]) == set(cfg.rolling.model_dump())
    assert md["object"]["name"] == "egg" and json.loads(md["object"]["size_mm"])[0] == 53.0
    conf = md["configuration"]
    assert json.loads(conf["sim"]) is True
    assert json.loads(conf["hand"])["proximal_length_mm"] == cfg.hand.proximal_length_mm
    assert json.loads(conf["axes"])["phi2"] == cfg.axes.phi2
    media, urdf = rec.attachments["sdh2.urdf"]
    assert media == "application/xml" and b'<robot name="sdh2">' in urdf


def test_an_export_without_frames_or_contacts(cfg: Settings, tmp_path: Path) -> None:
    """A run that faulted before its first contact: no A, B — an empty scene, no cones."""
    store = RunStore(tmp_path / "runs.sqlite")
    run_id = store.create_run({})
    rec = Recorder(store.path, run_id)
    s = _samples(cfg, 1)[0]
    none = {n: None for n in ("Ay", "Az", "By", "Bz", "Cy", "Cz", "Dy", "Dz", "S1", "S2")}
    rec.sample(Sample(**{**{f.name: getattr(s, f.name) for f in fields(Sample)}, **none}))
    rec.close()
    raw = io.BytesIO()
    assert store.export_mcap(run_id, raw) == 3
    store.close()
    got = read(raw.getvalue())
    (entity,) = [e for e in got.messages["/scene"][0]["entities"] if e["id"] == "contacts"]
    assert "spheres" not in entity and "cylinders" not in entity
    assert got.metadata["object"] == {"name": "none (a real hand)"}


def test_the_reconstructed_outline_is_a_line_in_the_contacts(
    cfg: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recognition's outline (telemetry.estimate_outline) as a closed line beside AB, only
    once a class is known."""
    from google.protobuf.json_format import MessageToDict

    from sdh2svc.service import telemetry

    def tri(rec: Any, a: Any, b: Any, n: int = 64) -> np.ndarray:
        return np.array([a, b, (a[0], a[1] + rec.size_a)])

    def lines(row: dict[str, Any]) -> list[dict[str, Any]]:
        schema = fm.SceneUpdate.get_schema()
        msg = fm.SceneUpdate(entities=[hand.contacts(row, 0, 0.4)])
        decoded = _proto_class(schema.name, schema.data).FromString(msg.encode())
        return MessageToDict(decoded, preserving_proto_field_name=True)["entities"][0]["lines"]

    monkeypatch.setattr(telemetry, "outline", tri)
    s = _samples(cfg, 1)[0]
    row = dict(zip(Sample.columns(), s.row(), strict=True))
    hand = HandFrames.of(cfg)
    assert len(lines(row)) == 1  # AB only: no class, no estimate
    row.update(object_class="circle", class_confidence=0.8, size_a=25.0, rotation_est=3.0)
    _ab, est = lines(row)
    assert est["type"] == "LINE_LOOP"
    got = [c for p in est["points"] for c in (p.get("y", 0.0) * 1e3, p["z"] * 1e3)]
    assert got == pytest.approx([s.Ay, s.Az, s.By, s.Bz, s.Ay, s.Az + 25.0], abs=0.006)  # 0.01 mm


def test_the_cones_open_as_wide_as_the_sample_recorded(cfg: Settings) -> None:
    """A sample records the cones' half-angle the run widened them to (Sample.alpha): the scene's
    cones open that wide; a sample without one (an older recording) takes the run's α."""
    scene_cls = _proto_class("foxglove.SceneUpdate", fm.SceneUpdate.get_schema().data)
    s = _samples(cfg, 1)[0]
    row = dict(zip(Sample.columns(), s.row(), strict=True))
    hand, run_alpha = HandFrames.of(cfg), math.radians(22.0)
    for recorded, opening in ((30.0, 30.0), (None, 22.0)):
        msg = scene_cls.FromString(hand.scene({**row, "alpha": recorded}, 7, run_alpha).encode())
        (entity,) = [e for e in msg.entities if e.id == "contacts"]
        assert len(entity.cylinders) == 2
        for c in entity.cylinders:
            assert c.size.x / c.size.z == pytest.approx(2 * math.tan(math.radians(opening)))


def test_the_configuration_record_is_the_runs_own(cfg: Settings, tmp_path: Path) -> None:
    """The record says what the run recorded, whatever the exporting process's configuration
    is now; a run of a version that recorded none says so, rather than passing the exporter's
    off as its own."""
    store = RunStore(tmp_path / "runs.sqlite")
    try:
        recorded = {**cfg.recorded(), "safety": {"force_ceiling_factor": 2.5}}
        ids = [store.create_run({"configuration": recorded}), store.create_run({})]
        for run_id in ids:
            store.finish_run(run_id, "completed", {})
        confs, softwares = [], []
        for run_id in ids:
            raw = io.BytesIO()
            store.export_mcap(run_id, raw, cfg)
            md = read(raw.getvalue()).metadata
            confs.append(md["configuration"])
            softwares.append(md["software"])
    finally:
        store.close()
    assert json.loads(confs[0]["safety"]) == {"force_ceiling_factor": 2.5}
    assert json.loads(confs[0]["hand"]) == cfg.recorded()["hand"]
    assert confs[1] == {"recorded": "none: a run of an older version, drawn with the exporting "
                        "configuration"}  # fmt: skip
    # neither recorded which sdh2svc made it: not the exporter's version passed off as theirs
    assert softwares == [{"recorded": "none: a run of a version older than the record"}] * 2


def test_a_recorded_configuration_this_version_refuses_is_named(
    cfg: Settings, tmp_path: Path
) -> None:
    """A run recorded by a version whose configuration this one refuses cannot be drawn as it
    was: the export says which key (the API answers 409 with it), it draws nothing wrong."""
    store = RunStore(tmp_path / "runs.sqlite")
    recorded = cfg.recorded()
    recorded["tactile"] = {**recorded["tactile"], "texel_pitch_mm": -3.4}
    run_id = store.create_run({"configuration": recorded})
    try:
        with pytest.raises(ConfigError, match=r"recorded configuration.*tactile\.texel_pitch_mm"):
            store.export_mcap(run_id, io.BytesIO(), cfg)
    finally:
        store.close()
