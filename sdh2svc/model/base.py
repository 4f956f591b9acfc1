"""The immutable value base shared by every configuration and model value."""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict


class Finite(BaseModel):
    """An immutable, validated value: unknown keys are errors, fields never change once made,
    and numbers are finite: NaN and ±∞ are refused as no number (named as such, not as a range
    they fall outside of)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


def clean_json(obj: Any) -> Any:
    """JSON has no NaN or infinity: null in their place (the dashboard treats it as a gap)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [clean_json(v) for v in obj]
    return obj
