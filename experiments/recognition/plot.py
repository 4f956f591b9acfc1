"""Plot the rotation estimate against the true rotation for captured runs (one panel each).

    python -m experiments.recognition.plot /tmp/recog/thesis.jsonl rubber egg cylinder \\
        --out experiments/recognition/rotation.png
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from experiments.recognition.evaluate import context, load_cases, run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("ids", nargs="+")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    ctx = context()
    from sdh2svc.control.recognition import packaged_model

    cases = [c for c in load_cases(a.capture, ctx) if c.id in a.ids]
    fig, axes = plt.subplots(len(cases), 1, figsize=(8, 2.4 * len(cases)), squeeze=False)
    for ax, case in zip(axes[:, 0], cases, strict=True):
        recs = run(case, ctx, packaged_model())
        idx = [
            i for i, s in enumerate(case.steps) if s.obs.Lambda is not None and s.psi is not None
        ]
        i0 = idx[0]
        psi0 = case.steps[i0].psi
        assert psi0 is not None
        true = np.degrees([case.steps[i].psi - psi0 for i in idx])  # type: ignore[operator]
        est = [recs[i].rotation - recs[i0].rotation for i in idx]
        ax.plot(idx, true, label="true ψ − ψ₀", lw=2, color="0.6")
        ax.plot(idx, est, label="rolling kinematics", lw=1, color="C0")
        ax.set_title(case.id, fontsize=9)
        ax.set_ylabel("deg")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("rolling iteration")
    fig.tight_layout()
    fig.savefig(a.out, dpi=80)


if __name__ == "__main__":
    main()
