"""Reports: one page per unit, and the line's summary over many units (HTML with PNG figures).

The unit's page (``<unit>-<record>.html`` and ``.png``): the verdict and the rule, a table of
every judged axis (error, the estimator's u, the system term, U, limit, verdict), the record's
identity (station, operator, time, software, sensor, capture and its SHA-256), and a figure:

- the board seen from the LiDAR (board frame, X_O right, Z_O up) with the returns the estimate
  used, placed on it by the estimated pose, and the edge rays that located its rectangle;
- the LiDAR seen from above: its nominal frame and its estimated one, the deviation (position
  and angles) drawn 10x, as labelled (a degree or a millimetre would not show);
- each judged axis against its limit: the tolerance zone, the guard bands (limit -+ U) and the
  error with its U, coloured by the axis's verdict.

and, beneath, ``<unit>-<record>-explain.png``: why the board was found or not
(`scenarios.explain`, what ``aimbench estimate --explain`` draws) on the first scan of the
estimate and the edge brackets of all its scans, with the advice line (no board, ambiguous, a
size the rays refuse) on the page.

The line's summary (``summary.html``, ``summary.png``): counts and pass rate, per-axis
histograms of the errors with their limits, and an individuals control chart of each axis (the
centre line, the 3-sigma control limits from the average moving range, sigma = MR/1.128, and
the specification limits).

matplotlib (already a dependency) draws; the page embeds its PNG, so one file carries it all.
"""

from __future__ import annotations

import base64
import html
import time
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.inspection.records import AXES, SCALE, UNIT
from scenarios.inspection.verdict import RULE_TEXT

COLORS = {"pass": "#2e7d32", "fail": "#c62828", "inconclusive": "#ef8f00"}
#: How much the top view magnifies the angular deviation of the estimated frame.
ANGLE_MAGNIFICATION = 10.0


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:60]


# -- one unit ----------------------------------------------------------------------------------

def unit_figure(row: dict, insp: Any, path: Path) -> Path:
    """The unit's figure (module docstring) as a PNG."""
    plt = _plt()
    judged = [a for a in AXES if row[f"verdict_{a}"] is not None]
    fig = plt.figure(figsize=(13.0, 4.6), dpi=100)
    ax_board = fig.add_subplot(1, 3, 1)
    ax_top = fig.add_subplot(1, 3, 2)
    ax_ax = fig.add_subplot(1, 3, 3)
    _board_panel(ax_board, row, insp)
    _top_panel(ax_top, row, insp)
    _axes_panel(ax_ax, row, judged)
    fig.suptitle(f"unit {row['unit']}: {row['verdict'].upper()}", color=COLORS[row["verdict"]],
                 fontsize=14, fontweight="bold")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _board_points(insp: Any) -> tuple[np.ndarray, np.ndarray]:
    """The returns used and the feature firings, in the board frame (m), from the estimate."""
    est = getattr(insp, "estimate", None)
    if est is None or not est.success or not insp.scans:
        return np.zeros((0, 3)), np.zeros((0, 3))
    from twin.core.scan import Scan

    scan = insp.scans[0] if len(insp.scans) == 1 else Scan.concatenate(insp.scans)
    xyz = np.column_stack((scan.x, scan.y, scan.z))
    out = []
    for key in ("board", "features"):
        idx = np.asarray(est.used.get(key, []), dtype=np.int64).reshape(-1)
        idx = idx[(idx >= 0) & (idx < len(scan))]
        idx = idx[scan.valid[idx]]
        out.append(est.pose.transform(xyz[idx]))
    return out[0], out[1]


def _board_panel(ax: Any, row: dict, insp: Any) -> None:
    st = row["station_json"]["board"]
    w, h = st["width_mm"], st["height_mm"]
    ax.add_patch(_rect(-w / 2, -h / 2, w, h))
    pts, feats = _board_points(insp)
    if len(pts):
        every = max(1, len(pts) // 6000)
        ax.scatter(pts[::every, 0] * 1e3, pts[::every, 2] * 1e3, s=1.0, c="#1e88e5",
                   label=f"returns used ({len(pts)})")
    if len(feats):
        ax.scatter(feats[:, 0] * 1e3, feats[:, 2] * 1e3, s=4.0, c="#d81b60",
                   label="edge rays (hits)")
    ax.set_xlim(-0.7 * w, 0.7 * w)
    ax.set_ylim(-0.8 * h, 0.8 * h)
    ax.set_aspect("equal")
    ax.set_xlabel("X_O (mm), right seen from the LiDAR")
    ax.set_ylabel("Z_O (mm), up")
    ax.set_title(f"the board ({w:g} x {h:g} mm) and the points used")
    ax.legend(loc="lower center", fontsize=7)


def _rect(x: float, y: float, w: float, h: float) -> Any:
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, fill=False, lw=1.5, ec="#555555")


