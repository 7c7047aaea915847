"""``formtwin serve``: live tracking over MQTT with a durable store and a live page."""

from __future__ import annotations

import argparse
import gc
import os
import signal
import threading
from pathlib import Path
from typing import Any

from formtwin.cli.options import (
    add_tracker_options,
    model_spec,
    noise_note,
    spec_defaults,
    tracker_config,
)
from formtwin.cli.source import add_source_options, make_service, opcua_results, opcua_source
from formtwin.service.plausibility import CLIP_SAMPLES

DEFAULT_TOPIC = "plant/line1/press1/stroke"


def add_broker_options(p: argparse.ArgumentParser) -> None:
    """Broker address and security options shared by serve and replay."""
    p.add_argument("--broker", default="mqtt://127.0.0.1:1883",
                   help="mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (default: %(default)s)")
    p.add_argument("--username", help="broker user name")
    p.add_argument("--password-file", help="file holding the broker password (else the "
                   "environment variable FORMTWIN_MQTT_PASSWORD is used)")
    p.add_argument("--tls", action="store_true", help="use TLS (implied by mqtts://)")
    p.add_argument("--ca-file", help="CA bundle (PEM) to verify the broker")
    p.add_argument("--cert-file", help="client certificate (PEM) for TLS client auth")
    p.add_argument("--key-file", help="client key (PEM) for TLS client auth")


def broker_config(args: argparse.Namespace) -> Any:
    """A :class:`~formtwin.service.mqtt.BrokerConfig` from the parsed options."""
    from formtwin.service.mqtt import BrokerConfig

    password = os.environ.get("FORMTWIN_MQTT_PASSWORD")
    if args.password_file:
        password = Path(args.password_file).read_text(encoding="utf-8").strip()
    if password is not None and not args.username:
        raise ValueError("a broker password was given but no --username")
    return BrokerConfig.from_url(args.broker, tls=args.tls, ca_file=args.ca_file,
                                 cert_file=args.cert_file, key_file=args.key_file,
                                 username=args.username, password=password)


def add_monitor_options(p: argparse.ArgumentParser) -> None:
    """Control charts and alarms (fixed with the store at its first start)."""
    g = p.add_argument_group("monitoring (EWMA/CUSUM charts, model-mismatch alarm)")
    g.add_argument("--no-monitor", action="store_true", help="no control charts or alarms")
    g.add_argument("--monitor-config", metavar="FILE.json",
                   help="chart configuration with user-set in-control means, sigmas and "
                   "limits (MonitorConfig JSON); default: calibrated on simulated in-control "
                   "runs with the spec's statistics")
    g.add_argument("--cache", metavar="DIR",
                   help="folder of the chart calibrations and measurement models a new "
                   "store computes at its first start, kept by a digest of their inputs and "
                   "reused by the next new store with the same ones (default: "
                   "$FORMTWIN_CACHE, else $XDG_CACHE_HOME/formtwin, else ~/.cache/formtwin;"
                   " '' for none)")
    g.add_argument("--monitor-runs", type=int, default=2,
                   help="simulated in-control runs to calibrate on (default: %(default)s)")
    g.add_argument("--monitor-products", type=int, default=600,
                   help="products per calibration run (default: %(default)s)")
    g.add_argument("--monitor-warmup", type=int, default=50,
                   help="products not charted at the start (default: %(default)s)")
    g.add_argument("--monitor-phase1", type=int, default=100,
                   help="products after the warm-up that set the angles' in-control level "
                   "(default: %(default)s)")
    g.add_argument("--monitor-arl0", type=float, default=1.0e6,
                   help="in-control average run length of each state variable's CUSUM chart "
                   "(default: %(default)g; EWMA, GLR and mismatch charts: 1e7, 1e5, 1e7)")


def control_settings(args: argparse.Namespace) -> Any:
    """The service's :class:`~formtwin.service.control.ControlSettings` from the serve
    options (None without ``--target-angle``): the weight learned on the line unless
    ``--control-fixed-weight``; options not given take the control study's tuning."""
    if args.target_angle is None:
        return None
    from formtwin.service.control import ControlSettings

    given = {k: v for k, v in (("lam", args.control_lam), ("weight", args.control_weight),
                                ("rho", args.control_rho)) if v is not None}
    if args.control_fixed_weight:
        return ControlSettings.fixed_weight(args.target_angle, args.control_max_step, **given)
    return ControlSettings(args.target_angle, args.control_max_step, **given)


def _controller(args: argparse.Namespace, proc: Any) -> None:
    """Attach feedforward control to ``proc`` when ``--target-angle`` is given."""
    settings = control_settings(args)
    if settings is None:
        return
    from formtwin.service.control import ServiceController

    proc.controller = ServiceController(proc.tracker, settings, proc.store)


