"""An independent Foxglove WebSocket client (protocol ``foxglove.websocket.v1``) for tests.

foxglove-sdk servers speak the same protocol under the subprotocol name ``foxglove.sdk.v1``
(identical so far); the client offers both and accepts either.

Written from the protocol specification, not from foxglove-sdk: text frames are JSON
(``serverInfo``, ``advertise``, ...); the client sends ``subscribe``; binary frames with opcode 1
are ``messageData``: ``u8 op | u32 subscription id | u64 log time ns | payload`` (little-endian).
Parameters are JSON ops (``getParameters``, ``setParameters``, ``subscribeParameterUpdates``; the
server answers ``parameterValues``); a service call is the client's binary opcode 2,
``u8 op | u32 service id | u32 call id | u32 encoding length | encoding | payload``, answered by
the server's opcode 3 of the same layout or a JSON ``serviceCallFailure``.
Protobuf channels carry a base64 ``FileDescriptorSet`` as their schema; :func:`decoder_for`
builds the message class from it with ``google.protobuf``.
"""

from __future__ import annotations

import base64
import json
import struct
import time
from dataclasses import dataclass, field
from typing import Any

from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
_MESSAGE_DATA = 0x01
_SERVICE_REQUEST, _SERVICE_RESPONSE = 0x02, 0x03
_HEAD = struct.Struct("<BIQ")
_CALL = struct.Struct("<BIII")


@dataclass
class Received:
    topic: str
    log_time: int
    payload: bytes


@dataclass
class FoxgloveClient:
    """A connected client: :meth:`wait_channels`, :meth:`subscribe`, :meth:`recv`."""

    ws: ClientConnection
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    """topic -> the advertised channel (id, encoding, schemaName, schema, schemaEncoding)."""
    server_info: dict[str, Any] | None = None
    services: dict[str, dict[str, Any]] = field(default_factory=dict)
    """name -> the advertised service (id, name, type, request, response)."""
    parameter_updates: list[dict[str, Any]] = field(default_factory=list)
    """``parameterValues`` messages without an id (subscribed updates), in arrival order."""
    _subs: dict[int, str] = field(default_factory=dict)
    _answers: dict[str, dict[str, Any]] = field(default_factory=dict)
    _calls: dict[int, Any] = field(default_factory=dict)

    @classmethod
    def open(cls, url: str, attempts: int = 300, **kwargs: Any) -> FoxgloveClient:
        """Connect, retrying while the server is not up yet (``attempts`` × 0.1 s)."""
        last: Exception | None = None
        for _ in range(attempts):
            try:
                ws = connect(url, subprotocols=list(SUBPROTOCOLS), compression=None, **kwargs)
                ws.__enter__()  # websockets 14+: a connection is a context manager
            except OSError as exc:
                last = exc
                time.sleep(0.1)
                continue
            if ws.subprotocol not in SUBPROTOCOLS:
                raise AssertionError(f"server chose subprotocol {ws.subprotocol!r}")
            return cls(ws)
        raise AssertionError(f"cannot connect to {url}: {last}")

    def _handle_text(self, text: str) -> None:
        msg = json.loads(text)
        op = msg.get("op")
        if op == "serverInfo":
            self.server_info = msg
        elif op == "advertise":
            for ch in msg["channels"]:
                self.channels[ch["topic"]] = ch
        elif op == "advertiseServices":
            for svc in msg["services"]:
                self.services[svc["name"]] = svc
        elif op == "parameterValues":
            if msg.get("id") is None:
                self.parameter_updates.append(msg)
            else:
                self._answers[msg["id"]] = msg
        elif op == "serviceCallFailure":
            self._calls[msg["callId"]] = AssertionError(msg["message"])
        elif op == "unadvertise":
            gone = set(msg["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}

    def wait_channels(self, topics: set[str], max_frames: int = 1000) -> None:
        for _ in range(max_frames):
            if topics <= set(self.channels):
                return
            frame = self.ws.recv(timeout=30)
            if isinstance(frame, str):
                self._handle_text(frame)
        raise AssertionError(f"not advertised: {topics - set(self.channels)}")

    def _pump(self, done: Any, timeout: float = 60.0) -> None:
        """Read frames until ``done()`` (messages on subscriptions are dropped meanwhile)."""
        deadline = time.monotonic() + timeout
        while not done():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError("no answer from the Foxglove server")
            frame = self.ws.recv(timeout=remaining)
            if isinstance(frame, str):
                self._handle_text(frame)
            elif frame and frame[0] == _SERVICE_RESPONSE:
                _op, _sid, call_id, n = _CALL.unpack_from(frame)
                self._calls[call_id] = bytes(frame[_CALL.size + n :])

    def _ask(self, msg: dict[str, Any], timeout: float) -> dict[str, Any]:
        rid = f"r{len(self._answers) + 1}-{time.monotonic_ns()}"
        self.ws.send(json.dumps({**msg, "id": rid}))
        self._pump(lambda: rid in self._answers, timeout)
        return {p["name"]: p.get("value") for p in self._answers.pop(rid)["parameters"]}

    def get_parameters(self, names: list[str], timeout: float = 60.0) -> dict[str, Any]:
        """``getParameters``: name -> value of the answer (all parameters for ``[]``)."""
        return self._ask({"op": "getParameters", "parameterNames": names}, timeout)

    def set_parameters(self, values: dict[str, Any], timeout: float = 60.0) -> dict[str, Any]:
        """``setParameters`` with an id: name -> value of the server's answer. A None value is
        sent as the protocol's unset (``value`` left out): foxglove-sdk drops a request with
        ``"value": null`` unanswered, so the call would wait out its timeout."""
        params = [{"name": k} if v is None else {"name": k, "value": v} for k, v in values.items()]
        return self._ask({"op": "setParameters", "parameters": params}, timeout)

    def subscribe_parameters(self, names: list[str]) -> None:
        self.ws.send(json.dumps({"op": "subscribeParameterUpdates", "parameterNames": names}))

    def wait_services(self, names: set[str], timeout: float = 30.0) -> None:
        self._pump(lambda: names <= set(self.services), timeout)

    def call_service(self, name: str, request: Any, timeout: float = 60.0) -> Any:
        """Call a JSON service; its decoded JSON response (AssertionError on a failure)."""
        svc = self.services[name]
        call_id = len(self._calls) + 1
        while call_id in self._calls:
            call_id += 1
        enc, payload = b"json", json.dumps(request).encode()
        head = _CALL.pack(_SERVICE_REQUEST, svc["id"], call_id, len(enc))
        self.ws.send(head + enc + payload)
        self._calls[call_id] = None
        self._pump(lambda: self._calls[call_id] is not None, timeout)
        out = self._calls[call_id]
        if isinstance(out, Exception):
            raise out
        return json.loads(out)

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for topic in topics:
            sub_id = len(self._subs) + 1
            self._subs[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def recv(self, timeout: float | None = None) -> Received | None:
        """The next message of a subscription (None on a text frame)."""
        frame = self.ws.recv(timeout=timeout)
        if isinstance(frame, str):
            self._handle_text(frame)
            return None
        if not frame or frame[0] != _MESSAGE_DATA:
            return None
        _op, sub_id, log_time = _HEAD.unpack_from(frame)
        return Received(self._subs[sub_id], log_time, bytes(frame[_HEAD.size :]))

    def close(self) -> None:
        self.ws.close()


def decoder_for(channel: dict[str, Any]) -> Any:
    """The protobuf message class of an advertised protobuf channel."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert channel["encoding"] == "protobuf"
    assert channel["schemaEncoding"] == "protobuf"
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
