"""The controller's own section of the configuration: what a run needs, and nothing else.

:class:`ControlConfig` is built by the composition root (``Settings.control()``), so the
controller never sees the service's, the links' or the simulator's settings.
"""

from __future__ import annotations

from dataclasses import dataclass

from sdh2svc.control.params import RollingParams
from sdh2svc.control.safety import RunConfig, SafetyConfig
from sdh2svc.model.hand import AxisMap, JointLimits
from sdh2svc.model.observe import ModelContext


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """A run's configuration: the model, the wiring, the limits, the phases, the supervisor."""

    ctx: ModelContext
    axes: AxisMap
    limits: JointLimits
    run: RunConfig
    safety: SafetyConfig
    rolling: RollingParams  # the parameters a run starts with unless it is given others
