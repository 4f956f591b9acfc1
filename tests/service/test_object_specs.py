"""Object specs as the API takes them (sdh2svc.sim.objects): bounded, strict, derived geometry
computed once (tests/service/test_hardening.py sends the same through a live service)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from sdh2svc.config import format_errors
from sdh2svc.sim.objects import PRESETS, ObjectSpec, Outline, parse_object


def ring(n: int, a: float = 30.0, b: float = 20.0) -> list[list[float]]:
    return [[a * math.cos(2 * math.pi * k / n), b * math.sin(2 * math.pi * k / n)]
            for k in range(n)]  # fmt: skip


def errors(data: dict) -> list[str]:
    with pytest.raises(ValidationError) as e:
        parse_object(data)
    return format_errors(e.value, ObjectSpec)


def test_presets_and_both_windings_are_taken() -> None:
    for p in PRESETS.values():
        assert parse_object(p.model_dump()) == p
    cw = parse_object({"kind": "polygon", "vertices_mm": ring(64)[::-1], "depth_mm": 10})
    ccw = parse_object({"kind": "polygon", "vertices_mm": ring(64), "depth_mm": 10})
    assert cw.size_mm == pytest.approx(60.0) and ccw.size_mm == pytest.approx(60.0)


def test_limits_name_the_field_and_range() -> None:
    assert errors({"kind": "circle", "diameter_mm": 4, "depth_mm": 10}) == [
        "circle.diameter_mm = 4: Input should be greater than or equal to 5 "
        "(allowed: 5.0 ≤ diameter_mm ≤ 150.0)"
    ]
    (line,) = errors({"kind": "box", "width_mm": 30, "height_mm": 20, "depth_mm": float("inf")})
    assert line.startswith("box.depth_mm = inf") and "1.0 ≤ depth_mm ≤ 150.0" in line
    (line,) = errors({"kind": "stick", "length_mm": "60", "depth_mm": 10})
    assert "length_mm" in line and "valid number" in line
    (line,) = errors({"kind": "polygon", "vertices_mm": ring(65), "depth_mm": 10})
    assert "at most 64" in line
    (line,) = errors({"kind": "polygon", "vertices_mm": [[0, 0], [100, 0], [100, 0.5]],
                      "depth_mm": 10})  # fmt: skip
    assert "thin" in line
    lines = errors({"kind": "polygon", "vertices_mm": [[0, 0], [200, 0], [0, 30]], "depth_mm": 10})
    assert lines[0] == ("polygon.vertices_mm.1.0 = 200: Input should be less than or equal to 150 "
                        "(allowed: -150.0 ≤ vertices_mm ≤ 150.0)")  # fmt: skip
    (line,) = errors({"kind": "polygon", "vertices_mm": [[0, 0], [140, 0], [140, 140], [0, 140]],
                      "depth_mm": 10})  # fmt: skip
    assert "5 … 150 mm across" in line  # the diagonal: 198 mm
    (line,) = errors({"kind": "circle", "diameter_mm": 30, "depth_mm": 10, "name": "n" * 65})
    assert "name" in line and "n" * 81 not in line


def test_derived_geometry_is_computed_once() -> None:
    poly = parse_object({"kind": "polygon", "vertices_mm": ring(64), "depth_mm": 10})
    assert "size_mm" in poly.__dict__  # the validator measured it: cached since
    first = poly.outline()
    assert poly.outline() is first and not first[0].flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        first[0][0, 0] = 1.0
    egg = PRESETS["egg"]
    assert egg.outline() is egg.outline()
    o = Outline(poly)
    assert o.perimeter_points is o.perimeter_points
    assert np.ptp(o.perimeter_points[:, 0]) == pytest.approx(60.0, abs=0.1)


def test_a_spec_named_as_a_preset_must_be_that_preset() -> None:
    """A box called "egg" would show as the egg on the dashboard and in the run history."""
    from sdh2svc.service.hand_service import ServiceError, parse_object_request

    for name, preset in PRESETS.items():  # the preset's own spec, under its name: taken
        assert parse_object_request(None, preset.model_dump()) == preset, name
    box = {"kind": "box", "width_mm": 40, "height_mm": 30, "depth_mm": 30}
    assert parse_object_request(None, {**box, "name": "my block"}).name == "my block"
    with pytest.raises(ServiceError) as refused:
        parse_object_request(None, {**box, "name": "egg"})
    assert refused.value.status == 422
    assert refused.value.details == [
        "name = 'egg': a preset's name, and this spec is not that preset: give the object a "
        "name of its own (or choose the preset by name)"
    ]
