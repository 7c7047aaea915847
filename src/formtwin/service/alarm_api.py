"""The live page's alarm routes (added to the app of :mod:`formtwin.service.web`).

* ``GET /api/monitor`` -- the charted quantities, chart settings and limits;
* ``GET /api/alarms?unacked=1&active=1`` -- stored alarm episodes, oldest first (raised,
  active or cleared, acknowledged or not; :mod:`formtwin.monitoring.episodes`);
* ``GET /api/signals?since_seq=N`` -- the per-product signals (a chart beyond its limit),
  each with its episode's id;
* ``POST /api/alarms/{id}/ack`` -- acknowledge an episode; needs the page token (header
  ``X-Formtwin-Token``, the ``token`` of the page's URL as printed by ``formtwin serve``):
  reading is open on the page's address, acting is not. A wrong or missing token is 403, an
  unknown id 404. The acknowledgement is stored, sent to every open page and, with
  ``on_ack``, published (the serve command: on the alarms topic, event ``acknowledged``,
  so a control room or MES that subscribes sees who has seen what).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from formtwin.service.alarms import ServiceMonitor
from formtwin.service.web import TOKEN_HEADER, LiveFeed, token_ok


def add_alarm_routes(app: FastAPI, monitor: ServiceMonitor, feed: LiveFeed, token: str,
                     on_ack: Callable[[dict[str, Any]], None] | None = None) -> None:
    """Add the alarm routes to ``app``; acknowledging needs ``token`` (empty: the page is
    read-only, acknowledging is refused, :func:`formtwin.service.web.token_ok`);
    ``on_ack`` gets each acknowledged episode as ``{"event": "acknowledged", **episode}``
    (again on a repeated acknowledgement, which keeps the first one's time and note)."""

    @app.get("/api/monitor")
    def limits() -> JSONResponse:
        return JSONResponse(monitor.limits())

    @app.get("/api/alarms")
    def alarms(unacked: int = 0, active: int = 0) -> JSONResponse:
        return JSONResponse(monitor.alarms(unacked=bool(unacked), active=bool(active)))

    @app.get("/api/signals")
    def signals(since_seq: int = 0) -> JSONResponse:
        return JSONResponse(monitor.signals(since_seq=since_seq))

    @app.post("/api/alarms/{alarm_id}/ack")
    async def ack(alarm_id: int, request: Request) -> JSONResponse:
        refused = token_ok(request, token)
        if refused is not None:
            return refused
        note = ""
        if request.headers.get("content-type", "").startswith("application/json"):
            try:
                body: Any = await request.json()
            except ValueError:
                return JSONResponse({"error": "body is not JSON"}, status_code=400)
            note = str(body.get("note", "")) if isinstance(body, dict) else ""
        try:
            alarm = monitor.acknowledge(alarm_id, note)
        except KeyError:
            return JSONResponse({"error": f"no alarm with id {alarm_id}"}, status_code=404)
        feed.push({"type": "ack", "alarm": alarm})
        if on_ack is not None:
            on_ack({"event": "acknowledged", **alarm})
        return JSONResponse(alarm)


__all__ = ["TOKEN_HEADER", "add_alarm_routes"]