def _cache_dir(args: argparse.Namespace) -> str | None:
    """``--cache`` (None for '': no cache; not given: the default folder)."""
    if args.cache is None:
        from formtwin.service.cache import default_dir

        return str(default_dir())
    return args.cache or None


def _monitor(args: argparse.Namespace, proc: Any) -> Any:
    """The service's charts (None with --no-monitor), attached to ``proc``."""
    if args.no_monitor:
        return None
    from formtwin.monitoring.calibrate import ChartDesign
    from formtwin.service.alarms import MonitorSource, ServiceMonitor, monitor_config

    design = ChartDesign(warmup=args.monitor_warmup, phase1=args.monitor_phase1,
                         arl0_per_chart=args.monitor_arl0)
    source = MonitorSource(file=args.monitor_config, runs=args.monitor_runs,
                           products=args.monitor_products, design=design,
                           seed=proc.tracker.config.seed, cache=_cache_dir(args))
    monitor = ServiceMonitor(proc.store, monitor_config(proc.store, proc.tracker, source),
                             source.cache)
    proc.monitor = monitor
    return monitor


def add_check_options(p: argparse.ArgumentParser) -> None:
    """Plausibility limits, model-health rule and ``--check`` (docs/explanation/service.md)."""
    g = p.add_argument_group("plausibility of a stroke and model health (default limits "
                             "derived from the spec's ranges through the model)")
    g.add_argument("--min-peak", type=float, metavar="N",
                   help="lowest peak force of a stroke, N (default: half the smallest peak "
                   "the model gives over the spec's ranges): below it, no_stroke")
    g.add_argument("--clip-samples", type=int, default=CLIP_SAMPLES, metavar="K",
                   help="K consecutive samples at the maximum are a clipped sensor "
                   "(default: %(default)s)")
    g.add_argument("--peak-window", metavar="LO,HI",
                   help="accepted positions of the peak force on the curve axis, in the "
                   "spec's [curve] unit (ms for the demonstrator; default: the model's range "
                   "over the spec's ranges, widened by 5 samples)")
    g.add_argument("--mismatch-k", type=int, default=5, metavar="K",
                   help="model_mismatch when K of the last M products are not explained "
                   "(default: %(default)s)")
    g.add_argument("--mismatch-m", type=int, default=10, metavar="M",
                   help="window of the mismatch rule, products (default: %(default)s)")
    g.add_argument("--check", type=int, metavar="N",
                   help="process the first N products, then exit: 0 if the model explains "
                   "them, 1 with the model_mismatch message if it does not")


