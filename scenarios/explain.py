"""Why an estimate found the board, or did not: one picture and one line of advice (issue 34).

`aimbench estimate --explain FILE.png` and the inspection's unit page draw `explain_figure`:
the scan around the board as the LiDAR sees it (azimuth to the right, as the sensor turns,
elevation up: each ring a row), every return coloured by its range; every board-like candidate
the estimator weighed, outlined and labelled with its index, the search's score, its fit's
status and its log weight; the chosen rectangle; the board's returns, and the hits and misses
that bracket its edges; the rings that cross it; a title with the status and the pose; and the
advice (`advice`), the one thing to change when no board is found, or it is ambiguous, or its
size is not the one given. The most common complaint about target-based calibration tools is a
board that is not found, silently.

`advice` is a plain function of the result (no matplotlib): the command line prints it beside
a failed estimate with or without the picture.
"""

from __future__ import annotations

import itertools
import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from align.board import BoardSpec
from align.geometry import board_centre
from align.params import DEFAULT_PARAMS
from align.result import Hints, PoseEstimate, Status
from twin.core.pose import Pose
from twin.core.scan import Scan

#: Fewest degrees of azimuth either side of the window's centre a picture shows.
MIN_HALF_WIDTH_DEG = 12.0
#: The window's margin about the board (or the candidates), as a fraction of their extent.
MARGIN = 0.6
#: The tallest the picture's axes grow, inches: a narrower window is widened to fill them.
MAX_AXES_HEIGHT_IN = 4.2
#: Colours of the candidates' outlines, by index (the chosen one is drawn in black).
CANDIDATE_COLORS = ("#1e88e5", "#d81b60", "#8e24aa", "#f4511e", "#00897b", "#6d4c41")


# -- advice -------------------------------------------------------------------------------------

def _mm(v: float) -> str:
    return f"{1e3 * v:.0f}"


def _size_advice(diag: dict, board: BoardSpec) -> str | None:
    """The rays see another size than the one given (`align.fit.size`): say which."""
    d2 = diag.get("size_mismatch_d2")
    if d2 is None or not (diag.get("size_freed") or d2 > DEFAULT_PARAMS.size_refused_d2):
        return None
    w, h = diag["seen_width_m"], diag["seen_height_m"]
    sw, sh = diag.get("seen_width_std_m") or 0.0, diag.get("seen_height_std_m") or 0.0
    return (f"the rays see a {_mm(w)} +-{_mm(sw)} x {_mm(h)} +-{_mm(sh)} mm board, not the "
            f"{_mm(board.width)} x {_mm(board.height)} mm given (d2 {d2:.0f}): check --board-mm"
            " (or the unit's range offset: ranges read long make the board look larger)")


def _centre(pose: Pose | None) -> np.ndarray | None:
    """The board's centre in the LiDAR's frame {L}, m (`align.choice.Candidate.centre`)."""
    return None if pose is None else board_centre(pose.as_array())


def _where(c: dict) -> str:
    """A candidate as a user finds it: its azimuth and distance from the LiDAR."""
    p = _centre(c.get("pose"))
    if p is None:
        return f"candidate {c['index']}"
    az = math.degrees(math.atan2(p[0], p[1]))
    return f"candidate {c['index']} (azimuth {az:+.0f} deg, {np.linalg.norm(p):.1f} m)"


def _ranked(est: PoseEstimate) -> list[dict]:
    """The weighed candidates that passed, the heaviest first."""
    cands = [c for c in est.used.get("candidates", ()) if c.get("log_weight") is not None
             and math.isfinite(c["log_weight"])]
    return sorted(cands, key=lambda c: -c["log_weight"])


def _partial_advice(diag: dict) -> str:
    """What to change for a board the known rectangle does not explain."""
    seen = diag.get("edges_seen")
    missing = [n for n, k in zip(("left", "right", "bottom", "top"), "lrbt", strict=True)
               if seen is not None and k not in seen]
    if missing:
        what = (f"nothing is seen beyond its {'/'.join(missing)} edge: bring the whole board "
                "into view (and inside --azimuth-deg), or clear what hides that edge")
    elif diag.get("occluded_rays", 0) > diag.get("inside_misses", 0):
        what = (f"{diag['occluded_rays']} rays are blocked in front of the board: clear the "
                "view between the LiDAR and the board")
    elif diag.get("inside_misses", 0) > 0:
        what = (f"{diag['inside_misses']} rays pass through the board: a dark or shiny patch, or "
                "a hole, where the board should be")
    elif diag.get("outside_hits", 0) > 0:
        what = (f"{diag['outside_hits']} returns beyond the rectangle's edges: something flush "
                "beside the board, or a board larger than --board-mm")
    else:
        what = "the fit does not explain the rays near its edges"
    return f"only part of the board is explained: {what}"


