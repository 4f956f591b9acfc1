"""The proximal links are obstacles too: an object low between them presses their pads."""

from __future__ import annotations

import numpy as np

from sdh2svc.config import load_config
from sdh2svc.connect import hand_model
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import parse_object


def test_object_between_the_proximal_links_presses_their_pads() -> None:
    cfg = load_config(overrides=["sim.sensor.noise=false", "sim.sensor.creep=false"],
                      use_env=False)  # fmt: skip
    ball = parse_object({"kind": "circle", "name": "ball", "diameter_mm": 42, "depth_mm": 30})
    world = PhysicsWorld(hand_model(cfg), cfg.sim, ball)
    world.place(ball, height_mm=55.0)  # below the fingertips, level with the proximal pads
    off = np.cumsum([0] + [r * c for r, c in world.matrix_shapes])
    a = cfg.axes
    q = [90.0, -20.0, 20.0, 0.0, 0.0, -20.0, 20.0]
    sums: list[int] = [0] * 6
    for i in range(300):
        q[a.phi2] += 0.1
        q[a.phi4] += 0.1
        world.move_joints(0.02 * (i + 1), q, [True] * 7)
        frame = world.tactile_frame(0.02 * (i + 1), [0.5] * 6, [0] * 6)
        sums = [int(frame[off[k] : off[k + 1]].sum()) for k in range(6)]
        if min(sums[a.finger1_proximal_matrix], sums[a.finger2_proximal_matrix]) > 1000:
            break
    assert sums[a.finger1_proximal_matrix] > 1000 and sums[a.finger2_proximal_matrix] > 1000
    assert sums[a.finger1_distal_matrix] == sums[a.finger2_distal_matrix] == 0
    surfaces = {c.surface for c in world.truth().contacts}
    assert surfaces == {"proximal1", "proximal2"}
    # symmetric pose, symmetric object: both proximal pads read the same (solver tolerance)
    p1, p2 = sums[a.finger1_proximal_matrix], sums[a.finger2_proximal_matrix]
    assert abs(p1 - p2) <= 0.02 * max(p1, p2)
