"""A campaign's results: one Parquet file, one row per case, written from ``cases.jsonl``.

The file's metadata (key ``sdh2svc.campaign``) holds what made it: the suite, the ``--set``
values, the effective configuration and the code version (the same JSON as ``campaign.json``).
pyarrow, pandas, polars and duckdb read it as they read any Parquet file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from sdh2svc.campaign.case import Suite

METADATA_KEY = b"sdh2svc.campaign"

_f64, _i64, _str, _bool = pa.float64(), pa.int64(), pa.string(), pa.bool_()
SCHEMA = pa.schema([
    ("id", _str), ("family", _str), ("success", _bool), ("failure", _str), ("status", _str),
    ("fault", _str), ("message", _str),
    ("strokes", _i64), ("cycles", _i64), ("half_strokes", _i64), ("half_strokes_turned", _i64),
    ("half_stroke_rotation_deg", pa.list_(_f64)), ("min_half_stroke_deg", _f64),
    ("mean_stroke_rotation_deg", _f64), ("rotation_range_deg", _f64),
    ("dropped", _bool), ("slips", _i64),
    ("lambda_at_grasp_mm", _f64), ("true_width_mm", _f64), ("true_contact_width_mm", _f64),
    ("lambda_error_mm", _f64), ("lambda_error_placement_mm", _f64),
    ("fd", _f64), ("f_min", _f64), ("f_max", _f64), ("f_mean", _f64), ("true_f_min", _f64),
    ("true_f_max", _f64), ("true_f_mean", _f64), ("f_in_band", _bool), ("peak_force", _f64),
    ("iterations", _i64), ("sim_s", _f64), ("wall_s", _f64),
    ("object_kind", _str), ("object_name", _str), ("size_mm", _f64), ("depth_mm", _f64),
    ("friction", _f64), ("mass_g", _f64), ("height_mm", _f64), ("angle_deg", _f64),
    ("seed", _i64), ("gain_factor", _f64), ("sensor_gain", _f64), ("dead_texels", _i64),
    ("spec", _str), ("traceback", _str),
])  # fmt: skip
COLUMNS = tuple(SCHEMA.names)


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def to_table(rows: Sequence[Mapping[str, Any]], info: Mapping[str, Any] | None = None) -> pa.Table:
    data = {name: [_clean(r.get(name)) for r in rows] for name in COLUMNS}
    meta = {METADATA_KEY: json.dumps(info or {}, ensure_ascii=False).encode()}
    return pa.Table.from_pydict(data, schema=SCHEMA.with_metadata(meta))


def _table(out: Path, suite: Suite | None, info: Mapping[str, Any] | None) -> pa.Table:
    """``OUT/cases.jsonl`` as the results' table (in the suite's order; the last row of a case
    recorded twice wins)."""
    from sdh2svc.campaign.run import CAMPAIGN_FILE, read_rows

    rows = {r["id"]: r for r in read_rows(out) if "id" in r}
    if suite is not None:
        ordered = [rows[c.id] for c in suite.cases if c.id in rows]
    else:
        ordered = list(rows.values())
    if info is None and (out / CAMPAIGN_FILE).exists():
        info = json.loads((out / CAMPAIGN_FILE).read_text())
    return to_table(ordered, info)


def write_results(out: Path, *, suite: Suite | None = None,
                  info: Mapping[str, Any] | None = None) -> Path:  # fmt: skip
    """(Re)write ``OUT/results.parquet`` from ``OUT/cases.jsonl`` (see :func:`_table`)."""
    from sdh2svc.campaign.run import RESULTS_FILE

    path = out / RESULTS_FILE
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(_table(out, suite, info), tmp)
    tmp.replace(path)
    return path


def results_from_rows(out: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """What :func:`read_results` would read after :func:`write_results`, without writing."""
    return _rows_and_info(_table(out, None, None))


def _rows_and_info(table: pa.Table) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    meta = table.schema.metadata or {}
    return table.to_pylist(), json.loads(meta.get(METADATA_KEY, b"{}"))


def read_results(out: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The rows and the campaign's metadata of ``OUT/results.parquet``."""
    from sdh2svc.campaign.run import RESULTS_FILE

    return _rows_and_info(pq.read_table(out / RESULTS_FILE))
