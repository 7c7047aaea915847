"""Where ``formtwin serve`` takes its strokes from: the MQTT topic (default) or a press's
OPC UA server (``--source opc.tcp://...``, docs/reference/opcua.md)."""

from __future__ import annotations

import argparse
from typing import Any


def add_source_options(p: argparse.ArgumentParser) -> None:
    """Where the strokes come from: the MQTT topic (default) or a press's OPC UA server."""
    p.add_argument("--source", metavar="URL",
                   help="opc.tcp://HOST:PORT: subscribe to the press's OPC UA server for the "
                   "strokes (estimates still go to --broker); default: the MQTT --topic")
    p.add_argument("--opcua-map", metavar="TOML",
                   help="OPC UA node mapping, section [opcua] (docs/reference/opcua.md; "
                   "default: the OPC 40503-1 based names)")
    p.add_argument("--opcua-results", metavar="URL",
                   help="opc.tcp://HOST:PORT[/PATH]: also serve each product's estimate, "
                   "final angle and suggested setting as OPC UA variables of formtwin's own "
                   "server there (docs/reference/opcua.md), for the line's PLC or SCADA")
    p.add_argument("--opcua-results-security", metavar="CERT,KEY",
                   help="the results server's certificate and private key files: then only "
                   "Basic256Sha256 SignAndEncrypt sessions (default: security mode None)")
    p.add_argument("--opcua-results-users", metavar="FILE",
                   help="file of user:password lines: then only these users may read the "
                   "results (default: anonymous)")


def opcua_source(args: argparse.Namespace) -> Any:
    """The OPC UA source of ``--source opc.tcp://...`` (its mapping read now, so that a bad
    file stops the start at once), or None for the MQTT topic."""
    if args.source is None:
        if args.opcua_map:
            raise ValueError("--opcua-map needs --source opc.tcp://HOST:PORT")
        return None
    from formtwin.service.opcua import OpcUaSource
    from formtwin.service.opcua_map import OpcUaMapping

    mapping = OpcUaMapping.from_toml(args.opcua_map) if args.opcua_map else OpcUaMapping()
    return OpcUaSource(args.source, mapping)


def make_service(args: argparse.Namespace, proc: Any, broker: Any, topics: Any,
                 source: Any, check: bool = False) -> Any:
    """The MQTT service, or with an OPC UA ``source`` the OPC UA one; ``check``
    (``serve --check``): on a clean MQTT session of its own id, gone when it disconnects."""
    from formtwin.service.mqtt import check_client_id

    client_id = check_client_id(args.client_id) if check else args.client_id
    if source is None:
        from formtwin.service.mqtt import MqttService

        return MqttService(proc, broker, topics, persistent=not check, client_id=client_id)
    from formtwin.service.opcua import OpcUaService

    return OpcUaService(proc, source, broker, topics, client_id=client_id)


def opcua_results(args: argparse.Namespace, proc: Any) -> Any:
    """The started OPC UA results server of ``--opcua-results``, listening to ``proc``'s
    outcomes after its other listener, or None without the option."""
    if not args.opcua_results:
        if args.opcua_results_security or args.opcua_results_users:
            raise ValueError("--opcua-results-security/-users need --opcua-results URL")
        return None
    from formtwin.cli.options import model_spec
    from formtwin.service.opcua_results import ResultsServer, read_users

    cert = None
    if args.opcua_results_security:
        parts = [f.strip() for f in args.opcua_results_security.split(",")]
        if len(parts) != 2:
            raise ValueError(f"--opcua-results-security {args.opcua_results_security!r}: "
                             "expected CERT,KEY")
        cert = (parts[0], parts[1])
    users = read_users(args.opcua_results_users) if args.opcua_results_users else None
    spec = getattr(proc.tracker, "spec", None) or model_spec(args)
    results = ResultsServer(args.opcua_results, tuple(proc.tracker_names()),
                            tuple(o.name for o in spec.outputs), cert, users).start()
    results.listener, proc.on_outcome = proc.on_outcome, results.on_outcome
    print(f"estimates also as OPC UA variables: {args.opcua_results}", flush=True)
    return results
