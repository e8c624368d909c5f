"""Wire formats of the deploy runtime: K-bit message datagrams (UDP) and control lines (TCP).

Message datagram, agent to agent, big-endian, 23 + ceil(K / 8) bytes:
    magic b"BCM1" | run id u32 | sender u16 | episode u32 | step u32 | seq u32 | K u8 | bits, packed MSB first
`step` is the step the message was sent at (it is read at `step + delay`), `seq` counts the sender's
messages over the run (one per step; the same for every recipient of one message), so a receiver can
tell stale, duplicate and missing messages apart. A datagram from another run (run id) is ignored.

Control, world to agent and back: one JSON object per line over a TCP connection on loopback
(`LineSocket`). Messages: hello, config, ready, step, move, stop, stats (see `world.py`/`agent.py`).
A line that is not a JSON object raises `Malformed`; the world ignores and counts such lines.
"""

from __future__ import annotations

import base64
import json
import select
import socket
import struct
import time
from typing import Any, NamedTuple

import numpy as np

MAGIC = b"BCM1"
HEADER = struct.Struct("!4sIHIIIB")


class Datagram(NamedTuple):
    run_id: int
    sender: int
    episode: int
    step: int
    seq: int
    bits: np.ndarray  # (K,) uint8


def pack_datagram(run_id: int, sender: int, episode: int, step: int, seq: int, bits: np.ndarray) -> bytes:
    bits = np.asarray(bits, dtype=np.uint8)
    return HEADER.pack(MAGIC, run_id, sender, episode, step, seq, bits.size) + np.packbits(bits).tobytes()


def unpack_datagram(data: bytes) -> Datagram | None:
    """The datagram, or None for anything that is not one of ours (wrong magic, truncated)."""
    if len(data) < HEADER.size:
        return None
    magic, run_id, sender, episode, step, seq, k = HEADER.unpack_from(data)
    payload = np.frombuffer(data, dtype=np.uint8, offset=HEADER.size)
    if magic != MAGIC or payload.size != (k + 7) // 8:
        return None
    return Datagram(run_id, sender, episode, step, seq, np.unpackbits(payload)[:k])


# ---------------------------------------------------------------------- arrays as JSON
def encode_array(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=np.uint8).tobytes()).decode("ascii")


def decode_array(text: str, shape: tuple[int, ...]) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype=np.uint8).reshape(shape)


# ---------------------------------------------------------------------- control connection
class PeerGone(ConnectionError):
    """The other end closed the connection (it ended or died)."""


class Malformed(ValueError):
    """A control line that is not a JSON object: the connection goes on, the line is dropped."""


class LineSocket:
    """JSON lines over a connected TCP socket, with deadlines (absolute `time.monotonic()` seconds)."""

    def __init__(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # one small line per step: no Nagle wait
        sock.setblocking(False)
        self.sock = sock
        self._buffer = b""

    def send(self, obj: dict[str, Any]) -> None:
        data = (json.dumps(obj, separators=(",", ":")) + "\n").encode()
        self.sock.setblocking(True)
        try:
            self.sock.sendall(data)
        except OSError as err:
            raise PeerGone(str(err)) from None
        finally:
            self.sock.setblocking(False)

    def recv(self, deadline: float) -> dict[str, Any]:
        """The next line as an object; `TimeoutError` at the deadline, `PeerGone` at end of stream,
        `Malformed` (the line consumed) when it is not a JSON object."""
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no reply before the deadline")
            ready, _, _ = select.select([self.sock], [], [], left)
            if not ready:
                continue
            try:
                chunk = self.sock.recv(65536)
            except BlockingIOError:
                continue
            except OSError as err:
                raise PeerGone(str(err)) from None
            if not chunk:
                raise PeerGone("connection closed")
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        try:
            obj = json.loads(line)
        except ValueError as err:  # not UTF-8 or not JSON
            raise Malformed(f"not JSON ({err})") from None
        if not isinstance(obj, dict):
            raise Malformed(f"not a JSON object: {line[:40]!r}")
        return obj

    def close(self) -> None:
        self.sock.close()