def _frame_arrows(ax: Any, pos: np.ndarray, rot: np.ndarray, color: str, label: str,
                  length: float) -> None:
    """The LiDAR frame's X_L and Y_L (forward) from `pos`, top view, mm."""
    for col, name, style in ((1, "Y_L", "-"), (0, "X_L", "--")):
        d = rot[:, col] * length
        ax.annotate("", xy=(pos[0] + d[0], pos[1] + d[1]), xytext=(pos[0], pos[1]),
                    arrowprops={"arrowstyle": "->", "color": color, "ls": style, "lw": 1.6})
        ax.text(pos[0] + 1.05 * d[0], pos[1] + 1.05 * d[1], name, color=color, fontsize=7)
    ax.plot([pos[0]], [pos[1]], "o", color=color, label=label)


def _top_panel(ax: Any, row: dict, insp: Any) -> None:
    """Around the LiDAR, from above: the nominal frame and the estimated one, the deviation
    (position and angles) drawn `ANGLE_MAGNIFICATION` times, and the way to the board."""
    from twin.core.pose import Pose

    st = row["station_json"]
    b = st["board"]
    nom = row["nominal"] or {}
    m = ANGLE_MAGNIFICATION
    if nom:
        n_pose = Pose.from_edge(**{k: v for k, v in nom.items() if k != "from"})
        c = n_pose.translation * 1e3
        to_board = np.array(b["position_mm"][:2]) - c[:2]
        to_board = 120.0 * to_board / max(np.linalg.norm(to_board), 1e-9)
        tip = c[:2] + 1.6 * to_board
        ax.annotate("", xy=tuple(tip), xytext=(c[0], c[1]),
                    arrowprops={"arrowstyle": "->", "color": "#bbbbbb", "lw": 1.0})
        ax.text(tip[0], tip[1], "to the board", color="#888888", fontsize=7)
        _frame_arrows(ax, c, n_pose.rotation(), "#777777", "nominal", 150.0)
        if row["err_x"] is not None:
            err = np.array([row[f"err_{a}"] for a in AXES], dtype=float)
            dev = Pose(*(err[:3] * m), *(err[3:] * m))
            _frame_arrows(ax, c + dev.translation * 1e3, n_pose.rotation() @ dev.rotation(),
                          COLORS[row["verdict"]], "estimated", 150.0)
        ax.set_xlim(c[0] - 260, c[0] + 260)
        ax.set_ylim(c[1] - 200, c[1] + 260)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x (mm), station frame {st['frame']['name']}")
    ax.set_ylabel("y (mm), towards the board")
    ax.set_title(f"the LiDAR from above: deviation drawn {m:g}x", fontsize=10)
    ax.legend(loc="lower right", fontsize=7)


def _axes_panel(ax: Any, row: dict, judged: list[str]) -> None:
    k = row["coverage_k"]
    for i, a in enumerate(judged):
        lim = row[f"limit_{a}"]
        e = row[f"err_{a}"] / lim
        big_u = row[f"u_{a}"] * k / lim if row[f"u_{a}"] is not None else 0.0
        y = len(judged) - 1 - i
        ax.barh(y, 2.0, left=-1.0, height=0.6, color="#e8f5e9", ec="#2e7d32")
        if big_u < 1:
            ax.barh(y, 2 * (1 - big_u), left=-(1 - big_u), height=0.3, color="#c8e6c9")
        color = COLORS[row[f"verdict_{a}"]]
        ax.errorbar([e], [y], xerr=[[big_u], [big_u]], fmt="o", color=color, capsize=4)
        ax.text(1.55, y, f"{row[f'err_{a}'] * SCALE[a]:+.3f} +-{row[f'u_{a}'] * k * SCALE[a]:.3f}"
                f" {UNIT[a]}", va="center", fontsize=8, color=color)
    ax.set_yticks(range(len(judged)), [f"{a} ({UNIT[a]})" for a in reversed(judged)])
    ax.axvline(-1, c="#2e7d32", lw=1)
    ax.axvline(1, c="#2e7d32", lw=1)
    ax.set_xlim(-2.2, 2.9)
    ax.set_xlabel("error / limit\n(tolerance zone -1..1; inner band: acceptance zone)")
    ax.set_title(f"each axis: error +- U (k = {k:g})")


def _table(header: list[str], rows: list[list[str]]) -> str:
    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    out += ["<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>"
            for r in rows]
    return "".join(out) + "</table>"


