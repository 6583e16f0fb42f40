"""A small socketcand server (the ASCII protocol over TCP, raw mode only) bridging one in-process
python-can bus to TCP clients on 127.0.0.1, so that the fake drives and the daemon can be
separate processes (python-can's ``socketcand`` interface is the client).

Protocol as python-can's client speaks it: the server greets ``< hi >``; the client sends
``< open CHANNEL >`` (→ ``< ok >``) and ``< rawmode >`` (→ ``< ok >``); then the client sends
``< send ID LEN B0 B1 … >`` (hex) and receives ``< frame ID SECS.USECS DATAHEX >``.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

import can

__all__ = ["SocketcandServer", "frame_line", "parse_send"]

log = logging.getLogger("robid.fake_controller")

#: the client reads its two ``< ok >`` answers with one recv each: frames to a new client wait
#: until it sends its first frame (it has read the answer then), or this long after the answer
_SETTLE_S = 0.2


def frame_line(msg: can.Message) -> bytes:
    """A received frame as socketcand sends it in raw mode."""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    return f"< frame {ident} {msg.timestamp:.6f} {bytes(msg.data).hex().upper()} >".encode()


def parse_send(body: str) -> can.Message:
    """``send ID LEN B…`` (the text between ``<`` and ``>``) as a frame; ValueError if bad."""
    parts = body.split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {body!r}")
    ident, length = int(parts[1], 16), int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if length != len(data) or length > 8 or ident > 0x1FFFFFFF:
        raise ValueError(f"bad frame: {body!r}")
    return can.Message(arbitration_id=ident, is_extended_id=len(parts[1]) > 3, data=data,
                       timestamp=time.time())


class _Client:
    def __init__(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.sock, self.addr = sock, addr
        self.raw_since: float | None = None  # frames flow this long after raw mode
        self.lock = threading.Lock()

    def send(self, data: bytes) -> bool:
        try:
            with self.lock:
                self.sock.sendall(data)
            return True
        except OSError:
            return False


class SocketcandServer:
    """Serves ``channel`` of ``bus`` (a python-can bus owned by the caller) on
    ``127.0.0.1:port`` (0 = a free port, see ``port`` after ``start``)."""

    def __init__(self, bus: can.BusABC, channel: str = "can0", port: int = 0) -> None:
        self.bus, self.channel = bus, channel
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", port))
        self.port: int = self._sock.getsockname()[1]
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._quit = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        self._sock.listen(4)
        self._sock.settimeout(0.2)
        for target, name in ((self._accept_loop, "socketcand-accept"),
                             (self._bus_loop, "socketcand-bus")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("socketcand serving %s on 127.0.0.1:%d", self.channel, self.port)

    def stop(self) -> None:
        self._quit.set()
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            _close(c.sock)
        for t in self._threads:
            t.join(5.0)
        self._threads.clear()
        _close(self._sock)

    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    # -- threads
    def _accept_loop(self) -> None:
        while not self._quit.is_set():
            try:
                sock, addr = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, addr)
            t = threading.Thread(target=self._client_loop, args=(client,),
                                 name=f"socketcand-client-{addr[1]}", daemon=True)
            with self._lock:
                self._threads = [x for x in self._threads if x.is_alive()] + [t]
            t.start()

    def _bus_loop(self) -> None:
        """Frames of the bus (the fake drives) to every client in raw mode."""
        while not self._quit.is_set():
            try:
                msg = self.bus.recv(0.1)
            except can.CanError:
                return
            if msg is not None:
                self._forward(frame_line(msg), None)

    def _forward(self, line: bytes, origin: _Client | None) -> None:
        now = time.monotonic()
        with self._lock:
            targets = [c for c in self._clients if c is not origin and c.raw_since is not None
                       and now >= c.raw_since]
        for c in targets:
            if not c.send(line):
                self._drop(c, "connection lost")

    def _client_loop(self, client: _Client) -> None:
        """One client: greeting, open, rawmode, then its ``send`` commands onto the bus."""
        sock = client.sock
        sock.settimeout(0.2)
        client.send(b"< hi >")
        buf = b""
        opened = False
        while not self._quit.is_set():
            try:
                chunk = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                chunk = b""
            if not chunk:
                self._drop(client, "client closed the connection")
                return
            buf += chunk
            while (end := buf.find(b">")) >= 0:
                start = buf.find(b"<")
                body = buf[start + 1:end].decode("ascii", "replace").strip() if 0 <= start < end \
                    else ""
                buf = buf[end + 1:]
                opened = self._command(client, body, opened)
            if len(buf) > 1024:  # no '>' in sight: a client that does not speak socketcand
                self._drop(client, "garbage from client")
                return

    def _command(self, client: _Client, body: str, opened: bool) -> bool:
        if body.startswith("send ") and client.raw_since is not None:
            client.raw_since = min(client.raw_since, time.monotonic())
            try:
                msg = parse_send(body)
            except ValueError as err:
                client.send(f"< error {err} >".encode())
                return opened
            try:
                self.bus.send(msg)
            except can.CanError as err:
                log.warning("socketcand: frame not sent (%s)", err)
            self._forward(frame_line(msg), client)  # other clients see it too, as on a bus
        elif body == f"open {self.channel}":
            client.send(b"< ok >")
            return True
        elif body == "rawmode" and opened:
            client.send(b"< ok >")
            with self._lock:
                client.raw_since = time.monotonic() + _SETTLE_S
                self._clients.append(client)
            log.info("socketcand: client %s:%d in raw mode on %s", *client.addr, self.channel)
        else:
            client.send(f"< error unknown or out-of-order command {body[:40]!r} >".encode())
        return opened

    def _drop(self, client: _Client, why: str) -> None:
        with self._lock:
            known = client in self._clients
            self._clients = [c for c in self._clients if c is not client]
        _close(client.sock)
        if known:
            log.info("socketcand: client %s:%d gone (%s)", *client.addr, why)


def _close(sock: socket.socket) -> None:
    try:
        sock.close()
    except OSError:
        pass
