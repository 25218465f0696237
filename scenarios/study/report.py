"""A study's report: per-axis heat maps and curves, the bound beside the simulation everywhere,
and the cheapest design meeting a target.

Written into the study folder: ``report.md`` (every design's table; the target's answer),
``heatmap_fusedN.png`` (two varied parameters: per axis, the simulation's RMS above and the
bound below, on the same colour scale) and ``curve_PARAM.png`` (per axis, RMS against one
parameter: the simulation as markers, the bound as a dashed line of the same colour, a line per
scans fused). matplotlib, headless (Agg).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.study.results import EDGE, DesignResult, cheapest, export_parquet, summarize
from scenarios.study.store import StudyStore

#: The axes a plot shows (y, the distance, is the best known: left to the table).
PLOT_AXES = ("x_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")


def write(store: StudyStore, target: dict[str, float] | None = None,
          within_s: float | None = None, by: str = "sim", progress: bool = False
          ) -> tuple[Path, list[DesignResult], DesignResult | None]:
    """Write the report and the Parquet exports; (report.md, the results, the cheapest).
    progress: show each step on stderr (`scenarios.progress.Bar`): a report of many designs
    takes seconds (matplotlib, a figure per parameter)."""
    import matplotlib

    from scenarios.progress import Bar

    matplotlib.use("Agg")
    results = summarize(store)
    spec = store.get("spec")
    params = _varied(results)
    plotted = _plotted(results)
    figures = []
    numeric = [p for p in plotted if p != "scans_fused" and all(
        _is_number(r.params.get(p)) for r in results)]
    fused = sorted({r.fused for r in results}) if len(numeric) >= 2 else []
    steps = 2 + len(fused) + len(plotted)  # exports, figures, report.md
    with Bar(steps, "report", unit="steps", every=1, enabled=progress) as bar:
        bar.set_status("the Parquet exports")
        export_parquet(store, results)
        for n in fused:
            bar.update(1, status=f"heat map of {numeric[0]} x {numeric[1]}, {n} fused")
            figures.append(_heatmap(store.folder, [r for r in results if r.fused == n],
                                    numeric[0], numeric[1], n))
        for p in plotted:
            bar.update(1, status=f"curve of {p}")
            figures.append(_curve(store.folder, results, p))
        bar.update(1, status="report.md")
        best = cheapest(results, target, within_s, by) if target else None
        md = store.folder / "report.md"
        md.write_text(_markdown(store, spec, results, params, figures, target, within_s, by,
                                best), encoding="utf-8")
        bar.update(1, status="done")
    return md, results, best


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _varied(results: list[DesignResult]) -> list[str]:
    """The study's parameters, scans fused too when the study has several values of it."""
    names: list[str] = []
    for r in results:
        names += [k for k in r.params if k not in names]
    return names + (["scans_fused"] if len({r.fused for r in results}) > 1 else [])


def _plotted(results: list[DesignResult]) -> list[str]:
    """The parameters that take more than one value (a grid key with one value, such as the
    diamond study's board height, is a setting, not an axis of a figure)."""
    return [p for p in _varied(results)
            if len({repr(_value(r, p)) for r in results}) > 1]


def _value(r: DesignResult, p: str) -> Any:
    return r.fused if p == "scans_fused" else r.params.get(p)


