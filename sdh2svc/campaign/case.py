"""One campaign case and a suite of them: an object, where it is placed, how the sensor differs.

A case is data (a suite is a JSON file of them, readable and versioned). What it changes in a
run is said in one place, :meth:`Case.overrides` (configuration keys) and :attr:`Case.object`
(the object placed between the fingertips); everything else is the default configuration —
one configuration for every object.
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from sdh2svc.config import ConfigError, clip, format_errors
from sdh2svc.model.base import Finite
from sdh2svc.sim.objects import Ellipse, ObjectSpec, Shape

Family = Literal["box", "polygon", "ellipse", "circle", "stick", "rounded", "thesis"]
FAMILIES: tuple[str, ...] = ("box", "polygon", "ellipse", "circle", "stick", "rounded", "thesis")

SUITES_DIR = Path(__file__).parent / "suites"  # the named suites, packaged with the wheel

# The sensor's variation per run (thesis §5.1: real pads drift with use and temperature).
GAIN_FACTOR = (0.5, 1.5)  # × sim.sensor.gain_vs_library


class Texel(Finite):
    """One cell of one of the six matrices (wire order), e.g. a dead texel."""

    matrix: Annotated[int, Field(ge=0, le=5)]
    row: Annotated[int, Field(ge=0, le=13)]
    col: Annotated[int, Field(ge=0, le=5)]


class SensorVariation(Finite):
    """How this run's pads differ from the nominal sensor (None: the configuration's value)."""

    gain_factor: Annotated[float, Field(ge=GAIN_FACTOR[0], le=GAIN_FACTOR[1])] = 1.0
    creep_gain: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    creep_rise_s: Annotated[float, Field(gt=0.0, le=100.0)] | None = None
    noise_counts: Annotated[float, Field(ge=0.0, le=100.0)] | None = None
    dead_texels: tuple[Texel, ...] = ()


# A suite's name is also its campaign's folder (campaigns/NAME): a plain file name.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
SEED_MAX = 2**63 - 1  # a Parquet int64, as sim.seed is stored
# How far a case's stated true_width_mm may be from its object's width at its angle (mm): the
# generator writes it to 3 decimals.
WIDTH_TOLERANCE_MM = 0.01
# The widest contact the open fingers take (mm): from the default pre-shape the pads stand
# 122.5 mm apart (campaign/generate.py); a wider object is never gripped.
MAX_CONTACT_WIDTH_MM = 122.5


# The configuration keys a case may set (Case.overrides), bar the nominal sensor gain it scales
# (sim.sensor.gain_vs_library × gain_factor): a campaign's --set of one would be overridden.
CASE_KEYS = frozenset({
    "sim.seed", "sim.object_height_mm", "sim.object_angle_deg", "sim.sensor.creep_gain",
    "sim.sensor.creep_rise_s", "sim.sensor.noise_counts", "sim.sensor.dead_texels",
})  # fmt: skip


class Case(Finite):
    """One run of a campaign."""

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    family: Family
    object: ObjectSpec
    height_mm: Annotated[float, Field(ge=60.0, le=200.0)] = Field(
        description="z0 of the object's centre between the fingertips (sim.object_height_mm)"
    )
    angle_deg: Annotated[float, Field(ge=-180.0, le=180.0)] = 0.0
    seed: Annotated[int, Field(ge=0, le=SEED_MAX)] = 1
    sensor: SensorVariation = SensorVariation()
    true_width_mm: Annotated[float, Field(gt=0.0, le=200.0)] = Field(
        description="the object's width along y0 at its placement: where the fingertips touch"
    )

    @model_validator(mode="after")
    def _family_is_the_objects(self) -> Case:
        """The family names the object's kind (a report's and a comparison's rates by family
        count it there): a box without rounded corners, a rounded one a box with them; the
        thesis's family holds its objects, whatever their kind."""
        if self.family == "thesis":
            return self
        kind = self.object.kind
        rounded = (getattr(self.object, "corner_radius_mm", 0.0) or 0.0) > 0.0
        want = {"rounded": "box"}.get(self.family, self.family)
        if kind != want or (kind == "box" and rounded != (self.family == "rounded")):
            what = f"a {kind}"
            if kind == "box":
                what = f"a box with{'' if rounded else 'out'} rounded corners"
            raise ValueError(f"family {self.family!r} but the object is {what} (box: without "
                             "rounded corners; rounded: a box with them; thesis: any)")  # fmt: skip
        return self

    @model_validator(mode="after")
    def _width_is_the_objects(self) -> Case:
        """The stated width is the object's at its angle (a wrong one would skew every Λ error
        the campaign reports), and one the open fingers take."""
        # on a copy: the outline it caches would make equal cases compare unequal (arrays)
        width = contact_width_mm(self.object.model_copy(), self.angle_deg)
        if abs(width - self.true_width_mm) > WIDTH_TOLERANCE_MM:
            raise ValueError(
                f"true_width_mm is {self.true_width_mm:g} but the object is {width:.3f} mm wide "
                f"along y0 at angle_deg {self.angle_deg:g} (contact_width_mm)"
            )
        if width > MAX_CONTACT_WIDTH_MM:
            raise ValueError(
                f"the object is {width:.3f} mm wide where the fingertips touch it: the open "
                f"fingers take at most {MAX_CONTACT_WIDTH_MM:g} mm"
            )
        return self

    def overrides(self, base_gain: float) -> list[str]:
        """The configuration keys this case sets (``--set`` syntax; of :data:`CASE_KEYS`, and
        the sensor's gain), given the nominal ``sim.sensor.gain_vs_library``."""
        out = [f"sim.seed={self.seed}", f"sim.object_height_mm={self.height_mm!r}",
               f"sim.object_angle_deg={self.angle_deg!r}",
               f"sim.sensor.gain_vs_library={base_gain * self.sensor.gain_factor!r}"]  # fmt: skip
        s = self.sensor
        for key in ("creep_gain", "creep_rise_s", "noise_counts"):
            if (value := getattr(s, key)) is not None:
                out.append(f"sim.sensor.{key}={value!r}")
        if s.dead_texels:
            cells = [[t.matrix, t.row, t.col] for t in s.dead_texels]
            out.append(f"sim.sensor.dead_texels={json.dumps(cells)}")
        return out


