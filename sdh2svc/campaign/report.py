"""A campaign's report (``report.md`` and PNG plots) and the comparison of two campaigns."""

from __future__ import annotations

import json
import math
import statistics
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from sdh2svc.campaign.case import FAMILIES

Row = Mapping[str, Any]


def load(out: Path, *, refresh: bool = False) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """A campaign's rows and metadata, from ``cases.jsonl`` where there is one (the newest:
    a killed campaign's ``results.parquet`` lags behind it), else ``results.parquet``.
    ``refresh``: ``results.parquet`` is rewritten from ``cases.jsonl`` too (``report``, which
    writes into the folder anyway); else nothing in the folder is written (``compare``'s inputs
    may be read-only, or a reference). A folder that holds no campaign is refused; a file of a
    campaign that cannot be read (cut short, overwritten) is refused naming it (exit 2), one
    that cannot be written (exit 4)."""
    from pyarrow import ArrowException

    from sdh2svc.campaign.results import read_results, results_from_rows, write_results
    from sdh2svc.campaign.run import (
        CAMPAIGN_FILE,
        CASES_FILE,
        RESULTS_FILE,
        CampaignError,
        read_rows,
    )  # fmt: skip

    cases, results = out / CASES_FILE, out / RESULTS_FILE
    if not cases.exists() and not results.exists():
        raise FileNotFoundError(f"no campaign in {out} (no {CASES_FILE} or {RESULTS_FILE})")
    try:
        if cases.exists():
            if not (out / CAMPAIGN_FILE).exists():
                raise CampaignError(3, f"no campaign in {out}: {CASES_FILE} without the "
                                    f"{CAMPAIGN_FILE} a campaign run writes first")  # fmt: skip
            if not read_rows(out):  # (it keeps only results)
                raise CampaignError(2, f"{cases}: no case's result in it")
            if refresh:
                try:
                    write_results(out)
                except OSError as e:
                    raise CampaignError(4, f"cannot write {results}: {e.strerror or e}") from None
            return results_from_rows(out)
        return read_results(out)
    except (ArrowException, ValueError, TypeError, OSError) as e:  # json's are ValueErrors
        if isinstance(e, FileNotFoundError):
            raise
        raise CampaignError(2, f"cannot read the campaign in {out}: {e}") from None


def percent(k: int, n: int) -> str:
    """k of n as a percentage rounded to a tenth (43/60: 71.7 %), but never up onto a whole
    number, where a target is (1899/2000: 94.9 %, not 95 %); whole numbers without the
    decimal. Every rate of ``campaign report`` and ``compare`` is written by it."""
    tenths = (2000 * k + n) // (2 * n)  # rounded half up, in integers: no float's error
    if tenths % 10 == 0 and tenths * n > 1000 * k:  # rounded up onto a whole number
        tenths -= 1
    return f"{tenths // 10} %" if tenths % 10 == 0 else f"{tenths / 10:.1f} %"


