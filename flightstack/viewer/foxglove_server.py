"""The live view's WebSocket server: Foxglove's WebSocket protocol (the subset a viewer needs: serverInfo,
advertise, subscribe, unsubscribe, message data) on `websockets`, in its own thread and event loop, with
every client bounded, because it runs in the flight's process:

- at most MAX_CLIENTS connections at once (more are refused with HTTP 503);
- a client's message at most MAX_MESSAGE_BYTES (a longer one closes its connection, code 1009), read at
  most CONTROL_RATE_HZ per second (beyond that the server stops reading it: TCP pushes back);
- at most MAX_SUBSCRIPTIONS subscriptions per client, one per channel; a subscription to an unknown
  channel is refused;
- data for a client that does not keep up is dropped beyond SEND_QUEUE messages (counted in `dropped`).

So whatever the clients send, the server parses at most MAX_CLIENTS · CONTROL_RATE_HZ · MAX_MESSAGE_BYTES
bytes of their input per second, and sends each message of the flight at most MAX_CLIENTS times (docs/logs.md
gives the measured cost). What a client does wrong is
counted per kind in `wrongs` and logged at most once per REPORT_PERIOD_S per client address, one line.

Both subprotocol names are accepted: `foxglove.websocket.v1` (Lichtblick, Foxglove Studio) and
`foxglove.sdk.v1` (foxglove-sdk's clients); the reply names the one the client offered.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import http
import json
import logging
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import foxglove
    from websockets.asyncio.server import Server, ServerConnection
    from websockets.http11 import Request, Response

_log = logging.getLogger(__name__)

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
"""The protocol's two names (the same protocol); a client must offer one."""
MAX_CLIENTS = 4
"""Connections served at once; one more is refused (HTTP 503)."""
MAX_SUBSCRIPTIONS = 256
"""Subscriptions one client may hold."""
MAX_MESSAGE_BYTES = 32 * 1024
"""Longest message a client may send (B); a subscribe to about 800 channels fits."""
CONTROL_RATE_HZ = 10.0
"""A client's messages read per second (a burst of CONTROL_BURST first)."""
CONTROL_BURST = 10
"""Messages a client may send at once before CONTROL_RATE_HZ applies."""
SEND_QUEUE = 256
"""Messages waiting for a client beyond which its data is dropped (counted)."""
REPORT_PERIOD_S = 1.0
"""Least time between two log lines about one client address (s)."""
HANDSHAKE_TIMEOUT_S = 5.0
"""How long a connection may take to open (s)."""
START_TIMEOUT_S = 10.0
"""How long starting or stopping the server's thread may take (s)."""
MESSAGE_DATA = 0x01
"""Binary opcode of a message: subscription id u32, log time u64 (ns), payload (little endian)."""


@dataclass
class _Channel:
    id: int
    topic: str
    schema: foxglove.Schema

    def advertisement(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": "protobuf",
            "schemaName": self.schema.name,
            "schema": base64.b64encode(self.schema.data).decode("ascii"),
            "schemaEncoding": "protobuf",
        }


@dataclass(eq=False)
class _Client:
    ws: ServerConnection
    host: str
    subs: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    chans: dict[int, int] = field(default_factory=dict)  # channel id -> subscription id
    out: asyncio.Queue[str | bytes] = field(default_factory=lambda: asyncio.Queue(SEND_QUEUE))
    tokens: float = float(CONTROL_BURST)
    refill: float = field(default_factory=time.monotonic)

    async def throttle(self) -> None:
        """Wait until the client may send one more message (token bucket, CONTROL_RATE_HZ)."""
        now = time.monotonic()
        self.tokens = min(float(CONTROL_BURST), self.tokens + (now - self.refill) * CONTROL_RATE_HZ)
        self.refill = now
        if self.tokens < 1.0:
            await asyncio.sleep((1.0 - self.tokens) / CONTROL_RATE_HZ)
            self.tokens, self.refill = 1.0, time.monotonic()
        self.tokens -= 1.0


class Topic:
    """One advertised channel; `log` sends a message to the clients subscribed to it (any thread)."""

    def __init__(self, server: FoxgloveServer, channel: _Channel) -> None:
        self._server, self._channel = server, channel

    def log(self, msg: Any, /, *, log_time: int | None = None) -> None:
        """Send `msg` (bytes, or a foxglove message, encoded here) logged at `log_time` (ns)."""
        if self._channel.id not in self._server.wanted:
            return
        data = msg if isinstance(msg, bytes) else msg.encode()
        self._server.send(self._channel.id, log_time or 0, data)

    def topic(self) -> str:
        return self._channel.topic

    def subscribed(self) -> bool:
        """Whether some client subscribed to it now (what it logs reaches someone)."""
        return self._channel.id in self._server.wanted


