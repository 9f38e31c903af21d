"""Check that ``--scheduler ADDRESS`` is a Dask scheduler before Dask's client talks to it.

Dask's client trusts its peer: a service that is not Dask makes it wait for a handshake
without end (an HTTP server that never answers) or read a length header out of arbitrary
bytes and try to allocate exabytes. A Dask scheduler sends its handshake first on every
new TCP connection (``distributed.comm.core``: a frame of ``handshake_info()``, preceded by
its length as a native ``uint64``), so reading that frame, with a deadline and a size
limit, tells a Dask scheduler from anything else.
"""

from __future__ import annotations

import socket
import struct
import time

MAX_HANDSHAKE_BYTES = 1 << 20  # the handshake is ~100 bytes of msgpack
MARKER = b"pickle-protocol"  # a key of distributed's handshake_info()


class NotAScheduler(Exception):
    """The address does not answer as a Dask scheduler (the message says how)."""


def _host_port(address: str) -> tuple[str, int] | None:
    """``tcp://host:port`` or ``host:port`` -> (host, port); None for other protocols (tls, ucx, ...)."""
    if "://" in address:
        proto, address = address.split("://", 1)
        if proto != "tcp":
            return None
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]") or "127.0.0.1", int(port)


def _recv_exactly(sock: socket.socket, n: int, deadline: float) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout()
        sock.settimeout(left)
        part = sock.recv(n - len(buf))
        if not part:
            raise NotAScheduler("it closed the connection without a Dask handshake")
        buf += part
    return bytes(buf)


def probe(address: str, timeout: float) -> None:
    """Raise :class:`NotAScheduler` unless ``address`` sends a Dask handshake within ``timeout`` seconds
    (connect included). Addresses of other protocols than TCP are left to Dask."""
    hp = _host_port(address)
    if hp is None:
        return
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection(hp, timeout=timeout) as sock:
            (size,) = struct.unpack("Q", _recv_exactly(sock, 8, deadline))
            if not 0 < size <= MAX_HANDSHAKE_BYTES:
                raise NotAScheduler("it does not speak Dask's protocol (not a Dask scheduler)")
            if MARKER not in _recv_exactly(sock, size, deadline):
                raise NotAScheduler("it does not speak Dask's protocol (not a Dask scheduler)")
    except socket.timeout:
        raise NotAScheduler(f"no Dask handshake within {timeout:g} s") from None
    except OSError as exc:
        raise NotAScheduler(f"cannot connect to a Dask scheduler there within {timeout:g} s "
                            f"({type(exc).__name__}: {exc.strerror or exc})") from None  # fmt: skip