_STYLE = ("<style>body{font-family:sans-serif;max-width:1320px;margin:1em auto;} "
          "table{border-collapse:collapse;margin:0.5em 0;} td,th{border:1px solid #ccc;"
          "padding:2px 8px;text-align:right;} th{background:#f4f4f4;} "
          "h1 span{padding:0 0.4em;color:white;border-radius:4px;} img{max-width:100%;}</style>")


def _png_tag(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f"<img src='data:image/png;base64,{data}' alt='{html.escape(alt)}'>"


def unit_report(row: dict, insp: Any, folder: Path) -> Path:
    """Write the unit's page and figure into `folder`; returns the page."""
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"{_safe(row['unit'])}-{row['id']}"
    png = unit_figure(row, insp, folder / f"{stem}.png")
    explained = explain_figure(row, insp, folder / f"{stem}-explain.png")
    k = row["coverage_k"]
    rows = []
    for a in AXES:
        if row[f"err_{a}"] is None:
            continue
        s = SCALE[a]

        def f(c: str, a: str = a, s: float = s) -> str:
            v = row[f"{c}_{a}"]
            return "-" if v is None else f"{v * s:.3f}"
        big_u = "-" if row[f"u_{a}"] is None else f"{row[f'u_{a}'] * k * s:.3f}"
        rows.append([f"{a} ({UNIT[a]})", f"{row[f'err_{a}'] * s:+.3f}", f("u_est"), f("u_sys"),
                     big_u, f("limit"), row[f"verdict_{a}"] or "not judged"]
                    + ([] if row[f"true_{a}"] is None else [f"{row[f'true_{a}'] * s:+.3f}"]))
    # "measured" beside "true": the twin's truth is not what the gauge saw (issue 37: "error"
    # beside "true error (twin)" read as two measurements)
    header = ["axis", "measured error", "u estimator", "u system", "U = k u", "limit",
              "verdict"]
    if row["true_x"] is not None:
        header.append("true error (the twin's, not measured)")
    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(row["started_at"]))
    ident = [
        ["record", f"{row['id']} (trial {row['trial']} of this unit)"], ["time", when],
        ["station", f"{row['station']} (sha256 {row['station_sha256']})"],
        ["operator", row["operator"] or "-"],
        ["software", f"aimbench {row['software_version']}, {row['git_commit'] or '-'}"],
        ["sensor", f"{row['sensor_model']}, serial {row['sensor_serial'] or 'not reported'}"],
        ["calibration", str(row["calibration"] or "none")],
        ["source", row["source"]],
        ["capture", f"{row['capture_path'] or '-'} (sha256 {row['capture_sha256'] or '-'})"],
        ["scans", f"{row['scans']} used, {row['rejected_scans']} rejected; attempts "
                  f"{', '.join(str(a['scans']) for a in row['attempts'] or [])}"],
        ["board", f"found {bool(row['board_found'])}, {row['rings']} rings, "
                  f"{row['board_points']} points"],
        ["nominal", f"{row['nominal']}"],
    ]
    color = COLORS[row["verdict"]]
    page = folder / f"{stem}.html"
    page.write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>unit {html.escape(row['unit'])}"
        f"</title>{_STYLE}</head><body><h1>unit {html.escape(row['unit'])} "
        f"<span style='background:{color}'>{row['verdict'].upper()}</span></h1>"
        f"<p>{html.escape(row['message'] or '')}</p>"
        f"<p>Decision rule: {html.escape(RULE_TEXT[row['rule']])}, k = {k:g}. u is the "
        "estimator's standard uncertainty combined in quadrature with the station's stated "
        "measurement-system term.</p>"
        + _table(header, rows) + _png_tag(png, "the board, the frames and each axis")
        + _explained(explained) + _table(["", ""], ident) + "</body></html>", encoding="utf-8")
    return page


def _board_spec(row: dict) -> Any:
    """The station's board as align's `BoardSpec`, from the record."""
    from align.board import BoardSpec

    b = row["station_json"]["board"]
    return BoardSpec(b["width_mm"] * 1e-3, b["height_mm"] * 1e-3,
                     b.get("thickness_mm", 3.0) * 1e-3)


def explain_figure(row: dict, insp: Any, path: Path) -> tuple[Path, str | None] | None:
    """The estimate explained on its first scan, with the edge brackets of all
    (`scenarios.explain`), as a PNG, and its advice; None without an estimate or a scan."""
    est = getattr(insp, "estimate", None)
    if est is None or not getattr(insp, "scans", None):
        return None
    from scenarios.explain import advice, write_explain_png

    board = _board_spec(row)
    return write_explain_png(path, insp.scans, est, board), advice(est, board)