def _heatmap(folder: Path, results: list[DesignResult], px: str, py: str, n: int) -> Path:
    import matplotlib.pyplot as plt

    xs = sorted({r.params[px] for r in results})
    ys = sorted({r.params[py] for r in results})
    full = len(xs) * len(ys) <= len(results) and len(xs) > 1 and len(ys) > 1
    fig, axes = plt.subplots(2, len(PLOT_AXES), figsize=(3.2 * len(PLOT_AXES), 6.0),
                             squeeze=False, constrained_layout=True)
    for j, name in enumerate(PLOT_AXES):
        k = EDGE.index(name)
        sim = np.array([r.rms[k] for r in results])
        bound = np.array([r.bound[k] for r in results])
        both = np.concatenate((sim, bound))
        lo, hi = (np.nanmin(both), np.nanmax(both)) if np.isfinite(both).any() else (0.0, 1.0)
        for row, (label, values) in enumerate((("simulation", sim), ("bound", bound))):
            ax = axes[row, j]
            if full:
                grid = np.full((len(ys), len(xs)), np.nan)
                for r, v in zip(results, values, strict=True):
                    grid[ys.index(r.params[py]), xs.index(r.params[px])] = v
                # One cell per grid value, evenly spaced whatever the values' steps (2000,
                # 2500, 3000, 4000 mm would otherwise draw cells of different sizes).
                im = ax.imshow(grid, origin="lower", aspect="auto", vmin=lo, vmax=hi,
                               cmap="viridis")
                ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs])
                ax.set_yticks(range(len(ys)), [f"{y:g}" for y in ys])
                for yi in range(len(ys)):
                    for xi in range(len(xs)):
                        if np.isfinite(grid[yi, xi]):
                            ax.text(xi, yi, f"{grid[yi, xi]:.3g}", ha="center", va="center",
                                    fontsize=7, color="white")
            else:
                im = ax.scatter([r.params[px] for r in results],
                                [r.params[py] for r in results], c=values, vmin=lo, vmax=hi,
                                cmap="viridis", s=60)
            ax.set_title(f"{name.replace('_', ' RMS, ')} ({label})", fontsize=9)
            ax.set_xlabel(px, fontsize=8)
            ax.set_ylabel(py, fontsize=8)
            ax.tick_params(labelsize=7)
            if row == 1:
                fig.colorbar(im, ax=axes[:, j], shrink=0.8)
    fig.suptitle(f"RMS error per axis, {n} scan{'s' if n > 1 else ''} fused: simulation (top) "
                 "and bound (bottom); failed estimates left out", fontsize=10)
    path = folder / f"heatmap_fused{n}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


#: Most series one panel of a curve shows (tab20's colours); more is the table's job.
MAX_SERIES = 20


def _curve(folder: Path, results: list[DesignResult], p: str) -> Path:
    """RMS against `p`, per axis (columns); one row per scans fused when the study has several
    (so that a panel's lines differ by the other parameters only), a line per combination of
    the other parameters, the bound dashed in the same colour."""
    import matplotlib.pyplot as plt

    values = [_value(r, p) for r in results]
    numeric = all(_is_number(v) for v in values)
    ticks = sorted(set(values), key=lambda v: (str(type(v)), v))
    plotted = _plotted(results)
    by_fused = p != "scans_fused" and "scans_fused" in plotted
    fused_rows = sorted({r.fused for r in results}) if by_fused else [None]
    others = [q for q in plotted if q != p and q != "scans_fused"] + (
        ["scans_fused"] if not by_fused and p != "scans_fused" and "scans_fused" in plotted
        else [])

    def series_key(r: DesignResult) -> tuple:
        return tuple((q, _value(r, q)) for q in others)

    nrows = len(fused_rows)
    fig, axes = plt.subplots(nrows, len(PLOT_AXES), figsize=(3.4 * len(PLOT_AXES),
                                                             0.6 + 3.0 * nrows),
                             squeeze=False, constrained_layout=True)
    colors = plt.colormaps["tab20"].colors
    omitted = 0
    handles: dict[str, Any] = {}
    for row, n in enumerate(fused_rows):
        groups: dict[tuple, list[DesignResult]] = {}
        for r in results:
            if n is None or r.fused == n:
                groups.setdefault(series_key(r), []).append(r)
        shown = list(groups.items())[:MAX_SERIES]
        omitted = max(omitted, len(groups) - len(shown))
        for j, name in enumerate(PLOT_AXES):
            ax = axes[row, j]
            k = EDGE.index(name)
            for c, (key, rows) in enumerate(shown):
                rows = sorted(rows, key=lambda r: ticks.index(_value(r, p)))
                x = [(_value(r, p) if numeric else ticks.index(_value(r, p))) for r in rows]
                color = colors[(2 * c) % 20 if len(shown) <= 10 else c % 20]
                label = ", ".join(f"{q}={v:g}" if _is_number(v) else f"{q}={v}"
                                  for q, v in key) or "simulation"
                (line,) = ax.plot(x, [r.rms[k] for r in rows], "o-", color=color, ms=4)
                ax.plot(x, [r.bound[k] for r in rows], "--", color=color)
                handles.setdefault(label, line)
            if not numeric:
                ax.set_xticks(range(len(ticks)), [str(t) for t in ticks])
            title = name.replace("_", " RMS, ")
            ax.set_title(title + (f", {n} scan{'s' if n > 1 else ''} fused" if n else ""),
                         fontsize=9)
            ax.set_xlabel(p, fontsize=8)
            ax.tick_params(labelsize=7)
            ax.set_ylim(bottom=0)
    if len(handles) > 1 or (handles and "simulation" not in handles):
        fig.legend(list(handles.values()), list(handles), fontsize=7, loc="outside right upper")
    more = f"; {omitted} more series in the table" if omitted else ""
    fig.suptitle(f"RMS error against {p}: simulation (markers) and bound (dashed){more}",
                 fontsize=10)
    path = folder / f"curve_{_safe(p)}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")