def _window(text: str | None) -> tuple[float, float] | None:
    """``--peak-window LO,HI`` as two floats (ms)."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--peak-window {text!r}: expected LO,HI in the spec's curve unit, "
                         "e.g. -50,5 (ms)") from None
    return lo, hi


def _page_token(args: argparse.Namespace) -> str:
    """The configured page token ('' when none: the page is read-only)."""
    if args.page_token_file:
        return Path(args.page_token_file).read_text(encoding="utf-8").strip()
    return str(args.page_token or os.environ.get("FORMTWIN_PAGE_TOKEN", "")).strip()


class _Check:
    """``--check N``: stop after N accepted products, or at the first model mismatch."""

    def __init__(self, proc: Any, n: int, stop: threading.Event) -> None:
        self.proc, self.n, self.stop = proc, n, stop
        self.accepted = 0
        self.mismatch: dict[str, Any] | None = None
        self.listener: Any = None
        #: what to say about the sensor noise when the model does not explain the products
        self.noise = ""

    def __call__(self, out: Any) -> None:
        if self.listener is not None:
            self.listener(out)
        for note in out.notices:
            if note.get("reason") == "model_mismatch":
                self.mismatch = note
        if out.kind == "accepted":
            self.accepted += 1
        if self.mismatch is not None or self.accepted >= self.n:
            self.stop.set()

    def report(self) -> int:
        """Print the outcome; the exit code."""
        if self.mismatch is not None:
            print(f"model_mismatch after {self.accepted} products: {self.mismatch['detail']}",
                  flush=True)
            if self.noise:
                print(self.noise, flush=True)
            return 1
        if self.accepted < self.n:
            print(f"check incomplete: {self.accepted} of {self.n} products received", flush=True)
            return 1
        print(f"check passed: the model explains the first {self.n} products", flush=True)
        return 0


def register(sub: Any) -> None:
    """Add the ``serve`` command to the subparsers ``sub``."""
    p = sub.add_parser("serve", help="track live strokes from MQTT or OPC UA; store, publish, "
                       "live page",
                       description="Subscribe to force-curve strokes (MQTT QoS 1, or a "
                       "press's OPC UA server with --source) and to the line's sensor values, "
                       "run one tracker step per product, commit product + estimate + "
                       "checkpoint to SQLite, publish the estimate, acknowledge. Safe to kill "
                       "and restart.")
    model = p.add_mutually_exclusive_group(required=True)
    model.add_argument("--metamodel", help="metamodel file (formtwin.metamodel)")
    model.add_argument("--analytic", action="store_true",
                       help="use the closed-form analytic stand-in instead of a metamodel")
    add_broker_options(p)
    add_source_options(p)
    p.add_argument("--topic", default=DEFAULT_TOPIC, help="stroke topic (default: %(default)s)")
    p.add_argument("--results-topic", help="default: sibling 'estimate' of --topic")
    p.add_argument("--errors-topic", help="default: sibling 'errors' of --topic")
    p.add_argument("--alarms-topic", help="default: sibling 'alarms' of --topic")
    p.add_argument("--sensor-topic", help="sensor messages; default: sibling 'sensor'")
    p.add_argument("--client-id", default="formtwin-serve",
                   help="persistent MQTT session id; keep it across restarts (--check runs "
                   "on a clean session <id>-check-<pid> of its own)")
    p.add_argument("--store", default="formtwin-serve.sqlite",
                   help="SQLite store (default: %(default)s)")
    p.add_argument("--sync", choices=("normal", "full"), default="normal",
                   help="SQLite synchronous: normal survives kills, full also power loss")
    p.add_argument("--checkpoint-every", type=int, default=10, metavar="K",
                   help="store the tracker's state with every K-th product; a restart "
                   "replays the curves stored after it (default: %(default)s)")
    add_tracker_options(p)
    p.add_argument("--gate", type=float, default=0.0, metavar="K",
                   help="robust: gate single outlier curves whose loglik is K robust std "
                   "below the recent median (0: off)")
    p.add_argument("--max-bytes", type=int, default=65536, help="largest message, bytes")
    p.add_argument("--min-force", type=float, default=-50.0, help="lowest force sample, N")
    p.add_argument("--max-force", type=float, default=1.0e4, help="highest force sample, N")
    p.add_argument("--http-host", default="127.0.0.1", help="page bind address")
    p.add_argument("--http-port", type=int, default=8765, help="page port (0: any free)")
    p.add_argument("--no-page", action="store_true", help="do not serve the live page")
    p.add_argument("--page-token", help="token that state-changing actions on the page "
                   "(acknowledging alarms) need; prefer --page-token-file or the environment "
                   "variable FORMTWIN_PAGE_TOKEN (default: none, the page is read-only and "
                   "binds 127.0.0.1 only)")
    p.add_argument("--page-token-file", help="file holding the page token")
    add_check_options(p)
    add_monitor_options(p)
    g = p.add_argument_group("feedforward control of the final angle")
    g.add_argument("--target-angle", type=float, metavar="DEG",
                   help="suggest each product's press setting u for this final angle "
                   "(in the estimate message, 'control'); default: no suggestion")
    g.add_argument("--control-max-step", type=float, default=0.25, metavar="SHARE",
                   help="largest change of u per product, share of its range "
                   "(default: %(default)s)")
    g.add_argument("--control-lam", type=float, metavar="LAM",
                   help="EWMA weight of the trim on the measured final angles, 0-1 "
                   "(default: the control study's tuning)")
    g.add_argument("--control-rho", type=float, metavar="RHO",
                   help="persistence of the last product's deviation from the level, 0-1 "
                   "(default: the control study's tuning)")
    g.add_argument("--control-fixed-weight", action="store_true",
                   help="trust a fixed share of the estimates' product-to-product change "
                   "(default: the share learned on the line, the control study's best)")
    g.add_argument("--control-weight", type=float, metavar="W",
                   help="that share, 0-1 (with --control-fixed-weight; default: the control "
                   "study's best fixed weight), or the learned share's start (default 0)")
    p.add_argument("--status-every", type=float, default=60.0, metavar="S",
                   help="print a status line every S seconds (0: never)")
    p.add_argument("--connect-timeout", type=float, default=10.0,
                   help="seconds to wait for the broker at start")
    p.set_defaults(run=_serve)


def _serve(args: argparse.Namespace) -> int:
    from formtwin.service.mqtt import Topics
    from formtwin.service.runtime import ServiceSettings, open_processor

    broker = broker_config(args)
    topics = Topics.from_input(args.topic, args.results_topic, args.errors_topic,
                               args.alarms_topic, args.sensor_topic)
    source = opcua_source(args)
    if args.metamodel and not Path(args.metamodel).exists():
        raise ValueError(f"--metamodel {args.metamodel}: no such file")
    defaults = spec_defaults(model_spec(args))
    settings = ServiceSettings(
        model="analytic" if args.analytic else str(Path(args.metamodel).resolve()),
        tracker=tracker_config(args, defaults), gate_k=args.gate, max_bytes=args.max_bytes,
        min_force_N=args.min_force, max_force_N=args.max_force, min_peak_N=args.min_peak,
        clip_samples=args.clip_samples, peak_window_ms=_window(args.peak_window),
        health_k=args.mismatch_k, health_m=args.mismatch_m)
    token = _page_token(args)
    if args.check is not None and args.check < 1:
        raise ValueError(f"--check {args.check}: expected >= 1 products")
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the step is many small products (see formtwin._threads)
    threadpool_limits(limits=1, user_api="blas")
    proc = open_processor(args.store, settings, synchronous=args.sync.upper(),
                          checkpoint_every=args.checkpoint_every, cache=_cache_dir(args))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    page = monitor = results = None
    check = None if args.check is None else _Check(proc, args.check, stop)
    if check is not None:
        check.noise = noise_note(settings.tracker, model_spec(args))
    try:
        monitor = _monitor(args, proc)
        _controller(args, proc)
        describe = getattr(proc.plausible, "describe", None)
        if describe is not None:
            print(describe(), flush=True)
        print(f"tracker sensor noise: {settings.tracker.sensor_noise:g} N"
              + ("" if settings.tracker.sensor_noise > 0 else " (no [curve] noise_sd in the "
                 "spec and no --sensor-noise: a real sensor's noise reads as model mismatch)"),
              flush=True)
        counts = proc.store.counts()
        print(f"store {args.store}: {counts['accepted']} accepted, {counts['gated']} gated, "
              f"{counts['rejected']} rejected", flush=True)
        service = make_service(args, proc, broker, topics, source, check=check is not None)
        if not args.no_page:
            from formtwin.service.web import LiveFeed, PageServer
            from formtwin.spec import load_spec

            # units and outputs of the running spec (the tracker's), else the demonstrator's
            spec = getattr(proc.tracker, "spec", None) or load_spec()
            units = {v.name: v.internal_unit for v in spec.augmented}
            outputs = [{"name": o.name, "label": o.label, "unit": o.unit}
                       for o in spec.outputs]
            feed = LiveFeed(proc.tracker_names(), units=units, outputs=outputs,
                            sensors=tuple(proc.sensors.sensors))
            feed.seed(proc.store)
            feed.health_state = getattr(proc.health, "state", None)
            feed.n_particles = getattr(getattr(proc.tracker, "config", None), "n_particles",
                                       None)
            proc.on_outcome = feed.on_outcome
            page = PageServer(feed, args.http_host, args.http_port, token)
            if monitor is not None:
                from formtwin.service.alarm_api import add_alarm_routes

                add_alarm_routes(page.app, monitor, feed, token, on_ack=service.publish_alarm)
            url = page.start()
            print(f"live page: {url}" + (f"?token={token}" if token else ""), flush=True)
        results = opcua_results(args, proc)
        if check is not None:
            check.listener, proc.on_outcome = proc.on_outcome, check
        # the ~10^5 objects of the model, the libraries and the page live as long as the
        # process: kept out of the garbage collector's full collections, which otherwise
        # take ~60 ms every few hundred products and stall the stream (p99 latency)
        gc.freeze()
        if args.status_every > 0:
            threading.Thread(target=_status, args=(proc, service, stop, args.status_every),
                             daemon=True, name="formtwin-status").start()
        strokes = f"{topics.strokes} (sensor messages on {topics.sensors}) on " \
            f"{broker.host}:{broker.port}" if args.source is None \
            else f"{args.source} (OPC UA; results on {broker.host}:{broker.port})"
        print(f"serving {strokes} -> "
              f"{topics.results}, errors -> {topics.errors}"
              + (f", alarms -> {topics.alarms}" if monitor is not None else ""), flush=True)
        service.run(stop, timeout=args.connect_timeout,
                    on_connected=lambda: print("connected and subscribed", flush=True))
        print(f"stopped after {service.handled} messages ({service.busy_s:.2f} s busy, "
              f"tracker steps {proc.step_cpu_s:.3f} s CPU)",
              flush=True)
        if check is not None:
            return check.report()
    finally:
        if page is not None:
            page.stop()
        if results is not None:
            results.stop()
        proc.close()
    return 0


def _status(proc: Any, service: Any, stop: threading.Event, every: float) -> None:
    """Print a status line every ``every`` seconds until ``stop``."""
    last = service.handled
    while not stop.wait(every):
        c = proc.store.counts()
        rate = (service.handled - last) / every
        last = service.handled
        print(f"status: {c['accepted']} accepted, {c['gated']} gated, {c['rejected']} "
              f"rejected, {proc.redelivered} redelivered; {rate:.1f} messages/s; broker "
              f"{'connected' if service.connected.is_set() else 'DISCONNECTED'}", flush=True)