def _explained(explained: tuple[Path, str | None] | None) -> str:
    if explained is None:
        return ""
    png, tip = explained
    text = f"<p><b>Advice:</b> {html.escape(tip)}</p>" if tip else ""
    return ("<h2>How the board was found</h2>" + text
            + _png_tag(png, "the scan about the board, the candidates and the chosen rectangle"))


# -- the line ----------------------------------------------------------------------------------

def control_limits(values: np.ndarray) -> tuple[float, float, float]:
    """Individuals chart: (centre, lower, upper) control limits, mean -+ 3 MR/1.128 (`spc`)."""
    from scenarios.inspection import spc

    v = np.asarray(values, float)
    centre = float(v.mean())
    if len(v) < 2:
        return centre, centre, centre
    chart = spc.imr_chart(v)
    return chart.center, chart.lcl, chart.ucl


def line_summary(rows: list[dict], folder: Path) -> Path:
    """Write the line's summary page and figure into `folder`; returns the page."""
    folder.mkdir(parents=True, exist_ok=True)
    plt = _plt()
    ok = [r for r in rows if r["status"] == "ok"]
    judged = [a for a in AXES if any(r[f"verdict_{a}"] is not None for r in ok)]
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("pass", "fail", "inconclusive")}
    n = len(rows)
    fig, axs = plt.subplots(2, max(1, len(judged)), figsize=(4.0 * max(1, len(judged)), 7.0),
                            dpi=100, squeeze=False)
    for j, a in enumerate(judged):
        vals = np.array([r[f"err_{a}"] * SCALE[a] for r in ok if r[f"err_{a}"] is not None])
        lim = next(r[f"limit_{a}"] for r in ok if r[f"limit_{a}"] is not None) * SCALE[a]
        verdicts = [r["verdict"] for r in ok if r[f"err_{a}"] is not None]
        h = axs[0, j]
        bins = np.linspace(min(vals.min(), -lim) * 1.1, max(vals.max(), lim) * 1.1, 30)
        h.hist([vals[[v == k for k in verdicts]] for v in ("pass", "inconclusive", "fail")],
               bins=bins, stacked=True, color=[COLORS[v] for v in ("pass", "inconclusive",
                                                                     "fail")],
               label=["pass", "inconclusive", "fail"])
        for x in (-lim, lim):
            h.axvline(x, c="k", ls="--", lw=1)
        h.set_title(f"{a} error ({UNIT[a]})")
        h.legend(fontsize=7)
        c = axs[1, j]
        centre, lcl, ucl = control_limits(vals)
        c.plot(np.arange(1, len(vals) + 1), vals, "o-", ms=3, lw=0.8, c="#1e88e5")
        for y, style, name in ((centre, "-", "centre"), (lcl, ":", "LCL"), (ucl, ":", "UCL"),
                               (-lim, "--", "-limit"), (lim, "--", "+limit")):
            c.axhline(y, ls=style, c="k" if "limit" in name else "#c62828", lw=1)
        c.set_title(f"{a}: individuals chart (UCL {ucl:+.3g}, LCL {lcl:+.3g})", fontsize=9)
        c.set_xlabel("inspection")
    fig.suptitle(f"line summary: {n} inspections, pass rate {counts['pass'] / max(n, 1):.1%}")
    fig.tight_layout()
    png = folder / "summary.png"
    fig.savefig(png)
    plt.close(fig)
    units = {r["unit"]: r["verdict"] for r in rows}  # each unit's latest verdict
    table = _table(["", "inspections", "share", "units (latest)"], [
        [v.upper(), str(counts[v]), f"{counts[v] / max(n, 1):.1%}",
         str(sum(u == v for u in units.values()))] for v in ("pass", "fail", "inconclusive")])
    stats = []
    for a in judged:
        vals = np.array([r[f"err_{a}"] * SCALE[a] for r in ok if r[f"err_{a}"] is not None])
        centre, lcl, ucl = control_limits(vals)
        stats.append([f"{a} ({UNIT[a]})", f"{vals.mean():+.3f}", f"{vals.std(ddof=1):.3f}"
                      if len(vals) > 1 else "-", f"{lcl:+.3f}", f"{ucl:+.3f}"])
    page = folder / "summary.html"
    page.write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>line summary</title>{_STYLE}"
        f"</head><body><h1>line summary</h1><p>{n} inspections of {len(units)} units; pass rate "
        f"{counts['pass'] / max(n, 1):.1%}.</p>" + table
        + _table(["axis", "mean", "sd", "LCL", "UCL"], stats)
        + _png_tag(png, "histograms and control charts") + "</body></html>", encoding="utf-8")
    return page
