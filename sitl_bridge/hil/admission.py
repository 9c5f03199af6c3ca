"""Who may become a vehicle's autopilot on the simulator link (TCP 4560+i).

Connecting is not enough: a peer is admitted only once it speaks valid MAVLink as an
autopilot does (a HEARTBEAT from an autopilot, or HIL_ACTUATOR_CONTROLS; PX4 and the stub send
a HEARTBEAT right after connecting). Until then it waits here, one of possibly several. A peer
that sends garbage, stays silent too long (a stale connection queued before a reset), or hangs
up is dropped and logged; it never blocks the real autopilot behind it.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import time
from dataclasses import dataclass, field

from sitl_bridge import mavlink

log = logging.getLogger(__name__)

SILENCE_LIMIT_S = 10.0
"""Wall seconds a connected peer may stay silent before it is dropped."""
GARBAGE_LIMIT_BYTES = 4096
"""Bytes a peer may send without one valid autopilot message before it is dropped."""
_HIL_ACTUATOR_CONTROLS = mavlink.dialect.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS
_NOT_AN_AUTOPILOT = mavlink.dialect.MAV_AUTOPILOT_INVALID


@dataclass
class Admitted:
    """A peer that spoke as an autopilot: its socket, address and every byte it sent so far."""

    sock: socket.socket
    peer: str
    data: bytes


@dataclass
class _Candidate:
    sock: socket.socket
    peer: str
    since: float
    data: bytearray = field(default_factory=bytearray)
    parser: mavlink.FrameParser = field(default_factory=mavlink.FrameParser)


def _speaks_as_autopilot(frame: mavlink.Frame) -> bool:
    if frame.msgid == _HIL_ACTUATOR_CONTROLS:
        return True
    if frame.msgid == mavlink.HEARTBEAT:
        return mavlink.unpack_payload(frame)[2] != _NOT_AN_AUTOPILOT
    return False


class Admission:
    """The connections of one link's server socket that have not been admitted yet."""

    def __init__(self, server: socket.socket, instance: int) -> None:
        self.server = server
        self.instance = instance
        self.candidates: list[_Candidate] = []
        self.dropped = 0

    def wait(self, timeout_s: float) -> Admitted | None:
        """Accept new connections and read the waiting ones until one speaks as an autopilot
        (returned, the others closed) or `timeout_s` passes (None)."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            self._take_new()
            admitted = self._read_candidates()
            if admitted is not None:
                return admitted
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            watched = [self.server, *(c.sock for c in self.candidates)]
            select.select(watched, [], [], min(remaining, 1.0))

    def close(self) -> None:
        """Close every waiting connection."""
        for candidate in self.candidates:
            self._drop(candidate, None)
        self.candidates = []

    def _take_new(self) -> None:
        while True:
            try:
                sock, address = self.server.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.candidates.append(_Candidate(sock, f"{address[0]}:{address[1]}", time.monotonic()))

    def _read_candidates(self) -> Admitted | None:
        now = time.monotonic()
        for candidate in list(self.candidates):
            why = self._read(candidate)
            if why == "admitted":
                self.candidates.remove(candidate)
                self.close()  # one autopilot per vehicle: the first to speak
                return Admitted(candidate.sock, candidate.peer, bytes(candidate.data))
            if why is None and now - candidate.since > SILENCE_LIMIT_S:
                why = f"silent for {SILENCE_LIMIT_S:g} s"
            if why is not None:
                self.candidates.remove(candidate)
                self._drop(candidate, why)
        return None

    def _read(self, candidate: _Candidate) -> str | None:
        """'admitted', a reason to drop the peer, or None (keep waiting)."""
        while True:
            try:
                data = candidate.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return None
            except OSError as exc:
                return f"receive failed ({exc})"
            if not data:
                return "hung up before speaking"
            candidate.data += data
            if any(_speaks_as_autopilot(frame) for frame in candidate.parser.feed(data)):
                return "admitted"
            if len(candidate.data) > GARBAGE_LIMIT_BYTES:
                return f"sent {len(candidate.data)} bytes without a HEARTBEAT or HIL_ACTUATOR_CONTROLS"

    def _drop(self, candidate: _Candidate, why: str | None) -> None:
        with contextlib.suppress(OSError):
            candidate.sock.close()
        if why is not None:
            self.dropped += 1
            log.warning("vehicle %d: dropped a connection from %s on the simulator link: %s",
                        self.instance, candidate.peer, why)
