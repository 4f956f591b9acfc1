"""The servo tick's precomputed move (:class:`~sdh2svc.sim.sdh2._Move`, its coasting groups): the
references it sets are, bit for bit, the carry's offset and velocity plus the profile's share of
the span, as :meth:`Carry.offset`, :meth:`Carry.velocity`, :meth:`Profile.fraction` and
:meth:`Profile.rate` compute them one axis at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sdh2svc.protocol.sdh import NUM_AXES
from sdh2svc.sim.sdh2 import Carry, Profile, Sdh2Emulator, _Move
from sdh2svc.sim.world import ScriptedWorld

SHAPES = ((14, 6), (13, 6)) * 3


def _reference(move: _Move, tau: float) -> tuple[list[float], list[float]]:
    """References and their velocities, one axis at a time from the public formulas."""
    frac, rate = move.profile.fraction(tau), move.profile.rate(tau)
    ref, rvel = [], []
    for g, s, c in zip(move.goal, move.start, move.carry, strict=True):
        span = g - s - c.distance
        ref.append(s + c.offset(tau) + span * frac)
        rvel.append(c.velocity(tau) + span * rate)
    return ref, rvel


@pytest.mark.parametrize("sin2", [True, False])
def test_the_grouped_carries_give_each_axis_its_own_formula_exactly(sin2: bool) -> None:
    profile = Profile.plan([30.0, -12.0, 5.0, 8.0, 0.0, -3.0, 1.0], [40.0] * NUM_AXES,
                           [300.0] * NUM_AXES, sin2=sin2)  # fmt: skip
    # two axes share a carry time (one group), two have their own, three have none
    carry = (
        Carry.plan(25.0, 300.0, sin2=sin2, at_least=profile.ramp),
        Carry.plan(-25.0, 300.0, sin2=sin2, at_least=profile.ramp),
        Carry.plan(60.0, 300.0, sin2=sin2),
        Carry.plan(-7.0, 150.0, sin2=sin2),
        Carry.plan(0.0, 300.0, sin2=sin2),
        Carry.plan(0.0, 300.0, sin2=sin2),
        Carry.plan(0.0, 300.0, sin2=sin2),
    )
    start = (10.0, -5.5, 3.25, 0.0, -0.0, 7.0, -2.0)
    goal = (40.0, -17.5, 8.25, 8.0, -0.0, 4.0, -1.0)
    move = _Move(start, goal, profile, 2.0, True, carry)
    assert len(move.plain) == 3 and sorted(len(g.axes) for g in move.coast) == [1, 1, 2]
    emu = Sdh2Emulator(ScriptedWorld(SHAPES))
    emu._move = move
    ax = emu._ax
    ax.in_move[:] = [True] * NUM_AXES
    times = [c.time for c in carry if c.time > 0.0]
    taus = [-0.01, 0.0, 1e-4, *(t * f for t in times for f in (0.3, 1.0, 1.7)), profile.ramp,
            move.duration / 2, move.duration - 1e-4]  # fmt: skip
    for tau in taus:
        ax.ref[:], ax.rvel[:] = [math.nan] * NUM_AXES, [math.nan] * NUM_AXES
        emu._follow(move.t0 + tau)
        ref, rvel = _reference(move, move.t0 + tau - move.t0)  # the τ _follow sees
        # bit for bit, signed zeros included
        assert [math.copysign(1.0, r) for r in ax.ref] == [math.copysign(1.0, r) for r in ref]
        assert (ax.ref, ax.rvel) == (ref, rvel), tau


def test_a_blocked_or_finished_axis_keeps_its_reference() -> None:
    profile = Profile.plan([10.0] * NUM_AXES, [40.0] * NUM_AXES, [300.0] * NUM_AXES, sin2=True)
    carry = (Carry.plan(20.0, 300.0, sin2=True, at_least=profile.ramp),) * NUM_AXES
    move = _Move((0.0,) * NUM_AXES, (10.0,) * NUM_AXES, profile, 0.0, True, carry)
    emu = Sdh2Emulator(ScriptedWorld(SHAPES))
    emu._move = move
    ax = emu._ax
    ax.in_move[:] = [True, True, False, True, True, True, True]
    ax.blocked[:] = [0, 1, 0, 0, 0, 0, 0]
    ax.ref[:] = [-1.0] * NUM_AXES
    emu._follow(profile.ramp / 2)
    assert ax.ref[1] == ax.ref[2] == -1.0
    assert ax.ref[0] == ax.ref[3] == _reference(move, profile.ramp / 2)[0][0]


def _plan_reference(d: list[float], v: list[float], a: list[float], sin2: bool) -> Profile:
    """Profile.plan as the formulas read: max over the moving axes, with max()."""
    moving = [(abs(x), vi, ai) for x, vi, ai in zip(d, v, a, strict=True) if abs(x) > 1e-9]
    if not moving:
        return Profile(0.0, 0.0, sin2)
    k = (math.pi / 2 if sin2 else 1.0) * max(x / ai for x, _, ai in moving)
    cruise = max(math.sqrt(k), max(x / vi for x, vi, _ in moving))
    return Profile(cruise + k / cruise, k / cruise, sin2)


@pytest.mark.parametrize("sin2", [True, False])
def test_the_one_pass_profile_plan_is_the_formula(sin2: bool) -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        d = (rng.choice([0.0, 1e-10, 0.3, -2.0, 17.5, -45.0], NUM_AXES) * rng.random()).tolist()
        v = rng.choice([10.0, 40.0, 83.0], NUM_AXES).tolist()  # ties between axes
        a = rng.choice([100.0, 400.0, 1500.0], NUM_AXES).tolist()
        assert Profile.plan(d, v, a, sin2=sin2) == _plan_reference(d, v, a, sin2)
    with pytest.raises(ValueError):
        Profile.plan([1.0, 2.0], [40.0, 0.0], [100.0, 100.0], sin2=sin2)
    assert Profile.plan([1.0, 2e-10], [40.0, 0.0], [100.0, 0.0], sin2=sin2).duration > 0.0
