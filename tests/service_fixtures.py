"""Test helpers for the service: a private mosquitto on 127.0.0.1, free ports, a serve
subprocess. Imported by ``tests/test_service*.py`` (the tests folder is on ``sys.path``)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def find_binary(name: str, extra: tuple[str, ...] = ()) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    for p in extra:
        if os.path.exists(p):
            return p
    return None


def require_binary(name: str, extra: tuple[str, ...] = ()) -> str:
    """The binary's path; skip only when not root and it is missing (as root, fail: `make
    test` installs it through `make system-deps`)."""
    path = find_binary(name, extra)
    if path is None:
        if os.geteuid() == 0:
            pytest.fail(f"{name} is not installed; run `make system-deps` (apt-get install "
                        f"mosquitto chromium)")
        pytest.skip(f"{name} not installed and not root: `sudo make system-deps` to run "
                    "this test")
    return path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listening on 127.0.0.1:{port} after {timeout} s")


class Mosquitto:
    """A private mosquitto broker on 127.0.0.1 (temporary config, no persistence)."""

    def __init__(self, workdir: Path, extra_conf: str = "", anonymous: bool = True,
                 port: int | None = None) -> None:
        self.binary = require_binary("mosquitto", ("/usr/sbin/mosquitto",))
        self.workdir = workdir
        self.conf = workdir / "mosquitto.conf"
        for attempt in range(3):  # a free port may be taken before the broker binds it
            self.port = free_port() if port is None else port
            self.conf.write_text(
                f"listener {self.port} 127.0.0.1\n"
                f"allow_anonymous {'true' if anonymous else 'false'}\n"
                "persistence false\n"
                "max_queued_messages 100000\n"
                "max_inflight_messages 50\n"
                "log_dest stderr\n"
                "log_type error\n"
                "log_type warning\n" + extra_conf, encoding="utf-8")
            self.log = open(workdir / "mosquitto.log", "wb")  # noqa: SIM115
            self.proc = subprocess.Popen([self.binary, "-c", str(self.conf)],
                                         stdout=self.log, stderr=subprocess.STDOUT)
            try:
                wait_port(self.port)
                time.sleep(0.1)
            except TimeoutError:
                self.stop()
                raise
            if self.proc.poll() is None:
                return
            # it exited: the port was taken meanwhile (tests in parallel), and what
            # answered on it is another test's broker, never to be shared
            self.stop()
            if port is not None or attempt == 2:
                raise RuntimeError(f"mosquitto exited ({self.proc.returncode}) on port "
                                   f"{self.port}: {(workdir / 'mosquitto.log').read_text()}")

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.log.close()


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[Mosquitto]:
    """A running private broker for one test."""
    broker = Mosquitto(tmp_path)
    try:
        yield broker
    finally:
        broker.stop()


#: run the formtwin CLI in a subprocess with this interpreter
FORMTWIN = [sys.executable, "-c", "import sys; from formtwin.cli import main; sys.exit(main())"]


def serve_cmd(broker: Mosquitto, store: Path, *extra: str) -> list[str]:
    """Command line of a `formtwin serve` subprocess (analytic stand-in)."""
    return [*FORMTWIN, "serve", "--analytic", "--broker", broker.url, "--store", str(store),
            *extra]


def wait_serving(proc: subprocess.Popen[bytes], log: Path, timeout: float = 60.0) -> None:
    """Wait for a serve subprocess to be subscribed; fail with its log if it dies."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log_has(log, "connected and subscribed"):
            return
        if proc.poll() is not None:
            pytest.fail(f"serve exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        time.sleep(0.05)
    pytest.fail(f"serve not subscribed after {timeout} s:\n{log.read_text()[-3000:]}")


def start_serve(cmd: list[str], log_path: Path) -> subprocess.Popen[bytes]:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    fh = open(log_path, "ab")  # noqa: SIM115 - closed by the OS when the child ends
    return subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, cwd=REPO)


def replay_with_kills(cmd: list[str], log: Path, stream: Path, broker: str,
                      thresholds: list[int], rng: np.random.Generator,
                      done: Callable[[], bool], progress: Callable[[], int],
                      timeout: float) -> tuple[subprocess.Popen[bytes], int, str]:
    """Replay ``stream`` at full rate into a running ``serve cmd`` and SIGKILL the service
    each time ``progress()`` (products stored) passes the next of ``thresholds``,
    restarting it; at the second kill once more at a random moment of the restart itself.
    Runs until ``done()`` or ``timeout`` s; returns the service running now, the kill count
    and the replay's output (the replay must have succeeded)."""
    proc = start_serve(cmd, log)
    kills, deadline = 0, time.monotonic() + timeout

    def kill_and_restart() -> None:
        nonlocal proc, kills
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        kills += 1
        proc = start_serve(cmd, log)

    replay: subprocess.Popen[bytes] | None = None
    try:
        wait_serving(proc, log)
        replay = subprocess.Popen([*FORMTWIN, "replay", str(stream), "--broker", broker,
                                   "--rate", "0"], cwd=REPO, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT)
        while not done() and time.monotonic() < deadline:
            if thresholds and progress() >= thresholds[0]:
                thresholds.pop(0)
                kill_and_restart()
                if kills == 2:  # and once more at a random moment of the restart itself
                    time.sleep(float(rng.uniform(0.3, 2.0)))
                    kill_and_restart()
            time.sleep(0.01)
        out = replay.communicate(timeout=60)[0].decode()
    except BaseException:
        proc.kill()
        raise
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
    assert replay.returncode == 0, out
    return proc, kills, out


class Collector:
    """Subscribes (QoS 1) to topics and keeps every JSON message received, by topic.

    On a persistent session of its own id, subscribing again at every (re)connection: a
    collector that loses its connection (a busy machine: the broker's keepalive, a
    restarted socket) gets the messages published meanwhile from the broker's queue when
    paho reconnects, instead of silently receiving nothing more on a clean session whose
    subscription died with the connection. :attr:`disconnects` and :attr:`errors` (a
    message it could not read) say what happened when a test waits in vain."""

    def __init__(self, url: str, topics: list[str]) -> None:
        import json
        import threading

        import paho.mqtt.client as mqtt
        from paho.mqtt.enums import CallbackAPIVersion

        self._lock = threading.Lock()
        self.messages: dict[str, list[dict[str, object]]] = {t: [] for t in topics}
        self.disconnects: list[str] = []
        self.errors: list[str] = []
        port = int(url.rsplit(":", 1)[1])
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2,
                                  client_id=f"collector-{time.time_ns()}",
                                  clean_session=False)
        ready = threading.Event()

        def on_message(c: object, u: object, msg: mqtt.MQTTMessage) -> None:
            try:
                doc = json.loads(msg.payload)
            except ValueError as exc:  # kept, never raised into paho's thread
                self.errors.append(f"{msg.topic}: {exc}")
                return
            with self._lock:
                self.messages.setdefault(msg.topic, []).append(doc)

        def on_connect(c: mqtt.Client, u: object, flags: object, rc: object,
                       props: object = None) -> None:
            c.subscribe([(t, 1) for t in topics])

        self.client.on_message = on_message
        self.client.on_connect = on_connect
        self.client.on_subscribe = lambda *a: ready.set()
        self.client.on_disconnect = lambda c, u, f, rc, p=None: self.disconnects.append(
            str(rc))
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        if not ready.wait(10):
            raise TimeoutError("collector could not subscribe")

    def get(self, topic: str) -> list[dict[str, object]]:
        with self._lock:
            return list(self.messages.get(topic, []))

    def stop(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def wait_for(predicate: object, timeout: float, what: object, poll: float = 0.05) -> None:
    """Poll ``predicate()`` until true; fail the test after ``timeout`` seconds, saying
    ``what`` (a string, or a callable giving one at that moment)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return
        time.sleep(poll)
    pytest.fail(f"timed out after {timeout} s waiting for "
                f"{what() if callable(what) else what}")


def log_has(path: Path, text: str) -> bool:
    return path.exists() and text in path.read_text(encoding="utf-8", errors="replace")


def require_browser() -> tuple[str, Any]:
    """Headless Chromium and playwright's sync API, or skip the test (call it first)."""
    chromium = require_binary("chromium", ("/usr/bin/chromium",))
    return chromium, pytest.importorskip("playwright.sync_api")


@contextmanager
def live_page(url: str, height: int = 900) -> Iterator[tuple[Any, list[str]]]:
    """The live page at ``url`` in headless Chromium: ``(page, errors)``, with ``errors``
    the page's JavaScript errors so far; the browser closes on exit."""
    chromium, sync_api = require_browser()
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                     args=["--no-sandbox", "--disable-gpu",
                                           "--disable-dev-shm-usage"])
        try:
            page = browser.new_page(viewport={"width": 1300, "height": height})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url, timeout=30_000)
            yield page, errors
        finally:
            browser.close()


def stored_count(store: Path) -> int:
    """Products in a service's store (0 while it does not exist or is locked)."""
    if not store.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1.0) as db:
            return int(db.execute("SELECT COUNT(*) FROM products").fetchone()[0])
    except sqlite3.Error:
        return 0


def doc_commands(doc: Path, mark: str) -> list[str]:
    """The non-blank shell lines of the first ```sh block after ``mark`` in ``doc``."""
    text = doc.read_text(encoding="utf-8")
    block = text.split(mark, 1)[1].split("```sh\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def read_opcua_results(url: str, paths: list[str]) -> dict[str, Any]:
    """The values of the ``Formtwin/<path>`` nodes of formtwin's OPC UA results server at
    ``url`` (``serve --opcua-results``), as a client reads them."""
    from asyncua.sync import Client

    from formtwin.service.opcua_results import NAMESPACE

    with Client(url, timeout=10) as client:
        ns = client.get_namespace_index(NAMESPACE)
        root = client.nodes.objects.get_child([f"{ns}:Formtwin"])
        return {p: root.get_child([f"{ns}:{part}" for part in p.split("/")]).read_value()
                for p in paths}
