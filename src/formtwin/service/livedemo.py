"""``make live-demo``: a private broker, the service and a replaying press, together.

Run as ``python -m formtwin.service.livedemo [--rate R] [--n N] [--duration S]``. It

1. starts mosquitto on 127.0.0.1 (a free port, temporary config; Debian package
   ``mosquitto``),
2. writes a synthetic stream of ``N`` products from the analytic stand-in (2 N sensor
   noise, which the service's likelihood is told with ``--sensor-noise 2``),
3. starts ``formtwin serve`` (store in ``out/live-demo/``) and prints the page's address,
4. replays the stream at ``R`` strokes per second,
5. on Ctrl-C, at the end of the stream or after ``--duration`` seconds stops everything and
   exports the store to ``out/live-demo/estimates.parquet``.

This module is a program (like the CLI), so it prints.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

_CLI = [sys.executable, "-c", "import sys; from formtwin.cli import main; sys.exit(main())"]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _mosquitto() -> str:
    for p in (shutil.which("mosquitto"), "/usr/sbin/mosquitto"):
        if p and os.path.exists(p):
            return p
    raise OSError("mosquitto is not installed: `make system-deps` (apt-get install mosquitto)")


def _wait_line(log: Path, text: str, proc: subprocess.Popen[bytes], timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists():
            for line in log.read_text(errors="replace").splitlines():
                if text in line:
                    return line
        if proc.poll() is not None:
            raise OSError(f"process exited ({proc.returncode}); see {log}")
        time.sleep(0.1)
    raise OSError(f"timed out waiting for {text!r} in {log}")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the live demo (broker, service, replay, page); returns the exit code."""
    ap = argparse.ArgumentParser(prog="formtwin-live-demo", description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="out/live-demo", help="folder (default: %(default)s)")
    ap.add_argument("--n", type=int, default=3000, help="products in the stream")
    ap.add_argument("--rate", type=float, default=5.0, help="strokes per second")
    ap.add_argument("--particles", type=int, default=500, help="N of the tracker")
    ap.add_argument("--http-port", type=int, default=8765, help="page port")
    ap.add_argument("--duration", type=float, default=0.0,
                    help="stop after this many seconds (0: at the end of the stream)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "serve.sqlite"
    for old in out.glob("serve.sqlite*"):  # a fresh run each time
        old.unlink()
    tmp = Path(tempfile.mkdtemp(prefix="formtwin-live-"))
    port = _free_port()
    conf = tmp / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                    "max_queued_messages 100000\n", encoding="utf-8")
    procs: list[subprocess.Popen[bytes]] = []
    stop = {"now": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    try:
        procs.append(subprocess.Popen([_mosquitto(), "-c", str(conf)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        url = f"mqtt://127.0.0.1:{port}"
        print(f"broker: {url} (private mosquitto)")
        from formtwin.service.streams import make_stream

        stream = make_stream(out / "stream.npz", args.n, seed=0)
        print(f"stream: {args.n} synthetic products -> {stream}")
        serve_log = out / "serve.log"
        with open(serve_log, "wb") as fh:
            procs.append(subprocess.Popen(
                [*_CLI, "serve", "--analytic", "--sensor-noise", "2", "--broker", url,
                 "--store", str(store),
                 "--particles", str(args.particles), "--http-port", str(args.http_port)],
                stdout=fh, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1")))
        page = _wait_line(serve_log, "live page:", procs[-1], 120).split("live page:")[1].strip()
        _wait_line(serve_log, "connected and subscribed", procs[-1], 60)
        print(f"\n  live page: {page}\n")
        replay = subprocess.Popen([*_CLI, "replay", str(stream), "--broker", url, "--rate",
                                   str(args.rate)])
        procs.append(replay)
        t0 = time.monotonic()
        print(f"replaying at {args.rate:g} strokes/s; Ctrl-C to stop")
        while replay.poll() is None and not stop["now"]:
            if args.duration and time.monotonic() - t0 > args.duration:
                break
            time.sleep(0.2)
        time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
        shutil.rmtree(tmp, ignore_errors=True)
    if store.exists():
        from formtwin.service.export import export_store

        path, n = export_store(store, out / "estimates.parquet")
        print(f"exported {n} estimates -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
