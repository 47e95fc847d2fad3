"""Hostile "schedulers" on 127.0.0.1 for the ``--scheduler`` tests: local sockets only.

Each peer listens on a free port of 127.0.0.1 (never another interface),
serves every connection in a daemon thread the way its kind says, and stops
by itself after ``lifetime_s`` even if nobody stops it:

- ``refusing``: a port nothing listens on (the connection is refused);
- ``silent``: accepts and never sends a byte;
- ``garbage``: accepts and sends a length of 2**62 bytes, then random bytes;
- ``garbage-small``: sends 4 KiB of random bytes (a plausible length first, then noise);
- ``garbage-frames``: well-formed frames (a count and lengths that add up) of random bytes;
- ``trickle``: sends a plausible handshake length, then one byte every 0.2 s;
- ``closing``: accepts and closes at once.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time

__all__ = ["KINDS", "HostilePeer"]

KINDS = ("refusing", "silent", "garbage", "garbage-small", "garbage-frames", "trickle", "closing")


class HostilePeer:
    """A local socket that misbehaves as ``kind``; use as a context manager (``address`` is tcp://127.0.0.1:PORT)."""

    def __init__(self, kind: str, lifetime_s: float = 60.0) -> None:
        if kind not in KINDS:
            raise ValueError(f"kind={kind!r} must be one of {KINDS}")
        self.kind = kind
        self.lifetime_s = lifetime_s
        self._stop = threading.Event()
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.connections = 0
        self._thread: threading.Thread | None = None
        if kind == "refusing":
            self._server.close()  # the port is free again: connecting to it is refused
        else:
            self._server.listen(16)
            self._server.settimeout(0.1)
            self._thread = threading.Thread(target=self._accept, name=f"peer-{kind}", daemon=True)
            self._thread.start()

    def _accept(self) -> None:
        end = time.monotonic() + self.lifetime_s
        with self._server:
            while not self._stop.is_set() and time.monotonic() < end:
                try:
                    conn, _ = self._server.accept()
                except (TimeoutError, OSError):
                    continue
                self.connections += 1
                threading.Thread(target=self._serve, args=(conn, end), daemon=True).start()

    def _serve(self, conn: socket.socket, end: float) -> None:
        with conn:
            try:
                if self.kind == "garbage":
                    conn.sendall(struct.pack("Q", 1 << 62) + os.urandom(4096))
                elif self.kind == "garbage-small":
                    conn.sendall(struct.pack("Q", 4096) + os.urandom(4096))
                elif self.kind == "garbage-frames":
                    frames = [os.urandom(40), os.urandom(200)]
                    body = struct.pack("Q", len(frames)) + struct.pack(f"{len(frames)}Q", *map(len, frames)) + b"".join(frames)
                    conn.sendall(struct.pack("Q", len(body)) + body)
                elif self.kind == "trickle":
                    conn.sendall(struct.pack("Q", 400))
                    while not self._stop.is_set() and time.monotonic() < end:
                        conn.sendall(b"\x01")
                        time.sleep(0.2)
                elif self.kind == "closing":
                    return
                # silent, and the others after sending: hold the connection until stopped
                while not self._stop.is_set() and time.monotonic() < end:
                    time.sleep(0.05)
            except OSError:
                return

    def __enter__(self) -> HostilePeer:
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
