"""The line station's web pages (NiceGUI) and its HTTP/JSON endpoint for MES (FastAPI, which
NiceGUI is built on).

Why NiceGUI: the pages are Python beside the engine they show (no JavaScript build, no
template language), it is well kept (releases every few weeks, MIT), it serves every script,
style and font it uses from the package itself (Vue, Quasar, ECharts: a station on a line
network with no Internet draws its pages whole), and the same FastAPI application carries the
JSON endpoint. The pages poll the engine's state a few times a second.

- ``/``: the operator's page. The verdict, large and coloured; the unit-ID field (a barcode
  scanner types the id and Enter: the unit is inspected); per judged axis the error with its
  expanded uncertainty against the limit and the guard bands; progress while scanning; the
  board as the sensor saw it; the last units; alarms.
- ``/engineer``: the line engineer's page (login, role ``engineer``): SPC per axis (individuals
  and moving-range charts with Nelson's run rules, Cp/Cpk/Pp/Ppk, histograms), the Type-1 and
  gauge R&R studies in the store, the station file in force with its hash, the calibration
  identity, the audit trail, the batch (a change is logged).
- ``/login``: name and password of the station file's ``[[line.users]]`` (scrypt hashes); the
  session is NiceGUI's server-side user storage behind a signed cookie whose key is drawn anew
  at every start.
- ``/api/state`` (GET), ``/api/inspect`` (POST ``{"unit": ID}``: inspects and answers with the
  result; 409 while busy), ``/api/records`` (GET ``?limit=N``): JSON for MES. With users in the
  station file the endpoint asks for HTTP Basic credentials of a user who may inspect.
"""

from __future__ import annotations

import asyncio
import base64
import html
import json
import os
import time
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse
from nicegui import app, ui

from scenarios.inspection import spc
from scenarios.inspection.identity import station_hash
from scenarios.line import auth
from scenarios.line.engine import Busy, StationEngine, result_dict
from twin.core.errors import AimbenchError

COLORS = {"pass": "#2e7d32", "fail": "#c62828", "inconclusive": "#ef6c00", "busy": "#1565c0",
          "idle": "#616161", "error": "#6a1b9a"}
LAST_UNITS = 12


def _user() -> auth.User | None:
    d = app.storage.user.get("login")
    return auth.User(d["name"], d["role"]) if d else None


# -- drawing -----------------------------------------------------------------------------------

def band_svg(value: float | None, big_u: float | None, limit: float, verdict: str | None,
             width: int = 360, height: int = 34) -> str:
    """One axis as a picture: the specification [-limit, limit], its guard bands (U inside
    each limit, where ISO 14253-1 proves nothing), and the error with +-U."""
    span = 1.6 * max(limit, abs(value or 0.0) + (big_u or 0.0))

    def x(v: float) -> float:
        return width / 2 + v / span * (width / 2 - 6)

    u = min(big_u or 0.0, limit)
    parts = [f'<svg width="{width}" height="{height}" xmlns="http://www.w3.org/2000/svg">',
             f'<rect x="{x(-limit):.1f}" y="8" width="{x(limit) - x(-limit):.1f}" height="18" '
             'fill="#e8f5e9" stroke="#2e7d32"/>',
             f'<rect x="{x(-limit):.1f}" y="8" width="{x(-limit + u) - x(-limit):.1f}" '
             'height="18" fill="#ffe0b2"/>',
             f'<rect x="{x(limit - u):.1f}" y="8" width="{x(limit) - x(limit - u):.1f}" '
             'height="18" fill="#ffe0b2"/>',
             f'<line x1="{x(0):.1f}" y1="4" x2="{x(0):.1f}" y2="30" stroke="#9e9e9e"/>']
    if value is not None:
        c = COLORS.get(verdict or "", "#000")
        lo, hi = value - (big_u or 0.0), value + (big_u or 0.0)
        parts += [f'<line x1="{x(lo):.1f}" y1="17" x2="{x(hi):.1f}" y2="17" stroke="{c}" '
                  'stroke-width="3"/>',
                  f'<circle cx="{x(value):.1f}" cy="17" r="5" fill="{c}"/>']
    parts.append("</svg>")
    return "".join(parts)


