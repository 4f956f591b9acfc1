"""The recognition models' pairwise products: the radius model's, picked from the kind
model's, are expand's own to the last bit."""

from __future__ import annotations

import numpy as np

from sdh2svc.control.recognition import RADIUS_FEATURES, _sub_expansion, expand


def test_radius_products_picked_from_the_kind_models() -> None:
    rng = np.random.default_rng(5)
    for n in (RADIUS_FEATURES, RADIUS_FEATURES + 1, 69):
        x = rng.normal(size=(2, n)) * 10.0 ** rng.integers(-3, 4, size=(2, n))
        xx = expand(x)
        for row in range(2):
            want = expand(x[row, :RADIUS_FEATURES])
            got = xx[row].take(_sub_expansion(n))
            assert got.tobytes() == want.tobytes()


def test_expand_rows_as_one() -> None:
    x = np.random.default_rng(6).normal(size=(3, 7))
    xx = expand(x)
    i, j = np.triu_indices(7)
    assert xx.tobytes() == np.concatenate([x, x[:, i] * x[:, j]], axis=1).tobytes()
    assert all(xx[r].tobytes() == expand(x[r]).tobytes() for r in range(3))
