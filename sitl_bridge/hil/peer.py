"""`ConstantAutopilot`: the smallest autopilot side of the simulator protocol.

It connects to a `HilLink` like PX4 does (TCP client, HEARTBEAT and SET_MESSAGE_INTERVAL 115
first) and answers every HIL_SENSOR id 0 with one HIL_ACTUATOR_CONTROLS carrying the same
`time_usec` and fixed motor values. No estimator, no control: it exists to measure the link
and lockstep overhead (`sitl-bridge bench --link`) and to exercise them in tests. Run it in
the lockstep thread through `pump()` (a Lockstep pump), or in its own thread with `serve()`.
"""

from __future__ import annotations

import contextlib
import select
import socket
import struct
import threading
import time

from sitl_bridge import mavlink
from sitl_bridge.ports import HIL_BASE_PORT

_SENSOR_TIME = struct.Struct("<Q")
_ACTUATOR_CLASS = mavlink.dialect.MAVLink_hil_actuator_controls_message
_HEARTBEAT_CLASS = mavlink.dialect.MAVLink_heartbeat_message
_COMMAND_LONG_CLASS = mavlink.dialect.MAVLink_command_long_message

MODE_CUSTOM = mavlink.dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MODE_ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
FLAG_LOCKSTEP = 1


class ConstantAutopilot:
    """Answers each HIL_SENSOR id 0 with constant motor commands (see module docstring)."""

    def __init__(
        self,
        instance: int,
        host: str = "127.0.0.1",
        base_port: int = HIL_BASE_PORT,
        *,
        controls: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
        armed: bool = False,
    ) -> None:
        self.address = (host, base_port + instance)
        self.system_id = (instance + 1) & 0xFF
        self.controls = controls
        self.armed = armed
        self.sensor_msgs = 0
        self.last_time_usec = 0
        self._encoder = mavlink.FrameEncoder(self.system_id, 1)
        self._parser = mavlink.FrameParser()
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def connect(self, timeout_s: float = 5.0) -> None:
        """Connect to the simulator and send PX4's greeting (heartbeat, interval request)."""
        sock = socket.create_connection(self.address, timeout=timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self._sock = sock
        greeting = self._encoder.pack(
            _COMMAND_LONG_CLASS, 115.0, 5000.0, 0.0, 0.0, 0.0, 0.0, 0.0,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0,
        ) + self._encoder.pack(
            _HEARTBEAT_CLASS, 0, 0, mavlink.dialect.MAV_AUTOPILOT_PX4,
            MODE_ARMED if self.armed else 0, 0, 3,
        )
        sock.sendall(greeting)

    def fileno(self) -> int:
        return self._sock.fileno() if self._sock is not None else -1

    def pump(self) -> int:
        """Read what the simulator sent and answer every HIL_SENSOR id 0; never blocks.
        Returns the number of answers sent."""
        sock = self._sock
        if sock is None:
            return 0
        try:
            data = sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return 0
        if not data:
            self.close()
            return 0
        answers = b""
        count = 0
        mode = MODE_CUSTOM | (MODE_ARMED if self.armed else 0)
        c0, c1, c2, c3 = self.controls if self.armed else (0.0, 0.0, 0.0, 0.0)
        for frame in self._parser.feed(data):
            if frame.msgid != mavlink.HIL_SENSOR or frame.payload[-1] != 0:  # id is last
                continue
            (time_usec,) = _SENSOR_TIME.unpack_from(frame.payload)
            self.sensor_msgs += 1
            self.last_time_usec = time_usec
            answers += self._encoder.pack(
                _ACTUATOR_CLASS, time_usec, FLAG_LOCKSTEP,
                c0, c1, c2, c3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                mode,
            )
            count += 1
        if answers:
            self._send_all(sock, answers)
        return count

    @staticmethod
    def _send_all(sock: socket.socket, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                sent = sock.send(view)
            except BlockingIOError:
                select.select([], [sock], [], 1.0)
                continue
            view = view[sent:]

    def serve(self) -> None:
        """Answer from a background thread until `close()` (a separate-process-like peer)."""
        def loop() -> None:
            while not self._stop.is_set() and self._sock is not None:
                with contextlib.suppress(ValueError, OSError):
                    select.select([self._sock], [], [], 0.05)
                    self.pump()

        self._thread = threading.Thread(target=loop, name="constant-autopilot", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop serving and close the connection."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        self._thread = None
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = None

    def __enter__(self) -> ConstantAutopilot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """`python -m sitl_bridge.hil.peer -i N`: a trivial external autopilot for instance N."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-i", "--instance", type=int, default=0)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--base-port", type=int, default=HIL_BASE_PORT)
    parser.add_argument("--connect-timeout", type=float, default=30.0)
    args = parser.parse_args(argv)
    peer = ConstantAutopilot(args.instance, args.host, args.base_port)
    deadline = time.monotonic() + args.connect_timeout
    while True:
        try:
            peer.connect()
            break
        except OSError:
            if time.monotonic() > deadline:
                print(f"no simulator on {args.host}:{args.base_port + args.instance}")
                return 1
            time.sleep(0.1)
    try:
        while peer.fileno() >= 0:
            select.select([peer.fileno()], [], [], 1.0)
            peer.pump()
    except KeyboardInterrupt:
        pass
    finally:
        peer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
