"""The immutable value base shared by every configuration and model value."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Frozen(BaseModel):
    """An immutable, validated value: unknown keys are errors, fields never change once made."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class Finite(Frozen):
    """A :class:`Frozen` value whose numbers are finite: NaN and ±∞ are refused as no number
    (named as such, not as a range they fall outside of)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