def _window_hint(a: dict, b: dict, board: BoardSpec) -> str:
    """The ``--azimuth-deg`` that holds candidate ``a``'s rectangle, 3 deg either side, and
    whether it leaves ``b`` out."""
    if a.get("pose") is None:
        return ""
    c, hw = _circular_span(_az_el(_outline(a["pose"], board, 4))[0])
    hw += 3.0
    keeps = "keeps only"
    if b.get("pose") is not None:
        rel = _wrap(_az_el(_outline(b["pose"], board, 4))[0], c)
        if np.any(np.abs(rel) <= hw):
            keeps = "is around"
    return f" (--azimuth-deg {c:.0f}:{hw:.0f} {keeps} candidate {a['index']})"


def advice(est: PoseEstimate, board: BoardSpec, hints: Hints | None = None) -> str | None:
    """One line of advice on what to change, or None when there is nothing to say (a board found
    whole, of the size given). Each status's line rests on the result's own diagnostics."""
    diag, status = est.diagnostics, est.status
    hints = hints or Hints()
    size = _size_advice(diag, board)
    if status == Status.OK:
        return size
    if status == Status.PARTIAL_BOARD:
        return size or _partial_advice(diag)
    if status == Status.NO_BOARD:
        reason = diag.get("reason") or "no cluster looks like the board"
        window = ""
        if hints.azimuth_window is not None:
            c, hw = (math.degrees(v) for v in hints.azimuth_window)
            window = f" (now {c:g}:{hw:g})"
        return (f"{reason} ({_mm(board.width)} x {_mm(board.height)} mm): check --board-mm, "
                f"bring the board closer or face it to the LiDAR, or widen --azimuth-deg"
                f"{window}")
    if status == Status.BOARD_TOO_FAR:
        d = diag.get("distance_m")
        at = f"at {d:.1f} m" if d is not None and math.isfinite(d) else "too far"
        return (f"a board-like cluster {at}, beyond the usable {hints.max_distance:g} m: bring "
                "the board closer")
    if status == Status.TOO_FEW_RINGS:
        rings = f" ({diag['rings']})" if diag.get("rings") else ""
        return (f"fewer than 3 rings cross the board{rings}: bring it closer, or tilt it (hang "
                "it as a diamond) so that more rings cross it")
    if status == Status.AMBIGUOUS_BOARD:
        ranked = _ranked(est)
        lr = diag.get("board_log10_lr")
        ratio = f" (likelihood ratio 10^{lr:.1f})" if lr is not None else ""
        if len(ranked) >= 2:
            a, b = ranked[0], ranked[1]
            hint = _window_hint(a, b, board)
            return (f"{_where(a)} and {_where(b)} explain the rays alike{ratio}: narrow "
                    f"--azimuth-deg to the board's{hint}, give --expected-distance-m, or the "
                    "station's board.position_tolerance_mm")
        return (f"two board-like objects explain the rays alike{ratio}: narrow --azimuth-deg, "
                "give --expected-distance-m, or the station's board.position_tolerance_mm")
    if status == Status.BOARD_OUTSIDE_REGION:
        cands = _ranked(est)
        found = f": {_where(cands[0])}" if cands else ""
        return ("the only board-like object lies outside the station's board region"
                f"{found}; check board.position_mm and mount.nominal in the station file, or "
                "that the unit is mounted as the station says")
    if status == Status.NOT_CONVERGED:
        return ("the fit did not settle: check that the board and the LiDAR are still, or fuse "
                "more scans (--fuse N)")
    if status == Status.EMPTY_SCAN:
        return "the scan holds no return: check the capture or the sensor (aimbench info)"
    if status == Status.ESTIMATOR_ERROR:
        return f"the estimator failed: {diag.get('error', 'an exception')}"
    return diag.get("reason") or None


# -- the picture --------------------------------------------------------------------------------

def _wrap(deg: np.ndarray, centre: float) -> np.ndarray:
    """Azimuth relative to ``centre`` in [-180, 180), deg."""
    return (np.asarray(deg) - centre + 180.0) % 360.0 - 180.0