def interval(k: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate k/n: where the rate over everything the
    generator draws lies, given n of its cases (scipy.stats.binomtest)."""
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def span(lo: float, hi: float) -> str:
    """An interval in percent to a tenth, rounded outwards (never narrower than it is)."""
    return f"{math.floor(lo * 1000 + 1e-9) / 10:.1f}–{math.ceil(hi * 1000 - 1e-9) / 10:.1f} %"


def paired_p(better: int, worse: int) -> float:
    """McNemar's exact test on paired verdicts: the two-sided chance of a split at least this
    uneven among the ``better + worse`` cases whose verdict changed, were a change as likely
    one way as the other (1 when none changed)."""
    if better + worse == 0:
        return 1.0
    from scipy.stats import binomtest

    return float(binomtest(better, better + worse, 0.5).pvalue)


def judged_rows(rows: Sequence[Row]) -> list[Row]:
    """The cases with a verdict: all but the crashed."""
    return [r for r in rows if r["status"] != "crashed"]


def rate(rows: Sequence[Row]) -> str:
    """Successes over the cases judged: a crashed case is no result (the same ``campaign run``
    runs it again), counted apart (:func:`crash_note`)."""
    judged = judged_rows(rows)
    n = len(judged)
    ok = sum(1 for r in judged if r["success"])
    return f"{ok}/{n} ({percent(ok, n)})" if n else "–"


def crash_note(rows: Sequence[Row]) -> list[str]:
    """A line saying how many cases crashed and are left out of every rate (none: no line)."""
    n = len(rows) - len(judged_rows(rows))
    if not n:
        return []
    return [f"**{n} case{'' if n == 1 else 's'} crashed: no result, left out of every rate "
            "below** (the same `campaign run` runs them again).", ""]  # fmt: skip


def _rules(info: Mapping[str, Any]) -> dict[str, Any]:
    """A campaign's judging rules, with what a campaign recorded before a rule was named (the
    band on the controller's F) filled in."""
    return {**(info.get("judge") or {}), "f_band_on": band_judged_on(info)}


def band_judged_on(info: Mapping[str, Any]) -> str:
    """What the F band was judged on in a campaign: its ``judge`` record says; campaigns
    recorded before the truth's grip was judged the controller's own F."""
    return str((info.get("judge") or {}).get("f_band_on") or "the controller's F")


def by(rows: Iterable[Row], key: Callable[[Row], Any]) -> dict[Any, list[Row]]:
    groups: dict[Any, list[Row]] = defaultdict(list)
    for r in rows:
        groups[key(r)].append(r)
    return groups


def _family_order(fams: Iterable[str]) -> list[str]:
    fams = set(fams)
    return [f for f in FAMILIES if f in fams] + sorted(fams - set(FAMILIES))


def _fmt(x: Any, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _stats(values: Sequence[float]) -> str:
    import numpy as np

    if not values:
        return "–"
    a = np.asarray(values, dtype=float)
    return (f"median {np.median(a):.2f}, 5–95 % {np.percentile(a, 5):.2f} … "
            f"{np.percentile(a, 95):.2f} (n = {len(a)})")  # fmt: skip


RIGID_N_PER_MM3 = 0.5  # objects at least this stiff (2.5 × the pads' rubber) count as rigid
LAMBDA_TOLERANCE_MM = 1.7  # the texel uncertainty (thesis §4.2.2: ±1.7 mm per sensor)
GAIN_BANDS = ((0.5, 0.75), (0.75, 1.0), (1.0, 1.25), (1.25, 1.5))
CREEP_BANDS = ((0.05, 0.1125), (0.1125, 0.175), (0.175, 0.2375), (0.2375, 0.3))  # the generator's


def _spec_value(r: Row, *path: str) -> float | None:
    """A number from the case's spec (JSON), e.g. ``("sensor", "creep_gain")``; None if absent."""
    try:
        value: Any = json.loads(r["spec"])
        for key in path:
            value = value[key]
        return None if value is None else float(value)
    except (KeyError, TypeError, ValueError):
        return None


Band = tuple[float, float]


def _band_rows(
    rows: Sequence[Row], value: Callable[[Row], float | None], bands: Sequence[Band]
) -> list[tuple[float, float, list[Row]]]:
    """Each band's rows by ``value`` (lo ≤ v < hi, the last band closed at hi); rows without a
    value in none."""
    out = []
    for lo, hi in bands:
        last = hi == bands[-1][1]
        out.append((lo, hi, [r for r in rows if (v := value(r)) is not None
                             and (lo <= v < hi or (last and v == hi))]))  # fmt: skip
    return out


def _share(rows: Sequence[Row], ok: Callable[[Row], bool]) -> str:
    n = len(rows)
    k = sum(1 for r in rows if ok(r))
    return f"{k}/{n} ({percent(k, n)})" if n else "–"


def _headline(rows: Sequence[Row]) -> list[str]:
    """The controller's targets: no drop, Λ at grasp on rigid objects, success per gain and
    creep band."""
    stiffness = ("object", "material", "stiffness_n_per_mm3")
    rigid = [r for r in rows if (_spec_value(r, *stiffness) or 0.0) >= RIGID_N_PER_MM3
             and r["lambda_error_mm"] is not None]  # fmt: skip
    lines = [
        "",
        f"* **without a drop**: {_share(rows, lambda r: not r['dropped'])}",
        f"* **Λ at grasp within {LAMBDA_TOLERANCE_MM} mm** of the true contact width (the "
        "distance between the simulation's contact points on the object at the first "
        f"iteration), rigid objects (≥ {RIGID_N_PER_MM3} N/mm³) that reached an iteration: "
        f"{_share(rigid, lambda r: abs(r['lambda_error_mm']) <= LAMBDA_TOLERANCE_MM)}",
    ]

    def ok(r: Row) -> bool:
        return bool(r["success"])

    gain = _band_rows(rows, lambda r: r["gain_factor"], GAIN_BANDS)
    lines.append("* success by the sensor's gain factor: "
                 + ", ".join(f"×{lo}–{hi}: {_share(b, ok)}" for lo, hi, b in gain))  # fmt: skip
    creep = _band_rows(rows, lambda r: _spec_value(r, "sensor", "creep_gain"), CREEP_BANDS)
    bands = [f"{lo}–{hi}: {_share(b, ok)}" for lo, hi, b in creep if b]
    if bands:
        lines.append("* success by the sensor's creep gain (the share of a load that creeps in): "
                     + ", ".join(bands))  # fmt: skip
    return lines


def _interval_line(rows: Sequence[Row], generated: bool = True) -> list[str]:
    """The overall rate's 95 % interval: what the cases' number leaves open (over what the
    suite's generator draws; a hand-written suite's cases are a population of their own)."""
    n = len(rows)
    if not n:
        return []
    lo, hi = interval(sum(1 for r in rows if r["success"]), n)
    over = ("everything the suite's generator draws" if generated
            else "objects like these (a suite written by hand: no generator)")  # fmt: skip
    return [f"95 % interval for the success rate over {over}: "
            f"{span(lo, hi)} (Wilson score, {n} cases).", ""]  # fmt: skip


def write_report(out: Path) -> Path:
    """``OUT/report.md`` and its plots (``OUT/plots/*.png``); ``OUT/results.parquet`` brought
    up to date with ``OUT/cases.jsonl``. Rates, shares and plots are over the judged cases; the
    crashed ones are counted apart and listed."""
    every, info = load(out, refresh=True)
    rows = judged_rows(every)
    plots = out / "plots"
    plots.mkdir(exist_ok=True)
    lines = [f"# Campaign {info.get('suite', out.name)}", ""]
    code = info.get("code") or {}
    lines += [
        f"Suite `{info.get('suite')}` v{info.get('suite_version')} "
        f"(digest {info.get('suite_digest')}), {len(every)} of {info.get('cases', len(every))} "
        f"cases recorded; sdh2svc {code.get('version')} ({code.get('git_describe') or 'no git'})"
        f"; `--set` {' '.join(info.get('overrides') or []) or 'none'}.",
        "",
        "Success (`sdh2svc.campaign.run.judge`): completed every stroke, every half stroke "
        "turned the object ≥ 1° (the largest excursion of its true angle ψ within the half "
        "stroke), no drop, every grip after the grasp within [0.25, 2.5] × Fd, judged on "
        f"{band_judged_on(info)}.",
        "",
        *crash_note(every),
        f"**Success overall: {rate(rows)}**",
        "",
        *_interval_line(rows, info.get("generator_seed") is not None),
        "| family | cases | success | Λ error mm (median) | wall s per case (mean) |",
        "|---|---|---|---|---|",
    ]
    fams = by(rows, lambda r: r["family"])
    for fam in _family_order(fams):
        rs = fams[fam]
        errs = sorted(r["lambda_error_mm"] for r in rs if r["lambda_error_mm"] is not None)
        walls = [r["wall_s"] for r in rs if r["wall_s"] is not None]
        med = statistics.median(errs) if errs else None  # (the mean of two middle ones)
        lines.append(f"| {fam} | {len(rs)} | {rate(rs)} | {_fmt(med)} | "
                     f"{_fmt(sum(walls) / len(walls) if walls else None, 1)} |")  # fmt: skip
    lines += _headline(rows)
    lines += ["", "## Failure reasons", "", "| reason | cases |", "|---|---|"]
    reasons = Counter(r["failure"] for r in rows if not r["success"])
    lines += [f"| {k} | {v} |" for k, v in reasons.most_common()] or ["| – | 0 |"]
    crashed = [r for r in every if r["status"] == "crashed"]
    if crashed:
        lines += ["", "Crashed cases (last line of the traceback):", ""]
        for r in crashed[:20]:
            last = (r["traceback"] or "").strip().splitlines()[-1:] or ["(no traceback)"]
            lines.append(f"* `{r['id']}`: `{last[0]}`")
        if len(crashed) > 20:
            lines.append(f"* … and {len(crashed) - 20} more (see `results.parquet`)")
    lines += ["", "## Distributions", ""]
    lam = [r["lambda_error_mm"] for r in rows if r["lambda_error_mm"] is not None]

    def x_fd(key: str) -> list[float]:
        return [r[key] / r["fd"] for r in rows if r.get(key) is not None and r["fd"]]

    rot = [h for r in rows for h in (r["half_stroke_rotation_deg"] or [])]
    lines += [
        f"* Λ at grasp − true contact width (mm): {_stats(lam)}",
        f"* lowest true grip after the grasp (× Fd): {_stats(x_fd('true_f_min'))}",
        f"* highest true grip after the grasp (× Fd): {_stats(x_fd('true_f_max'))}",
        f"* lowest F the controller read after the grasp (× Fd): {_stats(x_fd('f_min'))}",
        f"* highest F the controller read after the grasp (× Fd): {_stats(x_fd('f_max'))}",
        f"* true rotation per half stroke (°): {_stats(rot)}",
        "",
    ]
    figs = _plots(rows, plots)
    lines += ["## Plots", ""] + [f"![{name}](plots/{name}.png)" for name in figs]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _plots(rows: Sequence[Row], plots: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    made = []

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        fig.savefig(plots / f"{name}.png", dpi=90)
        plt.close(fig)
        made.append(name)

    fams = by(rows, lambda r: r["family"])
    order = _family_order(fams)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    vals = [sum(r["success"] for r in fams[f]) / len(fams[f]) for f in order]
    ax.bar(["all", *order], [sum(r["success"] for r in rows) / max(1, len(rows)), *vals])
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate")
    save(fig, "success_by_family")

    def success_map(xkey: str, ykey: str, xlabel: str, ylabel: str, name: str) -> None:
        pts = [(r[xkey], r[ykey], r["success"]) for r in rows
               if r[xkey] is not None and r[ykey] is not None]  # fmt: skip
        if not pts:
            return
        x, y, s = (np.asarray(v, dtype=float) for v in zip(*pts, strict=True))

        def edges(v: Any) -> Any:  # bins around every point, a point alone included
            pad = max(0.05 * (v.max() - v.min()), 0.02 * (abs(v.max()) + 1e-6))
            return np.linspace(v.min() - pad, v.max() + pad, min(8, len(set(v))) + 1)

        xb, yb = edges(x), edges(y)
        n, _, _ = np.histogram2d(x, y, bins=(xb, yb))
        k, _, _ = np.histogram2d(x, y, bins=(xb, yb), weights=s)
        with np.errstate(invalid="ignore", divide="ignore"):
            grid = np.where(n > 0, k / n, np.nan)
        fig, ax = plt.subplots(figsize=(5.5, 4))
        im = ax.pcolormesh(xb, yb, grid.T, vmin=0, vmax=1, cmap="RdYlGn")
        fig.colorbar(im, ax=ax, label="success rate")
        ax.scatter(x, y, c=["g" if v else "r" for v in s], s=8, edgecolors="k", linewidths=0.3)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        save(fig, name)

    success_map("true_width_mm", "friction", "contact width (mm)", "friction μ",
                "map_width_friction")  # fmt: skip
    success_map("height_mm", "size_mm", "placement height (mm)", "object size (mm)",
                "map_height_size")  # fmt: skip

    gains = sorted({r["gain_factor"] for r in rows if r["gain_factor"] is not None})
    if gains and order:
        gb = np.linspace(min(gains), max(gains) + 1e-9, min(6, len(gains)) + 1)
        grid = np.full((len(order), len(gb) - 1), np.nan)
        for i, f in enumerate(order):
            g = np.asarray([r["gain_factor"] for r in fams[f]], dtype=float)
            s = np.asarray([r["success"] for r in fams[f]], dtype=float)
            idx = np.clip(np.digitize(g, gb) - 1, 0, len(gb) - 2)
            for j in range(len(gb) - 1):
                if (idx == j).any():
                    grid[i, j] = s[idx == j].mean()
        fig, ax = plt.subplots(figsize=(6, 0.5 * len(order) + 2))
        im = ax.pcolormesh(gb, np.arange(len(order) + 1), grid, vmin=0, vmax=1, cmap="RdYlGn")
        ax.set_yticks(np.arange(len(order)) + 0.5, order)
        ax.set_xlabel("sensor gain factor (× nominal)")
        fig.colorbar(im, ax=ax, label="success rate")
        save(fig, "map_gain_family")

    reasons = Counter(r["failure"] for r in rows if not r["success"])
    if reasons:
        fig, ax = plt.subplots(figsize=(7, 0.4 * len(reasons) + 1.5))
        names, counts = zip(*reasons.most_common(), strict=True)
        ax.barh(names, counts)
        ax.invert_yaxis()
        ax.set_xlabel("cases")
        save(fig, "failure_reasons")

    for key, label, name in (
        ("lambda_error_mm", "Λ at grasp − true contact width (mm)", "dist_lambda_error"),
        ("f_mean", "mean F the controller read after the grasp", "dist_force"),
        ("mean_stroke_rotation_deg", "true rotation per stroke (°)", "dist_rotation"),
    ):
        vals = [r[key] for r in rows if r[key] is not None]
        if not vals:
            continue
        fig, ax = plt.subplots(figsize=(5.5, 3.2))
        ax.hist(vals, bins=min(30, max(5, len(vals) // 3)))
        ax.set_xlabel(label)
        ax.set_ylabel("cases")
        save(fig, name)
    return made


def _paired(better: int, worse: int) -> str:
    """Whether the cases that changed verdict say more than chance (McNemar, 5 % level)."""
    if better + worse == 0:
        return "Paired on the cases in both: no verdict changed."
    p = paired_p(better, worse)
    verdict = "significant at the 5 % level" if p < 0.05 else "not significant at the 5 % level"
    return (
        f"Paired on the cases in both: B better on {better}, worse on {worse}. McNemar's "
        f"exact test (the split of the {better + worse} changed verdicts against an even "
        f"one): p = {p:.3f}, {verdict}."
    )


def _campaign_line(label: str, out: Path, info: Mapping[str, Any]) -> str:
    """``A: `DIR` suite S (sdh2svc V, DESCRIBE), `--set` …``: which campaign a column is."""
    code, sets = info.get("code") or {}, " ".join(info.get("overrides") or []) or "none"
    return (
        f"{label}: `{out}` suite {info.get('suite')} (sdh2svc {code.get('version')}, "
        f"{code.get('git_describe')}), `--set` {sets}"
    )


def compare(a: Path, b: Path) -> str:
    """Markdown: the two campaigns' success rates side by side, and case by case what changed."""
    ra, ia = load(a)
    rb, ib = load(b)
    da, db = {r["id"]: r for r in ra}, {r["id"]: r for r in rb}
    # a case is paired with the same case: the same id and the same object, placement and
    # sensor (packaged suites share ids such as box-000 for different objects)
    common = [i for i in da if i in db and da[i]["spec"] == db[i]["spec"]]
    unpaired = [i for i in da if i in db and da[i]["spec"] != db[i]["spec"]]
    notes = []
    if ia.get("suite_digest") != ib.get("suite_digest"):
        notes += ["", f"The suites differ (digest {ia.get('suite_digest')} and "
                  f"{ib.get('suite_digest')}): only cases with the same id and spec are "
                  "paired."]  # fmt: skip
    if _rules(ia) != _rules(ib):
        notes += ["", f"**The two were judged by different rules** (A: {ia.get('judge')}, "
                  f"B: {ib.get('judge')}; the F band on {band_judged_on(ia)} in A, on "
                  f"{band_judged_on(ib)} in B): a changed verdict may be the rule's, not the "
                  "controller's."]  # fmt: skip
    if unpaired:
        notes += ["", f"**{len(unpaired)} cases share an id but not their spec (object, "
                  "placement, sensor): they are other cases, not paired** "
                  f"(e.g. {', '.join(unpaired[:3])}; different suites?)"]  # fmt: skip
    lines = [f"# {a} vs {b}", "", _campaign_line("A", a, ia), _campaign_line("B", b, ib), *notes,
             "", "| family | A | B |", "|---|---|---|",
             f"| **all** | {rate(ra)} | {rate(rb)} |"]  # fmt: skip
    fa, fb = by(ra, lambda r: r["family"]), by(rb, lambda r: r["family"])
    for fam in _family_order(set(fa) | set(fb)):
        lines.append(f"| {fam} | {rate(fa.get(fam, []))} | {rate(fb.get(fam, []))} |")
    # a crash is no result (the campaign runs it again): no verdict to pair, either way
    crashed = [i for i in common if "crashed" in (da[i]["status"], db[i]["status"])]
    judged = [i for i in common if i not in set(crashed)]
    better = [i for i in judged if not da[i]["success"] and db[i]["success"]]
    worse = [i for i in judged if da[i]["success"] and not db[i]["success"]]
    changed = [i for i in judged if not da[i]["success"] and not db[i]["success"]
               and da[i]["failure"] != db[i]["failure"]]  # fmt: skip
    lines += ["", f"{len(common)} cases in both; only in A: {len(set(da) - set(common))}, "
              f"only in B: {len(set(db) - set(common))}."]  # fmt: skip
    if crashed:
        lines += ["", f"**{len(crashed)} of them crashed in A or B: no verdict, not compared** "
                  f"(e.g. {', '.join(crashed[:3])}; the same `campaign run` runs a crashed "
                  "case again)."]  # fmt: skip
    lines += ["", _paired(len(better), len(worse)), ""]
    for title, ids in (("Better in B (failed in A, succeeded in B)", better),
                       ("Worse in B (succeeded in A, failed in B)", worse),
                       ("Failed in both, for another reason", changed)):  # fmt: skip
        lines += [f"## {title}: {len(ids)}", ""]
        if ids:
            lines += ["| case | family | A | B |", "|---|---|---|---|"]
            for i in ids:
                lines.append(f"| {i} | {da[i]['family']} | {da[i]['failure'] or 'success'} | "
                             f"{db[i]['failure'] or 'success'} |")  # fmt: skip
            lines.append("")
    return "\n".join(lines) + "\n"
