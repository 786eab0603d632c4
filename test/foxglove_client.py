"""A Foxglove WebSocket client for tests (``websockets``, subprotocol ``foxglove.sdk.v1``): what
the Foxglove app does on connecting, written from the protocol's specification, not from
foxglove-sdk (github.com/foxglove/ws-protocol, docs/spec.md): JSON ``advertise`` /
``unadvertise`` from the server, ``subscribe`` / ``unsubscribe`` from the client, binary
message data (opcode 1, uint32 subscription id, uint64 receive time [ns], payload)."""

from __future__ import annotations

import json
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
_HEADER = struct.Struct("<BIQ")


@dataclass
class Received:
    subscription: int
    log_time: int
    payload: bytes
    arrived: float


@dataclass
class FoxgloveClient:
    url: str
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)
    messages: list[Received] = field(default_factory=list)
    unadvertised: list[int] = field(default_factory=list)
    server_info: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        self._connection = connect(self.url, subprotocols=[SUBPROTOCOL], open_timeout=10.0)
        self._ws = self._connection.__enter__()
        self._lock = threading.Lock()
        self._next_id = 1
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    @property
    def subprotocol(self) -> str | None:
        return self._ws.subprotocol

    def _receive(self) -> None:
        try:
            while True:
                frame = self._ws.recv()
                now = time.monotonic()
                if isinstance(frame, bytes):
                    if frame[0] == MESSAGE_DATA:
                        _, sub, log_time = _HEADER.unpack_from(frame)
                        with self._lock:
                            self.messages.append(
                                Received(sub, log_time, frame[_HEADER.size :], now)
                            )
                    continue
                msg = json.loads(frame)
                with self._lock:
                    if msg["op"] == "serverInfo":
                        self.server_info = msg
                    elif msg["op"] == "advertise":
                        for ch in msg["channels"]:
                            self.channels[ch["id"]] = ch
                    elif msg["op"] == "unadvertise":
                        for cid in msg["channelIds"]:
                            self.channels.pop(cid, None)
                            self.unadvertised.append(cid)
        except ConnectionClosed:
            pass
        finally:
            self.closed.set()

    def channel(self, topic: str) -> dict[str, Any] | None:
        with self._lock:
            return next((c for c in self.channels.values() if c["topic"] == topic), None)

    def wait(self, predicate: Any, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.02)
        return bool(predicate())

    def subscribe(self, channel_id: int) -> int:
        sub = self._next_id
        self._next_id += 1
        self.subscriptions[sub] = channel_id
        self._ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": channel_id}]})
        )
        return sub

    def unsubscribe(self, sub: int) -> None:
        self._ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [sub]}))
        self.subscriptions.pop(sub, None)

    def received(self, sub: int) -> list[Received]:
        with self._lock:
            return [m for m in self.messages if m.subscription == sub]

    def close(self) -> None:
        self._connection.__exit__(None, None, None)
        self._thread.join(timeout=5.0)

    def drop(self) -> None:
        """Vanish without a closing handshake (a killed browser tab)."""
        self._ws.socket.close()
        self._thread.join(timeout=5.0)


def decoder(channel: dict[str, Any]) -> Any:
    """A function decoding this channel's payloads with the schema it advertised (rosbags,
    from the advertised ``ros2msg`` text alone)."""
    from rosbags.typesys import Stores, get_typestore
    from rosbags.typesys.msg import get_types_from_msg

    assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg", channel
    store = get_typestore(Stores.EMPTY)
    name = channel["schemaName"]
    store.register(get_types_from_msg(channel["schema"], name))
    return lambda payload: store.deserialize_cdr(payload, name)
