"""The live page: FastAPI, Server-Sent Events and uPlot (shipped in ``static/``).

Routes

* ``GET /`` -- the page (``static/index.html`` + ``static/live.js``);
* ``GET /api/state`` -- variable names, recent points and counters (JSON);
* ``GET /events`` -- Server-Sent Events, one ``data:`` line per processed message, ids
  ``<epoch>:<n>``; a client coming back with another epoch (the service restarted) gets a
  ``reset`` event and reloads ``/api/state``;
* ``GET /static/...`` -- uPlot (MIT, see ``static/uPlot.LICENSE``) and the page's script.

The page is read-only unless a page token is configured (``formtwin serve
--page-token-file``, ``FORMTWIN_PAGE_TOKEN``): every state-changing request (acknowledging
an alarm) carries it in the header ``X-Formtwin-Token`` (:func:`token_ok`). Without a token
the page binds 127.0.0.1 only (:class:`PageServer` refuses any other address). A model
mismatch (:mod:`formtwin.service.health`) shows as a banner in words.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import threading
from collections import deque
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles

from formtwin.service.processor import Outcome
from formtwin.service.sensors import MEASUREMENT_SCHEMA, MEASUREMENTS_DDL
from formtwin.service.store import Store
from formtwin.spec import DEFAULT_OUTPUTS

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
#: the request header carrying the page token (state-changing requests need it)
TOKEN_HEADER = "x-formtwin-token"


class LiveFeed:
    """Thread-safe ring of recent points and counters, fed by processor outcomes.

    Parameters
    ----------
    names : tuple of str
        Names of the estimated quantities.
    maxlen : int
        Points kept for a page that (re)loads.
    units : dict, optional
        Unit of each name (internal units), shown on the page.
    outputs : list of dict, optional
        The spec's scalar outputs as ``{"name", "label", "unit"}``, one chart each (None:
        the demonstrator's two bend angles).
    sensors : tuple of str
        The sensors the service fuses (:mod:`formtwin.service.sensors`): the page shows
        their last values, and a camera's measured final angle against the prediction and
        calibrated interval issued for its product.
    """

    def __init__(self, names: tuple[str, ...], maxlen: int = 2000,
                 units: dict[str, str] | None = None,
                 outputs: list[dict[str, str]] | None = None,
                 sensors: tuple[str, ...] = ()) -> None:
        self.names = names
        self.units = dict(units or {})
        self.outputs = list(outputs) if outputs is not None else [
            {"name": o.name, "label": o.label, "unit": o.unit} for o in DEFAULT_OUTPUTS]
        #: changes with every process: a page that reconnects to a restarted service sees
        #: another epoch in its Last-Event-ID and reloads the state instead of waiting
        self.epoch = secrets.token_hex(4)
        self._lock = threading.Lock()
        self._events: deque[tuple[int, dict[str, Any]]] = deque(maxlen=maxlen)
        self._n = 0
        self.counts: dict[str, int] = {"accepted": 0, "gated": 0, "rejected": 0,
                                       "redelivered": 0}
        self.reasons: dict[str, int] = {}
        #: the model-health state for the banner (``ModelHealth.state``), if any
        self.health_state: Callable[[], dict[str, Any]] | None = None
        #: N of the tracker (the ESS chart's axis runs from 0 to N)
        self.n_particles: int | None = None
        #: the sensors the service fuses (:mod:`formtwin.service.sensors`), their last
        #: values, and the camera's values with the prediction issued for their products
        self.sensors = list(sensors)
        self.last_values: dict[str, dict[str, Any]] = {}
        self._finals: deque[dict[str, Any]] = deque(maxlen=maxlen)

    def seed(self, store: Store, n: int = 500) -> None:
        """Load counters and the last ``n`` points from the store (at start-up)."""
        c = store.counts()
        rows = list(store.products(since_seq=max(store.next_seq() - 1 - n, 0),
                                   status="accepted"))
        with self._lock:
            self.counts.update(c)
            self.reasons = store.rejection_counts()
        for r in rows:
            if r.estimate is not None:
                self._push(_point(r.estimate))
        store.ensure_tables(MEASUREMENTS_DDL)
        for (text,) in store.query("SELECT message FROM (SELECT id, message FROM "
                                   "measurements ORDER BY id DESC LIMIT ?) ORDER BY id", (n,)):
            self._sensor(json.loads(text))

    def push(self, event: dict[str, Any]) -> None:
        """Queue an event for the pages (e.g. an acknowledged alarm)."""
        self._push(event)

    def _push(self, event: dict[str, Any]) -> None:
        with self._lock:
            self._n += 1
            event["counts"] = dict(self.counts)
            event["reasons"] = dict(self.reasons)
            self._events.append((self._n, event))

    def on_outcome(self, out: Outcome) -> None:
        """Processor listener: count the outcome and queue an event."""
        with self._lock:
            self.counts[out.kind] = self.counts.get(out.kind, 0) + 1
            if out.is_error:
                reason = str(out.message.get("reason", "?"))
                self.reasons[reason] = self.reasons.get(reason, 0) + 1
        if out.kind == "accepted":
            self._push(_point(out.message))
            for answer in out.sensor_answers:  # values held for it, fused with it
                self._push({"type": "sensor", **self._sensor(answer)})
            if out.alarms:
                self._push({"type": "alarms", "alarms": list(out.alarms)})
            if out.notices:  # the model-health state changed: the banner follows
                self._push({"type": "health", "notices": list(out.notices),
                            "health": self._health()})
        elif out.message.get("schema") == MEASUREMENT_SCHEMA:
            self._push({"type": "sensor", **self._sensor(out.message)})
        elif out.is_error:
            self._push({"type": "rejected", "reason": out.message.get("reason"),
                        "detail": out.message.get("detail"), "part_id": out.part_id})
        else:
            self._push({"type": "counts"})

    def _sensor(self, msg: dict[str, Any]) -> dict[str, Any]:
        """Keep a sensor message's value (and a camera's with its prediction)."""
        keys = ("part_id", "sensor", "value", "status", "index", "predicted_deg",
                "interval90_deg")
        event = {k: msg.get(k) for k in keys}
        event["redelivered"] = bool(msg.get("redelivered"))
        with self._lock:
            self.last_values[str(msg.get("sensor"))] = event
            if event["predicted_deg"] is not None and event["status"] != "held" \
                    and not event["redelivered"]:
                self._finals.append(event)
        return event

    def since(self, n: int) -> tuple[int, list[tuple[int, dict[str, Any]]]]:
        """The newest event number and the ``(number, event)`` pairs after ``n``."""
        with self._lock:
            return self._n, [(k, e) for k, e in self._events if k > n]

    def _health(self) -> dict[str, Any] | None:
        try:
            return None if self.health_state is None else self.health_state()
        except Exception:  # the page must never break the tracking
            log.exception("reading the model-health state failed")
            return None

    def snapshot(self) -> dict[str, Any]:
        """The recent estimates as JSON-ready values (the page's first draw)."""
        health = self._health()
        with self._lock:
            points = [e for _, e in self._events if e.get("type") == "point"]
            return {"names": list(self.names), "units": self.units, "points": points,
                    "outputs": self.outputs,
                    "last": self._n,
                    "epoch": self.epoch, "counts": dict(self.counts),
                    "reasons": dict(self.reasons), "health": health,
                    "n_particles": self.n_particles, "sensors": list(self.sensors),
                    "last_values": dict(self.last_values), "finals": list(self._finals)}


def _point(msg: dict[str, Any]) -> dict[str, Any]:
    return {"type": "point", "seq": msg.get("seq"), "part_id": msg.get("part_id"),
            "index": msg.get("index"), "mean": msg.get("mean"), "std": msg.get("std"),
            "angles_mean": msg.get("angles_mean"), "angles_std": msg.get("angles_std"),
            "measured_angles": msg.get("measured_angles_deg"), "ess": msg.get("ess"),
            "collapsed": msg.get("collapsed"), "monitoring": msg.get("monitoring"),
            "health": msg.get("health"), "fit": msg.get("fit"),
            "model_health": msg.get("model_health")}


def create_app(feed: LiveFeed, poll_s: float = 0.1) -> FastAPI:
    """The FastAPI application of the live page (FastAPI resolves the handlers'
    annotations from this module's globals, hence the imports at the top)."""
    app = FastAPI(title="formtwin live", docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    app.state.closing = False

    @app.get("/")
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    @app.get("/favicon.ico")
    def favicon() -> Response:
        return Response(status_code=204)

    @app.get("/api/state")
    def state() -> JSONResponse:
        return JSONResponse(feed.snapshot())

    @app.get("/events")
    async def events(request: Request, last: int = -1, epoch: str = "") -> StreamingResponse:
        """Server-sent events: one per new estimate."""
        async def stream() -> AsyncIterator[str]:
            header = request.headers.get("last-event-id", "")
            ep, _, num = header.partition(":")
            if header and num.isdigit():
                client_epoch, n = ep, int(num)
            else:
                client_epoch, n = epoch, (feed.since(0)[0] if last < 0 else last)
            if client_epoch and client_epoch != feed.epoch:  # the service was restarted
                n = feed.since(0)[0]
                yield f"id: {feed.epoch}:{n}\ndata: {json.dumps({'type': 'reset'})}\n\n"
            idle = 0.0
            while not app.state.closing:
                if await request.is_disconnected():
                    break
                newest, items = feed.since(n)
                if items:
                    n = newest
                    idle = 0.0
                    for k, e in items:
                        data = json.dumps(e, allow_nan=False)
                        yield f"id: {feed.epoch}:{k}\ndata: {data}\n\n"
                else:
                    idle += poll_s
                    if idle >= 15.0:
                        idle = 0.0
                        yield ": keepalive\n\n"
                await asyncio.sleep(poll_s)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})

    return app


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address or ``localhost``."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def token_ok(request: Request, token: str) -> JSONResponse | None:
    """None if ``request`` may change state (header ``X-Formtwin-Token`` equal to the
    configured ``token``), else the 403 answer: the page is read-only without a configured
    token, and a wrong or missing token is refused."""
    import hmac

    if not token:
        return JSONResponse({"error": "the page is read-only: start formtwin serve with "
                             "--page-token-file or FORMTWIN_PAGE_TOKEN to act from it"},
                            status_code=403)
    given = request.headers.get(TOKEN_HEADER, "")
    if not hmac.compare_digest(given.encode(), token.encode()):
        return JSONResponse({"error": "page token missing or wrong"}, status_code=403)
    return None