class _Reports:
    """What clients did wrong, counted per kind (`total`) and logged at most once per REPORT_PERIOD_S per
    client address."""

    def __init__(self) -> None:
        self.total: Counter[str] = Counter()
        self._pending: dict[str, Counter[str]] = {}
        self._said: dict[str, float] = {}

    def note(self, host: str, kind: str, n: int = 1) -> None:
        self.total[kind] += n
        self._pending.setdefault(host, Counter())[kind] += n
        self.flush(host)

    def flush(self, host: str | None = None, *, force: bool = False) -> None:
        """Log what is pending for `host` (every host when None) if its period has passed (or `force`)."""
        now = time.monotonic()
        for h in [host] if host is not None else list(self._pending):
            counts = self._pending.get(h)
            if not counts or (not force and now - self._said.get(h, -1e9) < REPORT_PERIOD_S):
                continue
            self._said[h] = now
            del self._pending[h]
            what = "; ".join(f"{kind}: {n}" for kind, n in sorted(counts.items()))
            _log.warning("live view client %s: %s (counted; at most one line a second per client)", h, what)


class FoxgloveServer:
    """The server (module docstring) on host:port (port 0: any free one), started at construction;
    OSError when it cannot listen. `topic` advertises a channel; `stop` ends it."""

    def __init__(self, host: str, port: int, name: str) -> None:
        self.host, self.name = host, name
        self.session = str(time.time_ns())
        self.wanted: set[int] = set()  # channel ids some client subscribed to (read from any thread)
        self.dropped = 0
        self.refused = 0
        self._reports = _Reports()
        self._clients: set[_Client] = set()
        self._channels: dict[int, _Channel] = {}
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._server: Server | None = None
        self._reporter: asyncio.Task[None] | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(port,), name="flightstack-foxglove-ws", daemon=True
        )
        self._thread.start()
        if not self._started.wait(START_TIMEOUT_S):
            raise OSError(f"the server on {host}:{port} did not start within {START_TIMEOUT_S:g} s")
        if self._error is not None:
            raise OSError(str(self._error)) from self._error
        assert self._server is not None
        self.port: int = int(self._server.sockets[0].getsockname()[1])

    @property
    def wrongs(self) -> Counter[str]:
        """What clients did wrong so far, per kind."""
        return self._reports.total

    # ---- the flight's side (any thread) --------------------------------------------------------------
    def topic(self, topic: str, schema: foxglove.Schema) -> Topic:
        """Advertise a channel (to the clients connected now and to later ones); its Topic."""
        with self._lock:
            ch = _Channel(len(self._channels) + 1, topic, schema)
            self._channels[ch.id] = ch
        self._loop.call_soon_threadsafe(
            self._broadcast, json.dumps({"op": "advertise", "channels": [ch.advertisement()]})
        )
        return Topic(self, ch)

    def send(self, channel_id: int, log_time: int, data: bytes) -> None:
        """Queue one message of a channel for its subscribers."""
        self._loop.call_soon_threadsafe(self._fan_out, channel_id, log_time, data)

    def stop(self) -> None:
        """Close every connection and the listening socket; log what was still pending."""
        if self._loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop)
            with contextlib.suppress(Exception):
                fut.result(START_TIMEOUT_S)
        self._thread.join(START_TIMEOUT_S)
        self._reports.flush(force=True)

    # ---- the server's thread ---------------------------------------------------------------------------
    def _run(self, port: int) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._listen(port))
        except BaseException as exc:  # the port is taken, the address is not this machine's, ...
            self._error = exc
            self._started.set()
            return
        self._started.set()
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    async def _listen(self, port: int) -> None:
        from websockets.asyncio.server import serve

        self._server = await serve(
            self._serve,
            self.host,
            port,
            subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
            process_request=self._admit,
            process_response=self._answered,
            compression=None,
            max_size=MAX_MESSAGE_BYTES,
            max_queue=4,
            open_timeout=HANDSHAKE_TIMEOUT_S,
            logger=_log.getChild("ws"),
        )
        self._reporter = self._loop.create_task(self._report_periodically())

    async def _report_periodically(self) -> None:
        while True:
            await asyncio.sleep(REPORT_PERIOD_S)
            self._reports.flush()

    async def _shutdown(self) -> None:
        if self._reporter is not None:
            self._reporter.cancel()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), START_TIMEOUT_S)
        self._loop.stop()

    def _admit(self, conn: ServerConnection, request: Request) -> Response | None:
        if len(self._clients) < MAX_CLIENTS:
            return None
        self.refused += 1
        self._reports.note(_host(conn), "connections refused (server full)")
        return conn.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, f"at most {MAX_CLIENTS} viewers at once\n")

    def _answered(self, conn: ServerConnection, request: Request, response: Response) -> None:
        if response.status_code not in (
            http.HTTPStatus.SWITCHING_PROTOCOLS,
            http.HTTPStatus.SERVICE_UNAVAILABLE,
        ):
            self._reports.note(_host(conn), f"handshakes refused (HTTP {response.status_code})")

    async def _serve(self, ws: ServerConnection) -> None:
        from websockets.exceptions import ConnectionClosed

        if len(self._clients) >= MAX_CLIENTS:  # two handshakes that passed _admit at once
            self._reports.note(_host(ws), "connections refused (server full)")
            await ws.close(1013, "server full")
            return
        client = _Client(ws, _host(ws))
        self._clients.add(client)
        writer = asyncio.get_running_loop().create_task(self._write(client))
        try:
            info = {"op": "serverInfo", "name": self.name, "capabilities": [], "sessionId": self.session}
            with self._lock:
                channels = [ch.advertisement() for ch in self._channels.values()]
            self._queue(client, json.dumps(info))
            if channels:
                self._queue(client, json.dumps({"op": "advertise", "channels": channels}))
            async for msg in ws:
                await client.throttle()
                self._handle(client, msg)
        except ConnectionClosed:
            pass
        finally:
            sent = ws.protocol.close_sent
            if sent is not None and sent.code == 1009:
                self._reports.note(client.host, f"messages longer than {MAX_MESSAGE_BYTES} B")
            self._clients.discard(client)
            writer.cancel()
            self._refresh_wanted()

    async def _write(self, client: _Client) -> None:
        with contextlib.suppress(Exception):
            while True:
                await client.ws.send(await client.out.get())

    def _queue(self, client: _Client, frame: str | bytes) -> None:
        try:
            client.out.put_nowait(frame)
        except asyncio.QueueFull:
            self.dropped += 1

    def _broadcast(self, text: str) -> None:
        for client in self._clients:
            self._queue(client, text)

    def _fan_out(self, channel_id: int, log_time: int, data: bytes) -> None:
        for client in self._clients:
            sub = client.chans.get(channel_id)
            if sub is not None:
                self._queue(client, struct.pack("<BIQ", MESSAGE_DATA, sub, log_time) + data)

    def _handle(self, client: _Client, msg: str | bytes) -> None:
        """One message of a client: subscribe and unsubscribe; anything else is counted as wrong."""
        try:
            if isinstance(msg, bytes):
                raise ValueError("binary message")
            body = json.loads(msg)
            op = body.get("op") if isinstance(body, dict) else None
            if op == "subscribe":
                self._subscribe(client, body["subscriptions"])
            elif op == "unsubscribe":
                for sub in body["subscriptionIds"]:
                    client.chans.pop(client.subs.pop(sub, -1), None)
                self._refresh_wanted()
            else:
                raise ValueError(f"op {op!r}")
        except (ValueError, KeyError, TypeError):
            self._reports.note(client.host, "messages not understood")

    def _subscribe(self, client: _Client, subs: list[dict[str, Any]]) -> None:
        bad = unknown = over = 0
        with self._lock:
            known = set(self._channels)
        for s in subs:
            sub, ch = (s.get("id"), s.get("channelId")) if isinstance(s, dict) else (None, None)
            if (
                not isinstance(sub, int)
                or not isinstance(ch, int)
                or sub in client.subs
                or ch in client.chans
            ):
                bad += 1  # malformed, or a subscription id or channel the client already has
            elif ch not in known:
                unknown += 1
            elif len(client.subs) >= MAX_SUBSCRIPTIONS:
                over += 1
            else:
                client.subs[sub], client.chans[ch] = ch, sub
        for kind, n in (
            ("subscriptions malformed or repeated", bad),
            ("subscriptions to unknown channels", unknown),
            (f"subscriptions beyond {MAX_SUBSCRIPTIONS}", over),
        ):
            if n:
                self._reports.note(client.host, kind, n)
        self._refresh_wanted()

    def _refresh_wanted(self) -> None:
        self.wanted = {ch for client in self._clients for ch in client.chans}


def _host(conn: ServerConnection) -> str:
    addr = conn.remote_address
    return str(addr[0]) if addr else "?"


__all__ = [
    "CONTROL_RATE_HZ",
    "MAX_CLIENTS",
    "MAX_MESSAGE_BYTES",
    "MAX_SUBSCRIPTIONS",
    "SUBPROTOCOLS",
    "FoxgloveServer",
    "Topic",
]