def _az_el(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (clockwise from Y_L, as the sensor turns) and elevation of points in {L}, deg."""
    xyz = np.atleast_2d(xyz)
    az = np.degrees(np.arctan2(xyz[:, 0], xyz[:, 1]))
    el = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    return az, el


def _firing_az_el(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """Every firing's azimuth and elevation, deg: a return's where it lies seen from the
    LiDAR's origin (the rectangle is drawn the same way), a miss's along its laser's ray."""
    az = np.degrees(scan.azimuth)
    el = np.degrees(scan.elevation)
    v = scan.valid
    if np.any(v):
        az[v], el[v] = _az_el(scan.xyz[v])
    return az, el


def _outline(pose: Pose, board: BoardSpec, n: int = 24) -> np.ndarray:
    """The board's rectangle in {L}, (4 n + 1, 3), m: its edges sampled (a straight edge is
    not straight in azimuth and elevation)."""
    w, h = board.width / 2, board.height / 2
    corners = np.array([[-w, 0, -h], [w, 0, -h], [w, 0, h], [-w, 0, h], [-w, 0, -h]])
    t = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
    pts = np.concatenate([*(a + t * (b - a) for a, b in itertools.pairwise(corners)),
                          corners[-1:]])
    return (pts - pose.translation) @ pose.rotation()  # R^T (p_O - t), row by row


def _indices(idx: Any, n: int) -> np.ndarray:
    """Indices of the first scan (those of a fused estimate's later scans left out)."""
    a = np.asarray(idx if idx is not None else [], dtype=np.int64).reshape(-1)
    return a[(a >= 0) & (a < n)]


def _circular_span(az: np.ndarray) -> tuple[float, float]:
    """(centre, half width) of a set of azimuths, deg, through their circular mean."""
    c = math.degrees(float(np.angle(np.mean(np.exp(1j * np.radians(az))))))
    rel = _wrap(az, c)
    lo, hi = float(rel.min()), float(rel.max())
    return c + (lo + hi) / 2, (hi - lo) / 2


def _window(scan: Scan, est: PoseEstimate, board: BoardSpec, hints: Hints,
            az: np.ndarray) -> tuple[float, float, str]:
    """The picture's azimuth window (centre, half width, deg) and what it is around: the
    chosen board and the candidates; the candidates; the cluster found too far; the user's
    azimuth window; else the whole turn. The margin is the board's own half width (at least
    `MIN_HALF_WIDTH_DEG` / 2), so that what lies beside it shows."""
    pieces, own = [], 0.0
    if est.pose is not None:
        a = _az_el(_outline(est.pose, board, 4))[0]
        own = _circular_span(a)[1]
        pieces.append(a)
    for c in est.used.get("candidates", ()):
        if c.get("pose") is not None:
            a = _az_el(_outline(c["pose"], board, 4))[0]
            own = own or _circular_span(a)[1]
            pieces.append(a)
        idx = _indices(c.get("returns"), len(scan))
        if len(idx):
            pieces.append(az[idx])
    cluster = _indices(est.used.get("cluster"), len(scan))
    if len(cluster):
        pieces.append(az[cluster])
    if pieces:
        c, hw = _circular_span(np.concatenate(pieces))
        hw = min(180.0, max(MIN_HALF_WIDTH_DEG, hw + max(MARGIN * own,
                                                         MIN_HALF_WIDTH_DEG / 2)))
        return c, hw, "the board" if est.pose is not None else "the candidates"
    if hints.azimuth_window is not None:
        c, hw = (math.degrees(v) for v in hints.azimuth_window)
        return c, min(180.0, hw + MIN_HALF_WIDTH_DEG / 2), "the azimuth window given"
    return 0.0, 180.0, "the whole turn"


def _pose_text(pose: Pose | None) -> str:
    if pose is None:
        return "no pose"
    e = pose.to_edge()
    return (f"x {e['x_mm']:+.0f} y {e['y_mm']:+.0f} z {e['z_mm']:+.0f} mm, roll "
            f"{e['roll_deg']:+.2f} tilt {e['tilt_deg']:+.2f} yaw {e['yaw_deg']:+.2f} deg")


def _detail(est: PoseEstimate, board: BoardSpec, rings: np.ndarray) -> str:
    """The title's second line: the board given and seen, its edges, rings and the choice."""
    d = est.diagnostics
    parts = [f"board {_mm(board.width)} x {_mm(board.height)} mm"]
    if d.get("seen_width_m") is not None:
        parts.append(f"seen {_mm(d['seen_width_m'])} x {_mm(d['seen_height_m'])} mm")
    if "edges_left" in d:
        parts.append("edge brackets l/r/b/t " + "/".join(
            str(d[f"edges_{k}"]) for k in ("left", "right", "bottom", "top")))
    if len(rings):
        parts.append(f"{len(rings)} rings cross it ({_ranges(rings)})")
    elif d.get("rings"):
        parts.append(f"{d['rings']} rings")
    if d.get("distance_m") is not None and math.isfinite(d["distance_m"]):
        parts.append(f"cluster at {d['distance_m']:.2f} m")
    if d.get("chi2_per_dof") is not None:
        parts.append(f"chi2/dof {d['chi2_per_dof']:.2f}")
    n = len(est.used.get("candidates", ()))
    if n:
        lr = d.get("board_log10_lr")
        parts.append(f"{n} candidates" + (f", LR 10^{lr:.1f}" if lr is not None
                                          and math.isfinite(lr) else ""))
    return ", ".join(parts)


def _ranges(values: np.ndarray) -> str:
    """Ring numbers as runs: 0-5, 7, 9-15."""
    out, vals = [], sorted(int(v) for v in values)
    start = prev = vals[0]
    for v in [*vals[1:], None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if v is not None:
            start = prev = v
    return ", ".join(out)


def _brackets(scans: list[Scan], est: PoseEstimate) -> tuple[np.ndarray, np.ndarray]:
    """The edge brackets (``used["features"]``: a hit and a miss each, indexed into the
    concatenation of the scans): their azimuths and elevations, (k, 2) deg each."""
    feats = np.asarray(est.used.get("features", np.zeros((0, 2))), dtype=np.int64)
    feats = feats.reshape(-1, 2)
    total = sum(len(s) for s in scans)
    feats = feats[np.all((feats >= 0) & (feats < total), axis=1)]
    if not len(feats):
        return np.zeros((0, 2)), np.zeros((0, 2))
    joined = scans[0] if len(scans) == 1 else Scan.concatenate(scans)
    picked = joined.select(feats.reshape(-1))
    az, el = _firing_az_el(picked)
    return az.reshape(-1, 2), el.reshape(-1, 2)


def _candidate_line(c: dict, chosen: int | None) -> str:
    """One candidate as the picture's list says it: index, where, status, score, log weight."""
    lw = c.get("log_weight")
    w = f"{lw:.1f}" if lw is not None and math.isfinite(lw) else "-inf (failed its fit)"
    return (f"{_where(c)}: {c['status']}, search score {c['score']:.2f}, log weight {w}"
            + (", chosen" if c["index"] == chosen else ""))


def explain_figure(scans: Scan | Sequence[Scan], est: PoseEstimate, board: BoardSpec,
                   hints: Hints | None = None) -> Any:
    """The picture of ``est`` on its scan, a matplotlib Figure (module docstring). ``scans``:
    the scan, or the scans a fused estimate was made of: the picture is the first's (its
    returns, the board's among them, the candidates), with the edge brackets of every scan (a
    static scene: each bracket where its rays were). ``hints``: those the estimate was made
    with (the azimuth window drawn where nothing was found, the advice's limits)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.figure import Figure
    from matplotlib.ticker import FormatStrFormatter

    hints = hints or Hints()
    scan_list = [scans] if isinstance(scans, Scan) else list(scans)
    scan = scan_list[0]
    n = len(scan)
    az_all, el_all = _firing_az_el(scan)
    centre, half, around = _window(scan, est, board, hints, az_all)
    lo_el = float(np.degrees(scan.lasers.elevation.min())) - 2.0
    hi_el = float(np.degrees(scan.lasers.elevation.max())) + 2.0
    # the layout in inches: the title's two lines, the axes (a degree as long both ways; a
    # window narrower than the axes at their tallest widened to fill them: more of what is
    # beside the board), the azimuth's label, then the candidates and the advice beside the
    # legend
    width, left, right, top, below = 12.0, 0.65, 1.0, 0.75, 0.5
    aw = width - left - right
    whole_turn = half >= 180.0
    if whole_turn:
        ah = 3.0
    else:
        ah = float(np.clip(aw * (hi_el - lo_el) / (2 * half), 2.2, MAX_AXES_HEIGHT_IN))
        half = min(180.0, max(half, aw * (hi_el - lo_el) / (2 * ah)))
    rel = _wrap(az_all, centre)
    inside = np.abs(rel) <= half
    valid = scan.valid
    cands = list(est.used.get("candidates", ()))
    chosen = est.diagnostics.get("board_candidate") if est.success else None
    lines = [_candidate_line(c, chosen) for c in cands]
    tip = advice(est, board, hints)
    if tip:
        lines += textwrap.wrap("advice: " + tip, 110)
    band = max(len(lines), 4) * 0.16 + 0.2
    height = top + ah + below + band
    fig = Figure(figsize=(width, height), dpi=100)
    ax = fig.add_axes((left / width, (band + below) / height, aw / width, ah / height))
    cax = fig.add_axes(((width - right + 0.15) / width, (band + below) / height, 0.15 / width,
                        ah / height))
    board_idx = _indices(est.used.get("board"), n)
    on_board = np.zeros(n, dtype=bool)
    on_board[board_idx] = True
    # the scan: every return in the window coloured by its range (the board's drawn larger),
    # the rays without a return in grey
    m = inside & valid
    rng = scan.distance[m]
    vmin, vmax = ((float(np.percentile(rng, 2)), float(np.percentile(rng, 98)))
                  if len(rng) else (0.0, 1.0))
    vmax = max(vmax, vmin + 1e-3)
    # a log scale where the ranges span much (the board at 2 m, a far wall at 20): the board
    # and what is just behind it in colours apart
    norm = (LogNorm(max(vmin, 0.1), vmax) if vmax > 4 * max(vmin, 0.1)
            else Normalize(vmin, vmax))
    cmap = dict(cmap="viridis", norm=norm, linewidths=0, rasterized=True)
    dot = 1.5 if whole_turn else 3.0
    ax.scatter(rel[inside & ~valid], el_all[inside & ~valid], s=dot * 0.5, c="#cfcfcf",
               marker="s", linewidths=0, label="no return", rasterized=True)
    rest = m & ~on_board
    sc = ax.scatter(rel[rest], el_all[rest], s=dot, c=scan.distance[rest], **cmap)
    if len(board_idx):
        ax.scatter(rel[board_idx], el_all[board_idx], s=4 * dot, c=scan.distance[board_idx],
                   marker="s", label=f"the board's returns ({len(board_idx)}), larger",
                   **cmap)
    bar = fig.colorbar(sc, cax=cax)
    bar.set_label("range (m)", fontsize=8)
    lo_r, hi_r = norm.vmin, norm.vmax
    ticks = [t for t in (0.5, 1, 1.5, 2, 3, 4, 5, 7, 10, 15, 20, 30, 50, 100, 200)
             if lo_r <= t <= hi_r]
    if len(ticks) >= 2:
        bar.set_ticks(ticks)
    bar.ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    bar.ax.yaxis.set_minor_formatter(FormatStrFormatter(""))
    bar.ax.tick_params(labelsize=7)
    # the candidates the estimator weighed: each outlined (its fitted rectangle where its fit
    # gave one, the box of its returns else) and labelled
    for c in cands:
        color = CANDIDATE_COLORS[c["index"] % len(CANDIDATE_COLORS)]
        idx = _indices(c.get("returns"), n)
        if c.get("pose") is not None:
            a, e = _az_el(_outline(c["pose"], board))
            a = _wrap(a, centre)
        elif len(idx):
            a0, a1 = rel[idx].min(), rel[idx].max()
            e0, e1 = el_all[idx].min(), el_all[idx].max()
            a, e = np.array([a0, a1, a1, a0, a0]), np.array([e0, e0, e1, e1, e0])
        else:
            continue
        if c["index"] != chosen:
            ax.plot(a, e, ls="--", lw=1.3, color=color)
        lw = c.get("log_weight")
        label = (f"#{c['index']} {c['status']}\nscore {c['score']:.2f}, log w "
                 + (f"{lw:.1f}" if lw is not None and math.isfinite(lw) else "-inf"))
        shown = (np.abs(a) <= half) & (e <= hi_el)
        top = (int(np.flatnonzero(shown)[np.argmax(e[shown])]) if np.any(shown)
               else int(np.argmax(e)))
        ax.annotate(label, (float(np.clip(a[top], -half, half)), min(float(e[top]), hi_el)),
                    xytext=(0, 3), textcoords="offset points", ha="center", va="bottom",
                    fontsize=7, color=color, annotation_clip=False,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": color, "lw": 0.6,
                          "alpha": 0.9})
    # the cluster a board too far was seen as
    cluster = _indices(est.used.get("cluster"), n)
    if len(cluster):
        ax.scatter(rel[cluster], el_all[cluster], s=30, facecolors="none",
                   edgecolors="#f4511e", linewidths=0.8,
                   label=f"board-like cluster, too far ({len(cluster)})")
    # the rings that cross the board: their numbers in a column left of it
    rings = np.unique(scan.ring[board_idx]) if len(board_idx) else np.zeros(0, dtype=int)
    if len(rings):
        ring_of = scan.ring[board_idx]
        x0 = float(rel[board_idx].min()) - 1.0
        for r in rings:
            y = float(np.median(el_all[board_idx[ring_of == r]]))
            ax.text(x0, y, str(int(r)), fontsize=6.5, ha="right", va="center",
                    color="#333333")
        ax.text(x0, float(el_all[board_idx].max()) + 1.2, "ring", fontsize=6.5, ha="right",
                color="#333333")
    # the hits and misses that bracket the rectangle's edges, each pair joined
    f_az, f_el = _brackets(scan_list, est)
    if len(f_az):
        f_rel = _wrap(f_az, centre)
        for (h, mi), (eh, em) in zip(f_rel, f_el, strict=True):
            ax.plot([h, mi], [eh, em], color="#555555", lw=0.8, zorder=4)
        every = f", from {len(scan_list)} scans" if len(scan_list) > 1 else ""
        ax.scatter(f_rel[:, 0], f_el[:, 0], s=46, marker="o", facecolors="none",
                   edgecolors="#2e7d32", linewidths=1.3, zorder=5,
                   label=f"hit at an edge ({len(f_az)}{every})")
        ax.scatter(f_rel[:, 1], f_el[:, 1], s=20, marker="x", c="#c62828", linewidths=1.2,
                   zorder=5, label=f"miss at an edge ({len(f_az)}{every})")
    if est.pose is not None:
        a, e = _az_el(_outline(est.pose, board))
        ax.plot(_wrap(a, centre), e, color="k" if est.success else "#ef8f00", lw=1.8,
                zorder=6,
                label="the chosen rectangle" if est.success else "the fitted rectangle")
    if around == "the azimuth window given":
        for sign in (-1, 1):
            ax.axvline(sign * math.degrees(hints.azimuth_window[1]), color="#888888", ls=":",
                       lw=1.0, label="--azimuth-deg" if sign > 0 else None)
    ax.set_xlim(-half, half)
    ax.set_ylim(lo_el, hi_el)
    if not whole_turn:
        ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"azimuth (deg) from {centre:+.1f} deg, growing as the sensor turns "
                  f"(window: {around})", fontsize=9)
    ax.set_ylabel("elevation (deg)", fontsize=9)
    ax.tick_params(labelsize=8)
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower right", bbox_to_anchor=(1 - 0.1 / width,
                                                                       0.1 / height),
                   ncol=2, fontsize=7, markerscale=1.3, framealpha=0.9)
    ok = est.success
    fig.suptitle(f"{est.status}: {_pose_text(est.pose if ok else None)}", fontsize=12,
                 fontweight="bold", color="#2e7d32" if ok else "#c62828",
                 y=1 - 0.08 / height, va="top")
    fig.text(0.5, 1 - 0.42 / height, _detail(est, board, rings), ha="center", va="top",
             fontsize=8.5, color="#333333")
    if lines:
        color = "#333333" if not tip else ("#c62828" if not ok else "#8a5a00")
        fig.text(0.15 / width, 0.1 / height, "\n".join(lines), fontsize=8, va="bottom",
                 ha="left", color=color, linespacing=1.35)
    return fig


def write_explain_png(path: str | Path, scans: Scan | Sequence[Scan], est: PoseEstimate,
                      board: BoardSpec, hints: Hints | None = None, dpi: int = 100) -> Path:
    """Draw `explain_figure` into the PNG ``path`` (its folder made; 256 colours) and return
    the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    import io

    from PIL import Image  # matplotlib's own dependency

    fig = explain_figure(scans, est, board, hints)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    # 256 colours: a third of the bytes, the same picture (flat colours, a few gradients)
    with Image.open(buf) as im:
        im.convert("RGB").quantize(colors=256).save(path, format="PNG", optimize=True)
    return path