def imr_options(ax: spc.AxisSPC) -> dict[str, Any]:
    """ECharts options of an axis's individuals chart with its control and specification
    limits, the run rules' signals marked."""
    c = ax.chart
    n = list(range(1, len(c.values) + 1))
    flagged = {s.index for s in c.signals}

    def line(name: str, y: float, color: str, dash: str = "dashed") -> dict[str, Any]:
        return {"name": name, "type": "line", "data": [[1, y], [max(n), y]], "symbol": "none",
                "lineStyle": {"color": color, "type": dash, "width": 1}}

    return {
        "title": {"text": f"{ax.axis}: individuals", "textStyle": {"fontSize": 13}},
        "animation": False, "grid": {"left": 50, "right": 10, "top": 30, "bottom": 25},
        "xAxis": {"type": "value", "min": 1, "max": max(n)},
        "yAxis": {"type": "value", "scale": True},
        "series": [
            {"name": ax.axis, "type": "line", "data": [
                {"value": [i, v], "itemStyle": {"color": "#c62828" if i - 1 in flagged
                                                else "#1e88e5"}}
                for i, v in zip(n, c.values, strict=True)], "symbolSize": 5},
            line("UCL", c.ucl, "#c62828"), line("centre", c.center, "#424242", "solid"),
            line("LCL", c.lcl, "#c62828"), line("+limit", ax.limit, "#000", "dotted"),
            line("-limit", -ax.limit, "#000", "dotted")],
    }


def mr_options(ax: spc.AxisSPC) -> dict[str, Any]:
    c = ax.chart
    n = list(range(2, len(c.values) + 1))
    return {
        "title": {"text": f"{ax.axis}: moving range", "textStyle": {"fontSize": 13}},
        "animation": False, "grid": {"left": 50, "right": 10, "top": 30, "bottom": 25},
        "xAxis": {"type": "value", "min": 1, "max": max(len(c.values), 2)},
        "yAxis": {"type": "value"},
        "series": [
            {"type": "line", "data": [[i, v] for i, v in zip(n, c.moving_ranges, strict=True)],
             "symbolSize": 4},
            {"type": "line", "data": [[1, c.mr_ucl], [len(c.values), c.mr_ucl]],
             "symbol": "none", "lineStyle": {"color": "#c62828", "type": "dashed"}},
            {"type": "line", "data": [[1, c.mr_bar], [len(c.values), c.mr_bar]],
             "symbol": "none", "lineStyle": {"color": "#424242"}}],
    }


def hist_options(ax: spc.AxisSPC) -> dict[str, Any]:
    h = ax.histogram
    mids = [(a + b) / 2 for a, b in zip(h.edges[:-1], h.edges[1:], strict=True)]
    return {
        "title": {"text": f"{ax.axis}: histogram", "textStyle": {"fontSize": 13}},
        "animation": False, "grid": {"left": 40, "right": 10, "top": 30, "bottom": 25},
        "xAxis": {"type": "category", "data": [f"{m:.3g}" for m in mids]},
        "yAxis": {"type": "value"},
        "series": [{"type": "bar", "data": h.counts, "itemStyle": {"color": "#1e88e5"}}],
    }


# -- the pages ----------------------------------------------------------------------------------