def _fmt(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.3g}"


def _markdown(store: StudyStore, spec: dict, results: list[DesignResult], params: list[str],
              figures: list[Path], target: dict | None, within_s: float | None, by: str,
              best: DesignResult | None) -> str:
    p = spec["protocol"]
    lines = [f"# Study: {spec['name']}", "", spec.get("description") or "", "",
             f"Station: {store.get('station')['name']}; seed {spec['seed']}; method "
             f"{spec['method']}; {p['poses']} poses x {p['scans']} scans per design point "
             f"(mount angles within +-{p['angle_deg']:g} deg, x within +-{p['x_mm']:g} mm, "
             f"stage yaw within +-{p['stage_yaw_deg']:g} deg); status {store.status}.", "",
             "Per axis (station frame): RMS error of the simulation against the twin's truth | "
             "the bound's RMS over the same poses | their ratio; chi2 = mean (error / sigma)^2 "
             "(1: an honest sigma). Failed estimates are counted and left out of the errors.", ""]
    if target:
        goal = ", ".join(f"{k} <= {v:g}" for k, v in target.items())
        within = f" within {within_s:g} s" if within_s is not None else ""
        lines += ["## The cheapest design", "",
                  f"Target ({'simulation' if by == 'sim' else 'bound'}): {goal}{within} "
                  "(time: the scans fused at 10 scans/s plus one estimate's CPU time; cheapest: "
                  "the smallest board, then the shortest time; at most 1 % failed estimates).",
                  ""]
        if best is None:
            lines += ["No design of this study meets it.", ""]
        else:
            desc = ", ".join(f"{k} = {v}" for k, v in best.params.items())
            vals = "; ".join(f"{k} {best.rms[EDGE.index(k)]:.3g} (bound "
                             f"{_fmt(best.bound[EDGE.index(k)])})" for k in target)
            lines += [f"**Design point {best.point}**: {desc}, {best.fused} scan(s) fused: "
                      f"{vals}; {best.time_s:.2f} s; board {best.board_area_m2:.3f} m².", ""]
    head = [q for q in params if q != "scans_fused"] + ["fused", "poses", "failed"]
    cols = [f"{k} sim / bound / ratio" for k in ("roll_deg", "tilt_deg", "yaw_deg", "x_mm",
                                                 "z_mm")]
    lines += ["## Every design", "", "| " + " | ".join([*head, *cols, "chi2 roll/tilt/yaw/x",
                                                        "ms/est."]) + " |",
              "|" + "---|" * (len(head) + len(cols) + 2)]
    for r in results:
        cells = [str(_value(r, h)) if h not in ("fused", "poses", "failed") else
                 {"fused": str(r.fused), "poses": str(r.poses),
                  "failed": f"{r.failures}/{r.estimates}"}[h] for h in head]
        for k in ("roll_deg", "tilt_deg", "yaw_deg", "x_mm", "z_mm"):
            j = EDGE.index(k)
            cells.append(f"{_fmt(r.rms[j])} / {_fmt(r.bound[j])} / {_fmt(r.ratio[j])}")
        cells.append("/".join(_fmt(r.chi2[EDGE.index(k)]) for k in
                              ("roll_deg", "tilt_deg", "yaw_deg", "x_mm")))
        cells.append(_fmt(r.cpu_ms))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Figures", ""] + [f"![{f.stem}]({f.name})" for f in figures]
    lines += ["", "Exports: designs.parquet (this table, every axis), estimates.parquet (every "
                  "estimate).", ""]
    return "\n".join(lines)
