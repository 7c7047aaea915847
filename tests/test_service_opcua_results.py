"""The estimates as OPC UA variables (formtwin.service.opcua_results): what a client of the
server reads equals the outcome's message, an error sets LastError, bad URLs are named."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from service_fixtures import free_port, read_opcua_results

from formtwin.service.opcua_results import ResultsServer
from formtwin.service.processor import Outcome

NAMES = ("yield_stress", "thickness")
OUTPUTS = ("angle_stage1", "angle_stage2")


def _message(part: str, seq: int, thickness: float, **extra: Any) -> dict[str, Any]:
    return {"part_id": part, "seq": seq, "index": seq - 1, "cycle": 100 + seq,
            "mean": {"yield_stress": 301.5, "thickness": thickness},
            "std": {"yield_stress": 4.5, "thickness": None},
            "angles_mean": [44.1, 89.2], "angles_std": [0.3, 0.11], "ess": 212.5,
            "health": "ok", "flags": {"model_mismatch": False}, **extra}


def test_a_client_reads_the_last_product_and_the_last_error() -> None:
    url = f"opc.tcp://127.0.0.1:{free_port()}/formtwin"
    seen: list[str] = []
    server = ResultsServer(url, NAMES, OUTPUTS).start()
    server.listener = lambda out: seen.append(out.kind)
    try:
        first = read_opcua_results(url, ["PartId", "Estimate/thickness/Mean"])
        assert first == {"PartId": None, "Estimate/thickness/Mean": None}  # null until then
        server.on_outcome(Outcome("accepted", _message("P-1", 1, 0.3001)))
        last = _message("P-2", 2, 0.2998, final={"predicted_deg": 89.1,
                                                 "interval90_deg": [88.8, 89.4]},
                        control={"u": [0.012], "limited": True, "final_angle_deg": 90.01})
        alarm = {"schema": "formtwin.alarm/1", "chart": "ewma", "quantity": "thickness"}
        server.on_outcome(Outcome("accepted", last, "P-2", alarms=(alarm,)))
        server.on_outcome(Outcome("rejected", {"reason": "wrong_length",
                                               "detail": "force_N has 100 samples"}, "P-3"))
        server.on_outcome(Outcome("fused", {"status": "fused"}))  # a sensor's: nothing
        paths = ["PartId", "Seq", "Index", "CycleCount", "Health", "ModelMismatch", "Ess",
                 "Estimate/thickness/Mean", "Estimate/yield_stress/Std",
                 "Estimate/thickness/Std", "Outputs/angle_stage2/Mean",
                 "Outputs/angle_stage1/Std", "FinalAngle/Predicted", "FinalAngle/Low90",
                 "FinalAngle/High90", "Control/Setpoint", "Control/Limited",
                 "Control/PredictedDeg", "LastAlarm", "LastError"]
        import time

        deadline = time.monotonic() + 10
        while server.written < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        got = read_opcua_results(url, paths)
    finally:
        server.stop()
    assert seen == ["accepted", "accepted", "rejected", "fused"]
    assert server.written == 3
    expect = {"PartId": "P-2", "Seq": 2, "Index": 1, "CycleCount": 102, "Health": "ok",
              "ModelMismatch": False, "Ess": 212.5, "Estimate/thickness/Mean": 0.2998,
              "Estimate/yield_stress/Std": 4.5, "Outputs/angle_stage2/Mean": 89.2,
              "Outputs/angle_stage1/Std": 0.3, "FinalAngle/Predicted": 89.1,
              "FinalAngle/Low90": 88.8, "FinalAngle/High90": 89.4, "Control/Setpoint": [0.012],
              "Control/Limited": True, "Control/PredictedDeg": 90.01,
              "LastError": "wrong_length: force_N has 100 samples (part P-3)"}
    assert {k: got[k] for k in expect} == expect
    assert math.isnan(got["Estimate/thickness/Std"])  # null in the message
    assert '"chart": "ewma"' in got["LastAlarm"]


def test_bad_url_and_taken_port_are_named() -> None:
    with pytest.raises(ValueError, match="expected opc.tcp://HOST:PORT"):
        ResultsServer("http://127.0.0.1:4840", NAMES, OUTPUTS)
    url = f"opc.tcp://127.0.0.1:{free_port()}"
    server = ResultsServer(url, NAMES, OUTPUTS).start()
    try:
        with pytest.raises(OSError):
            ResultsServer(url, NAMES, OUTPUTS).start()
    finally:
        server.stop()


def test_a_secured_server_reads_only_to_its_users(tmp_path: Path) -> None:
    """With a certificate and users: a client that signs, encrypts and logs in reads the
    product; one with a wrong password or without security is refused."""
    import asyncio

    from asyncua import Client

    from formtwin.service.opcua_press import self_signed
    from formtwin.service.opcua_results import NAMESPACE, read_users

    certs = {}
    for who, uri in (("server", "urn:freeopcua:python:server"),
                     ("client", "urn:formtwin:client")):
        certs[who] = (str(tmp_path / f"{who}_cert.der"), str(tmp_path / f"{who}_key.pem"))
        self_signed(certs[who][1], certs[who][0], uri, server=who == "server")
    users = tmp_path / "users.txt"
    users.write_text("# who may read\nplc:s3cret\n", encoding="utf-8")
    assert read_users(users) == {"plc": "s3cret"}
    url = f"opc.tcp://127.0.0.1:{free_port()}/formtwin"
    server = ResultsServer(url, NAMES, OUTPUTS, certs["server"], read_users(users)).start()

    async def read_part(password: str | None) -> Any:
        client = Client(url, timeout=10)
        if password is not None:
            client.application_uri = "urn:formtwin:client"
            await client.set_security_string(
                f"Basic256Sha256,SignAndEncrypt,{certs['client'][0]},{certs['client'][1]}")
            client.set_user("plc")
            client.set_password(password)
        async with client:
            ns = await client.get_namespace_index(NAMESPACE)
            node = await client.nodes.objects.get_child([f"{ns}:Formtwin", f"{ns}:PartId"])
            return await node.read_value()

    try:
        server.on_outcome(Outcome("accepted", _message("P-9", 9, 0.3)))
        import time

        deadline = time.monotonic() + 10
        while server.written < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert asyncio.run(read_part("s3cret")) == "P-9"
        for password, why in (("wrong", "BadUserAccessDenied"), (None, "No matching endpoints")):
            with pytest.raises(Exception, match=why):
                asyncio.run(read_part(password))
    finally:
        server.stop()
    bad = tmp_path / "bad.txt"
    bad.write_text("plc s3cret\n", encoding="utf-8")
    with pytest.raises(ValueError, match="line 1: expected user:password"):
        read_users(bad)
    with pytest.raises(ValueError, match="no such file"):
        ResultsServer(url, NAMES, OUTPUTS, ("nope.der", "nope.pem"))