def build(engine: StationEngine, views: Path | None, type1_reference: str | None) -> None:
    """Register the pages and the JSON endpoint of one station on NiceGUI's app."""
    station = engine.station
    needs_login = bool(station.line.users)
    if views is not None:
        views.mkdir(parents=True, exist_ok=True)
        app.add_static_files("/views", str(views))

    def header(title: str) -> None:
        with ui.header().classes("items-center justify-between bg-grey-9"):
            ui.label(f"aimbench station {station.name}: {title}").classes("text-h6")
            with ui.row().classes("items-center"):
                ui.link("operator", "/").classes("text-white")
                ui.link("engineer", "/engineer").classes("text-white")
                u = _user()
                if u is not None:
                    ui.label(f"{u.name} ({u.role})")
                    ui.button("log out", on_click=lambda: _logout(u)).props("flat color=white")

    def _logout(u: auth.User) -> None:
        engine.audit(u.name, u.role, "logout")
        app.storage.user.pop("login", None)
        ui.navigate.to("/")

    @ui.page("/", title=f"aimbench {station.name}")
    def operator_page() -> None:
        header("operator")
        s0 = engine.snapshot
        with ui.row().classes("w-full no-wrap items-start"):
            with ui.column().classes("w-1/2"):
                verdict = ui.label("READY").classes("text-white text-center w-full").style(
                    "font-size: 72px; font-weight: 700; padding: 18px; border-radius: 12px")
                verdict.props("id=verdict")
                unit_lbl = ui.label("").classes("text-h5").props("id=verdict-unit")
                phase = ui.label("").classes("text-subtitle1").props("id=phase")
                progress = ui.linear_progress(value=0, show_value=False).props("indeterminate")
                progress.visible = False
                unit_in = ui.input("unit id (scan or type, then Enter)").props(
                    "autofocus outlined input-class=text-h5").classes("w-full")
                message = ui.label("").classes("text-body1").props("id=message")
                alarms = ui.column()
            with ui.column().classes("w-1/2"):
                axes_box = ui.html("", sanitize=False).props("id=axes")
                board = ui.image().classes("w-full")
                board.visible = False
        ui.label("last units").classes("text-h6")
        last = ui.table(columns=[
            {"name": c, "label": c, "field": c} for c in
            ("record", "unit", "trial", "verdict", "when", "by", "batch")], rows=[],
            row_key="record").classes("w-full").props("dense id=last-units")

        async def go() -> None:
            unit = unit_in.value
            unit_in.value = ""
            u = _user()
            try:
                await engine.trigger(unit, "web", who=u.name if u else "operator",
                                     role=u.role if u else "operator")
            except Busy as exc:
                ui.notify(str(exc), type="warning")
            except AimbenchError as exc:
                ui.notify(str(exc), type="negative")
            unit_in.run_method("focus")

        unit_in.on("keydown.enter", go)
        shown = {"results": -1, "state": None, "scans": -1}

        def refresh() -> None:
            s = engine.snapshot
            busy_s = time.time() - s.started_at if s.state == "busy" and s.started_at else 0.0
            key = (s.state, s.results, round(busy_s, 1), s.message, len(s.alarms))
            if key == shown.get("key"):
                return
            shown["key"] = key
            r = s.result
            if s.state == "busy":
                text, color = "INSPECTING", COLORS["busy"]
                unit_lbl.text = f"unit {s.unit} ({s.origin})"
                phase.text = f"scanning and estimating: {busy_s:.1f} s"
            elif s.state == "error":
                text, color = "ERROR", COLORS["error"]
                unit_lbl.text = f"unit {s.unit}"
                phase.text = ""
            elif s.state == "done" and r is not None:
                text, color = r["verdict"].upper(), COLORS[r["verdict"]]
                unit_lbl.text = (f"unit {r['unit']} (record {r['record']}, trial {r['trial']},"
                                 f" {r['scans']} scans, {r['total_s'] or 0:.1f} s)")
                phase.text = ""
            else:
                text, color = "READY", COLORS["idle"]
                unit_lbl.text, phase.text = "", ""
            verdict.text = text
            verdict.style(f"background-color: {color}")
            verdict.props(f"data-state={s.state} data-unit={html.escape(s.unit or '')}")
            progress.visible = s.state == "busy"
            message.text = s.message
            if r is not None and s.state != "busy":
                rows = "".join(_axis_row(a) for a in r["axes"])
                axes_box.content = (f"<table>{rows}</table><div style='font-size:12px'>"
                                    f"rule {r['rule']}, U = {r['k']:g} u; orange: the guard "
                                    "bands (within U of a limit)</div>")
                if r.get("board_view"):
                    board.set_source(f"/views/{r['board_view']}")
                    board.visible = True
            alarms.clear()
            with alarms:
                for a in s.alarms:
                    ui.label(f"ALARM {a['axis']}: {a['rule']}, {a['text']}").classes(
                        "text-negative text-bold")
            last.rows = [{"record": x["id"], "unit": x["unit"], "trial": x["trial"],
                          "verdict": x["verdict"].upper(),
                          "when": time.strftime("%H:%M:%S", time.localtime(x["finished_at"])),
                          "by": x["operator"] or "-", "batch": x["batch"] or "-"}
                         for x in reversed(engine.rows(
                             "WHERE id IN (SELECT id FROM inspection ORDER BY id DESC LIMIT ?)",
                             (LAST_UNITS,)))]

        del s0
        ui.timer(0.1, refresh)

    @ui.page("/login", title="aimbench login")
    def login_page() -> None:
        header("login")
        if not needs_login:
            ui.label("This station names no users ([[line.users]] in the station file): the "
                     "engineer's page cannot be opened. Add an engineer (aimbench station "
                     "--hash-password) and start the station again.")
            return
        name = ui.input("name")
        pw = ui.input("password", password=True)

        def try_login() -> None:
            u = auth.authenticate(station, name.value or "", pw.value or "")
            if u is None:
                engine.audit(name.value, None, "login refused", {"page": "web"})
                ui.notify("wrong name or password", type="negative")
                return
            app.storage.user["login"] = {"name": u.name, "role": u.role}
            engine.audit(u.name, u.role, "login", {"page": "web"})
            ui.navigate.to("/engineer")

        pw.on("keydown.enter", try_login)
        ui.button("log in", on_click=try_login).props("id=login-button")

    @ui.page("/engineer", title=f"aimbench {station.name}: engineer")
    async def engineer_page() -> None:
        u = _user()
        if u is None or not u.may("engineer"):
            ui.navigate.to("/login")
            return
        header("engineer")
        # the SPC's columns only, computed off the event loop (the PLC's requests go on)
        rows = await asyncio.to_thread(engine.recent, light=True)
        with ui.row().classes("items-center"):
            ui.label(f"batch: {engine.snapshot.batch or '(none)'}").classes("text-h6")
            batch_in = ui.input("new batch")

            def set_batch() -> None:
                engine.set_batch(batch_in.value, u.name, u.role)
                ui.notify(f"batch set to {engine.snapshot.batch}")
                ui.navigate.reload()

            ui.button("set batch", on_click=set_batch)
        ui.label(f"SPC over the last {len(rows)} records"
                 + (f" of batch {engine.snapshot.batch}" if engine.snapshot.batch else "")
                 ).classes("text-h6")
        axes = await asyncio.to_thread(spc.line_spc, rows)
        cap_rows = []
        for ax in axes:
            if ax.chart is None:
                continue
            c = ax.capability
            cap_rows.append({"axis": ax.axis, "n": c.n, "mean": f"{c.mean:+.4f}",
                             "s within": f"{c.sigma_within:.4f}",
                             "s overall": f"{c.sigma_overall:.4f}", "Cp": f"{c.cp:.2f}",
                             "Cpk": f"{c.cpk:.2f}", "Pp": f"{c.pp:.2f}", "Ppk": f"{c.ppk:.2f}",
                             "signals": ", ".join(f"#{s.index + 1} Nelson {s.rule}"
                                                  for s in ax.chart.signals[-6:]) or "none"})
            with ui.row().classes("w-full no-wrap"):
                ui.echart(imr_options(ax)).classes("w-1/2 h-56").props(
                    f"id=imr-{ax.axis}")
                ui.echart(mr_options(ax)).classes("w-1/4 h-56")
                ui.echart(hist_options(ax)).classes("w-1/4 h-56")
        if not cap_rows:
            ui.label("fewer than two records with a pose: no charts yet")
        ui.table(columns=[{"name": k, "label": k, "field": k} for k in (
            "axis", "n", "mean", "s within", "s overall", "Cp", "Cpk", "Pp", "Ppk", "signals")],
            rows=cap_rows, row_key="axis").props("dense id=capability")
        await _studies(engine, type1_reference)
        st = station.to_dict()
        ui.label("station file in force").classes("text-h6")
        ui.label(f"{station.name}, sha256 {station_hash(st)}").props("id=station-hash")
        last = engine.rows("WHERE id = (SELECT MAX(id) FROM inspection)")
        cal = last[0]["calibration"] if last else {}
        ui.label(f"calibration: {json.dumps(cal) if cal else 'none'}")
        ui.code(json.dumps(st, indent=1), language="json").classes("w-full h-64")
        ui.label("audit trail").classes("text-h6")
        ui.table(columns=[{"name": k, "label": k, "field": k} for k in (
            "id", "when", "who", "role", "action", "detail")], rows=[
            {"id": a["id"], "when": time.strftime("%Y-%m-%d %H:%M:%S",
                                                  time.localtime(a["at"])),
             "who": a["who"] or "-", "role": a["role"] or "-", "action": a["action"],
             "detail": json.dumps(a["detail"])[:120]} for a in engine.audit_rows(100)],
            row_key="id").props("dense id=audit").classes("w-full")

    # -- JSON for MES ------------------------------------------------------------------------------

    def api_user(request: Request) -> auth.User | None:
        if not needs_login:
            return auth.User("mes", "plc")
        head = request.headers.get("authorization", "")
        if not head.startswith("Basic "):
            return None
        try:
            name, _, pw = base64.b64decode(head[6:]).decode().partition(":")
        except ValueError:
            return None
        return auth.authenticate(station, name, pw)

    def unauthorized() -> JSONResponse:
        return JSONResponse({"error": "unauthorized", "message": "give HTTP Basic credentials "
                             "of a station user who may inspect"}, status_code=401,
                            headers={"WWW-Authenticate": 'Basic realm="aimbench station"'})

    @app.get("/api/state")
    def api_state(request: Request) -> Any:
        if api_user(request) is None:
            return unauthorized()
        return engine.snapshot.to_dict()

    @app.post("/api/inspect")
    async def api_inspect(request: Request) -> Any:
        u = api_user(request)
        if u is None or not u.may("inspect"):
            return unauthorized()
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict) or "unit" not in body:
            return JSONResponse({"error": "bad request", "message": 'POST {"unit": "ID"}'},
                                status_code=400)
        try:
            return await engine.trigger(body["unit"], "http", who=u.name, role=u.role)
        except Busy as exc:
            return JSONResponse({"error": "busy", "message": str(exc)}, status_code=409)
        except AimbenchError as exc:
            code = 500 if engine.snapshot.state == "error" else 400
            return JSONResponse({"error": "inspection" if code == 500 else "bad request",
                                 "message": str(exc)}, status_code=code)

    @app.get("/api/records")
    def api_records(request: Request, limit: int = 50) -> Any:
        if api_user(request) is None:
            return unauthorized()
        rows = engine.rows("WHERE id IN (SELECT id FROM inspection ORDER BY id DESC LIMIT ?)",
                           (max(1, min(limit, 1000)),))
        return [result_dict(r) for r in rows]