class Suite(Finite):
    """A named, versioned list of cases, and the generator seed that made it (None: by hand)."""

    name: str = Field(pattern=NAME_PATTERN, description="a plain file name: its campaign's folder")
    version: Annotated[int, Field(ge=1, le=SEED_MAX)] = 1
    generator_seed: Annotated[int, Field(ge=0, le=SEED_MAX)] | None = None
    description: str = ""
    cases: tuple[Case, ...] = Field(min_length=1)

    @classmethod
    def load(cls, path: str | Path) -> Suite:
        # strict: a number written as a string ("seed": "3") is a mistake in a file, not a seed
        return cls.model_validate_json(Path(path).read_bytes(), strict=True)

    def dump(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json())

    def to_json(self) -> str:
        """Stable text: the same suite always gives the same bytes (reproducible, diffable)."""
        data: Any = self.model_dump(mode="json")
        return json.dumps(data, indent=1, ensure_ascii=False) + "\n"


def extent_along_y0(obj: Shape, angle_deg: float) -> tuple[float, float]:
    """(min, max) of the object's outline along y0, relative to its centre, when it is turned by
    ``angle_deg`` (as sim.object_angle_deg turns it: object x along y0 at 0°).

    The outline is the convex core grown by the rounding radius, so the extent is the core's
    projection ± the radius; an ellipse is exact (the physics uses the exact ellipse, not its
    96-gon)."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    if isinstance(obj, Ellipse):
        half = math.hypot(obj.axis_a_mm / 2 * c, obj.axis_b_mm / 2 * s)
        return -half, half
    core, radius = obj.outline()
    y = np.asarray(core, dtype=float) @ np.array([c, -s])  # y0 of R(angle)·v
    return float(y.min()) - radius, float(y.max()) + radius


def contact_width_mm(obj: Shape, angle_deg: float) -> float:
    """The object's true contact width at its placement: its width along y0 (the line between
    the fingertips) when turned by ``angle_deg`` — not its width across corners."""
    lo, hi = extent_along_y0(obj, angle_deg)
    return hi - lo


def load_suite(name_or_path: str | Path) -> Suite:
    """A packaged suite by name (``smoke``, ``bench-v1``, ``thesis``) or a suite file's path.
    An unknown name or a missing file raises :class:`FileNotFoundError`; an invalid suite
    :class:`~sdh2svc.config.ConfigError`, naming every bad field and its allowed range."""
    text = str(name_or_path)
    path = Path(text)
    if not (path.suffix.lower() == ".json" or os.sep in text or "/" in text or path.is_file()):
        path = SUITES_DIR / f"{text}.json"
        if not path.is_file():
            raise FileNotFoundError(
                f"no suite {clip(text)!r} (packaged suites: {', '.join(suite_names())}; or give a "
                "suite file's path)"
            )
    if path.is_dir():
        raise ConfigError([f"{path} is a directory, not a suite file"], f"suite {path}")
    try:
        suite = Suite.load(path)
    except ValidationError as e:
        problems = format_errors(e, Suite)
        if any(err["type"] == "json_invalid" for err in e.errors()):
            problems = [f"not a JSON suite file: {problems[0]} (suites are JSON, see smoke.json)"]
        raise ConfigError(problems, f"suite {path}") from None
    counts = Counter(c.id for c in suite.cases)
    dups = sorted(i for i, n in counts.items() if n > 1)
    if dups:
        raise ConfigError([f"cases: the id {d!r} is used more than once" for d in dups],
                          f"suite {path}")  # fmt: skip
    return suite


def suite_names() -> list[str]:
    """The packaged suites' names."""
    return sorted(p.stem for p in SUITES_DIR.glob("*.json"))


def wrap_deg(a: float) -> float:
    """An angle in degrees as the same angle in [−180, 180) (a placement's, a turn's)."""
    return (a + 180.0) % 360.0 - 180.0
