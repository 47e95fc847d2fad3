"""A Dask scheduler given with ``--scheduler`` is a peer, not a trusted source of sizes.

Dask's TCP protocol starts with the scheduler's handshake: an 8-byte length,
then that many bytes of frames (an 8-byte frame count, 8 bytes per frame
length, the frames).  Dask allocates whatever length the peer claims before
it reads it, so a port that answered garbage made ``afmtool`` ask for
exbibytes (``MemoryError``), or fail in ``struct`` and numpy; a port that
accepted and never answered hung the run.

:func:`probe_scheduler` reads that first message itself, before Dask does,
within one deadline for the whole exchange: it connects, reads the length,
checks it against :data:`MAX_HANDSHAKE_BYTES`, reads the frames (a peer
that trickles them runs into the deadline), checks that their lengths add
up and that they decode to a Dask handshake.  Anything else is one
:class:`~afmtool.errors.InputError` naming the address and what the peer
did.  :func:`connect_client` then hands the address to Dask with the same
time-out, and turns whatever Dask raises on a peer that passed the probe
but misbehaves later into the same kind of error.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from urllib.parse import urlsplit

from afmtool.errors import ConfigError, InputError

__all__ = ["DEFAULT_TIMEOUT_S", "MAX_HANDSHAKE_BYTES", "check_timeout", "connect_client", "probe_scheduler"]

#: Seconds a scheduler has to accept, answer and finish its handshake (``--scheduler-timeout``).
DEFAULT_TIMEOUT_S = 10.0
#: A Dask handshake is a small dict (a few hundred bytes); more is not a scheduler talking.
MAX_HANDSHAKE_BYTES = 1 << 16
_MAX_FRAMES = 64


def check_timeout(timeout_s: float, option: str = "--scheduler-timeout") -> float:
    """``timeout_s`` if it is a finite number of seconds in (0, 1 day]."""
    try:
        value = float(timeout_s)
    except (TypeError, ValueError):
        raise ConfigError(f"{option} {timeout_s!r} must be a number of seconds") from None
    if not (math.isfinite(value) and 0 < value <= 86_400):
        raise ConfigError(f"{option} {timeout_s!r} must be a number of seconds in (0, 86400]")
    return value


def _host_port(address: str) -> tuple[str, int]:
    text = address.strip()
    parts = urlsplit(text if "://" in text else f"tcp://{text}")
    if parts.scheme not in ("tcp", ""):
        raise InputError(f"--scheduler {address}: only tcp:// addresses are supported, got {parts.scheme}://")
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host, port = None, None
    if not host or port is None:
        raise InputError(f"--scheduler {address}: give it as tcp://HOST:PORT")
    return host, port


class _Deadline:
    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.end = time.monotonic() + timeout_s

    def left(self) -> float:
        return max(self.end - time.monotonic(), 0.0)


def _read_exactly(sock: socket.socket, n: int, deadline: _Deadline, address: str, what: str) -> bytes:
    """``n`` bytes, or InputError when the peer closes or the deadline passes first."""
    got = bytearray()
    while len(got) < n:
        left = deadline.left()
        if left <= 0:
            raise InputError(
                f"--scheduler {address}: sent {len(got)} of the {n} bytes of its {what} in "
                f"{deadline.timeout_s:g} s (--scheduler-timeout); not a Dask scheduler that answers"
            )
        sock.settimeout(left)
        try:
            part = sock.recv(min(n - len(got), 1 << 16))
        except TimeoutError:
            continue
        except OSError as exc:
            raise InputError(f"--scheduler {address}: connection lost ({exc.strerror or exc})") from None
        if not part:
            raise InputError(f"--scheduler {address}: closed the connection after {len(got)} of {n} bytes of its {what}")
        got += part
    return bytes(got)


def _check_frames(body: bytes, address: str) -> None:
    """The frames of a handshake: a count, their lengths adding up to the body, a dict that decodes."""
    (count,) = struct.unpack_from("Q", body, 0)
    if not 1 <= count <= _MAX_FRAMES or 8 + 8 * count > len(body):
        raise InputError(f"--scheduler {address}: not a Dask scheduler (its handshake claims {count} frames)")
    lengths = struct.unpack_from(f"{count}Q", body, 8)
    if 8 + 8 * count + sum(lengths) != len(body):
        raise InputError(f"--scheduler {address}: not a Dask scheduler (its handshake's frame lengths do not add up)")
    import logging

    log = logging.getLogger("distributed.protocol.core")  # it logs a traceback for bytes it cannot decode
    disabled, log.disabled = log.disabled, True
    try:
        from distributed.protocol.core import loads
        from distributed.protocol.utils import unpack_frames

        message = loads(unpack_frames(body))
    except Exception:  # noqa: BLE001 - whatever the decoder meets in a peer's bytes, the peer is not a scheduler
        message = None
    finally:
        log.disabled = disabled
    if not (isinstance(message, dict) and "python" in message):
        raise InputError(f"--scheduler {address}: not a Dask scheduler (its first message is not a Dask handshake)")


def probe_scheduler(address: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Check, within ``timeout_s`` in all, that ``address`` is a Dask scheduler that answers.

    Raises
    ------
    InputError
        The address is malformed, refuses or drops the connection, stays
        silent or trickles past the deadline, claims a handshake larger than
        :data:`MAX_HANDSHAKE_BYTES`, or answers anything that is not a Dask
        handshake.  Nothing is allocated beyond that limit.
    """
    deadline = _Deadline(check_timeout(timeout_s))
    host, port = _host_port(address)
    try:
        sock = socket.create_connection((host, port), timeout=max(deadline.left(), 0.001))
    except TimeoutError:
        raise InputError(f"--scheduler {address}: no connection within {deadline.timeout_s:g} s (--scheduler-timeout)") from None
    except OSError as exc:
        raise InputError(f"--scheduler {address}: cannot connect to a Dask scheduler there ({exc.strerror or exc})") from None
    with sock:
        (length,) = struct.unpack("Q", _read_exactly(sock, 8, deadline, address, "handshake's length"))
        if not 16 <= length <= MAX_HANDSHAKE_BYTES:
            raise InputError(
                f"--scheduler {address}: not a Dask scheduler (its first message claims {length:,} bytes; "
                f"a handshake is 16 to {MAX_HANDSHAKE_BYTES:,})"
            )
        _check_frames(_read_exactly(sock, length, deadline, address, "handshake"), address)


def connect_client(address: str, timeout_s: float = DEFAULT_TIMEOUT_S):
    """A ``distributed.Client`` on ``address``, after :func:`probe_scheduler`; errors as one InputError."""
    probe_scheduler(address, timeout_s)
    try:
        from distributed import Client
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'afmtool[cluster]'") from None
    try:
        return Client(address, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError, MemoryError, ValueError, struct.error, EOFError) as exc:
        raise InputError(f"--scheduler {address}: {type(exc).__name__} from the peer ({exc})") from None