class PageServer:
    """Run the page with uvicorn in a background thread.

    Parameters
    ----------
    feed : LiveFeed
    host : str
        Bind address; 127.0.0.1 by default. Any other address needs ``token``.
    port : int
        TCP port (0 picks a free one; see :attr:`url` after :meth:`start`).
    token : str
        The page token configured for state-changing actions (empty: the page is
        read-only, and only 127.0.0.1 is served).
    """

    def __init__(self, feed: LiveFeed, host: str = "127.0.0.1", port: int = 8765,
                 token: str = "") -> None:
        import uvicorn

        if not token and not is_loopback(host):
            raise ValueError(f"the live page binds {host!r} only with a page token "
                             "(--page-token-file or FORMTWIN_PAGE_TOKEN): without one it "
                             "serves 127.0.0.1 alone")
        self.app = create_app(feed)
        self._server = uvicorn.Server(uvicorn.Config(
            self.app, host=host, port=port, log_level="warning", access_log=False,
            timeout_graceful_shutdown=1, lifespan="off"))
        self._thread = threading.Thread(target=self._server.run, name="formtwin-page",
                                        daemon=True)
        self.host = host
        self.port = port

    def start(self, timeout: float = 10.0) -> str:
        """Start serving; return the page's URL."""
        self._thread.start()
        for _ in range(int(timeout / 0.05)):
            if self._server.started:
                break
            if not self._thread.is_alive():
                raise OSError(f"the page could not bind {self.host}:{self.port}")
            threading.Event().wait(0.05)
        else:
            raise OSError(f"the page did not start within {timeout:g} s")
        servers = getattr(self._server, "servers", [])
        if servers and servers[0].sockets:
            self.port = int(servers[0].sockets[0].getsockname()[1])
        return self.url

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{self.host}:{self.port}/"

    def stop(self) -> None:
        """Stop the page server and wait for its thread."""
        self.app.state.closing = True
        self._server.should_exit = True
        self._thread.join(timeout=5.0)