def _axis_row(a: dict[str, Any]) -> str:
    """One judged axis on the operator's page: error +- U (limit), the picture, the verdict."""
    band = band_svg(a["value"], a["U"], a["limit"], a["verdict"])
    color = COLORS.get(a["verdict"] or "", "#000")
    return (f"<tr><td style='padding-right:12px'><b>{a['axis']}</b></td>"
            f"<td style='padding-right:12px'>{_fmt(a['value'])} &plusmn; "
            f"{'-' if a['U'] is None else format(a['U'], '.3f')} "
            f"(limit {a['limit']:.3g})</td><td>{band}</td><td style='color:{color}'>"
            f"{(a['verdict'] or 'not judged').upper()}</td></tr>")


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:+.3f}"


#: Gauge R&R results by (batch, records): its bootstrap takes seconds, once per study.
_GRR_CACHE: dict[tuple[str, int], Any] = {}


async def _studies(engine: StationEngine, type1_reference: str | None) -> None:
    """The Type-1 and gauge R&R studies found in the store (by their batches' names)."""
    from scenarios.inspection import msa, studies
    from scenarios.inspection.verdict import EDGE_SCALE, EDGE_UNIT, edge_key, limits_si

    ui.label("measurement system").classes("text-h6")
    batches = engine.batches()
    t1 = [b for b in batches if b.startswith("type1")]
    lims = limits_si(engine.station.tolerances)
    if t1:
        rows = engine.rows("WHERE batch = ?", (t1[-1],))
        ref = {}
        if type1_reference:
            ref = studies.read_reference(type1_reference)[1]
        table = []
        for a, lim in lims.items():
            key, s = edge_key(a), EDGE_SCALE[a]
            x = studies.type1_data(rows, a)
            truth = [r[f"true_{a}"] for r in rows if r[f"true_{a}"] is not None]
            reference = ref.get(key, truth[0] * s if truth else None)
            if reference is None or len(x) < 2:
                continue
            r = msa.type1(x, reference, 2 * lim * s, key, EDGE_UNIT[a])
            table.append({"axis": key, "n": r.n, "bias": f"{r.bias:+.4f}", "p": f"{r.p:.3f}",
                          "Cg": f"{r.cg:.2f}", "Cgk": f"{r.cgk:.2f}",
                          "capable": "yes" if r.capable else "NO"})
        ui.label(f"Type-1 study: batch {t1[-1]}")
        ui.table(columns=[{"name": k, "label": k, "field": k} for k in (
            "axis", "n", "bias", "p", "Cg", "Cgk", "capable")], rows=table,
            row_key="axis").props("dense id=type1")
    else:
        ui.label("Type-1 study: none in this store (aimbench grr --type1 --reference FILE "
                 f"--db {engine.db})")
    grr = [b for b in batches if b.startswith("grr")]
    if grr:
        from scenarios.inspection.studies import grr_report

        try:
            key = (grr[-1], batches[grr[-1]])
            if key not in _GRR_CACHE:
                _GRR_CACHE[key] = await asyncio.to_thread(
                    grr_report, engine.rows("WHERE batch = ?", (grr[-1],)), engine.station,
                    0.95)
            res = _GRR_CACHE[key]
            ui.label(f"gauge R&R: batch {grr[-1]}")
            ui.table(columns=[{"name": k, "label": k, "field": k} for k in (
                "axis", "%GRR tol", "ndc", "acceptance")], rows=[
                {"axis": g.axis, "%GRR tol": f"{g.pct_tolerance.get('GRR', float('nan')):.1f}",
                 "ndc": g.ndc, "acceptance": g.verdict} for g in res],
                row_key="axis").props("dense id=grr")
        except AimbenchError as exc:
            ui.label(f"gauge R&R of {grr[-1]}: {exc}")
    else:
        ui.label("gauge R&R: none in this store (aimbench grr --twin ... or --batch NAME)")


def run(engine: StationEngine, host: str, port: int, opcua: Any, views: Path | None,
        type1_reference: str | None) -> None:
    """Serve the pages, the endpoint and (started with the app) the OPC UA server."""
    build(engine, views, type1_reference)

    async def started() -> None:
        import asyncio

        engine._loop = asyncio.get_running_loop()
        if opcua is not None:
            await opcua.start()
        print(f"station {engine.station.name}: http://{host}:{port}/ (engineer: /engineer, "
              f"JSON: /api/state, /api/inspect)"
              + (f", OPC UA opc.tcp://{host}:{opcua.port}/aimbench/station" if opcua else ""),
              flush=True)

    async def stopped() -> None:
        if opcua is not None:
            await opcua.stop()
        engine.close()

    app.on_startup(started)
    app.on_shutdown(stopped)
    ui.run(host=host, port=port, reload=False, show=False, title="aimbench station",
           storage_secret=os.urandom(32).hex(), show_welcome_message=False,
           uvicorn_logging_level="warning", favicon="🎯")
