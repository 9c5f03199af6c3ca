"""Standing fuzz suite of the MAVLink links during a hover (property-based, bounded in time).

Into the stub's MAVLink API link (real UDP, the `vehicle` fixture of test_stub_api.py) and into
both directions of the HIL link (real TCP between `HilLink` and the stub's `HilClient`, in
lockstep) go garbled frames, valid frames of any message with extreme field values (NaN, +-inf,
+-1e30, integer limits) and commands with random ids. Whatever arrives, the run stays alive and
the hovering vehicle stays within 0.5 m of where it held. Excluded are only the inputs that
legitimately move the vehicle: flight commands (arm/disarm, takeoff, land, RTL, mode changes,
reposition) and, on the simulator-to-autopilot side, the sensor messages themselves (a forged
but valid sensor reading is a sensor fault, not a link fault).
"""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from test_stub_api import command_long, d, of_type, vehicle  # noqa: F401 (fixture)
from test_stub_hostile_commands import _airborne

from sitl_bridge import mavlink
from sitl_bridge.autopilot.stub import StubVehicle
from sitl_bridge.autopilot.stub.modes import HOLD, CommandResult
from sitl_bridge.hil.link import HilLink
from sitl_bridge.hil.lockstep import Lockstep
from sitl_bridge.physics import Simulation
from sitl_bridge.sensors import SensorSuite
from sitl_bridge.world.loader import load_world

WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")
HOLD_RADIUS_M = 0.5
FLIGHT_COMMANDS = frozenset((
    d.MAV_CMD_COMPONENT_ARM_DISARM, d.MAV_CMD_NAV_TAKEOFF, d.MAV_CMD_NAV_LAND, d.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    d.MAV_CMD_DO_SET_MODE, d.MAV_CMD_DO_REPOSITION,
))
SENSOR_MESSAGES = frozenset((d.MAVLINK_MSG_ID_HIL_SENSOR, d.MAVLINK_MSG_ID_HIL_GPS,
                             d.MAVLINK_MSG_ID_HIL_STATE_QUATERNION))
EXAMPLES = 100
# One hover serves every example (a flight per example would take minutes); no shrinking, so a
# failure is reported (with its example) in bounded time too.
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                phases=(Phase.explicit, Phase.reuse, Phase.generate),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

_EXTREME_FLOATS = st.sampled_from([math.nan, math.inf, -math.inf, 1e30, -1e30, 3.4e38, -3.4e38, 0.0, -0.0, 1e-45])
_INT_RANGES = {"b": (-2**7, 2**7 - 1), "B": (0, 2**8 - 1), "h": (-2**15, 2**15 - 1), "H": (0, 2**16 - 1),
               "i": (-2**31, 2**31 - 1), "I": (0, 2**32 - 1), "q": (-2**63, 2**63 - 1), "Q": (0, 2**64 - 1)}


def _codes(fmt: str) -> list[tuple[int, str]]:
    """(repeat, type code) of a struct format; an 's' field is one value of that many bytes."""
    out, digits = [], ""
    for char in fmt.lstrip("<>=!@"):
        if char.isdigit():
            digits += char
            continue
        count = int(digits or 1)
        out.append((1, f"{count}s") if char == "s" else (count, char))
        digits = ""
    return out


@st.composite
def extreme_frame(draw, allowed_ids: list[int]) -> bytes:
    """A valid frame (right CRC) of one of `allowed_ids` with extreme field values."""
    msgid = draw(st.sampled_from(allowed_ids))
    cls = d.mavlink_map[msgid]
    values = []
    for count, code in _codes(cls.unpacker.format):
        if code.endswith("s"):
            values.append(draw(st.binary(min_size=int(code[:-1]), max_size=int(code[:-1]))))
            continue
        for _ in range(count):
            if code in "fd":
                values.append(draw(st.one_of(_EXTREME_FLOATS, st.floats(width=32 if code == "f" else 64))))
            else:
                lo, hi = _INT_RANGES[code]
                values.append(draw(st.one_of(st.sampled_from([lo, hi, 0, 1]), st.integers(lo, hi))))
    payload = bytearray(cls.unpacker.pack(*values))
    if msgid in (d.MAVLINK_MSG_ID_COMMAND_LONG, d.MAVLINK_MSG_ID_COMMAND_INT):
        # the command id (uint16) follows seven 4-byte parameters in both
        struct.pack_into("<H", payload, 28, draw(st.integers(0, 65535).filter(lambda c: c not in FLIGHT_COMMANDS)))
    system_id = draw(st.sampled_from([245, 255, 1, 0]))
    return mavlink.FrameEncoder(system_id, draw(st.sampled_from([190, 0, 1]))).frame(msgid, cls.crc_extra, bytes(payload))


@st.composite
def garbled(draw, frames: st.SearchStrategy[bytes]) -> bytes:
    """Random bytes, or a valid frame cut short, bit-flipped or glued to junk."""
    kind = draw(st.sampled_from(["junk", "truncated", "flipped", "glued"]))
    if kind == "junk":
        return draw(st.binary(min_size=1, max_size=280))
    frame = bytearray(draw(frames))
    if kind == "truncated":
        return bytes(frame[:draw(st.integers(1, max(1, len(frame) - 1)))])
    if kind == "flipped":
        at = draw(st.integers(0, len(frame) - 1))
        frame[at] ^= 1 << draw(st.integers(0, 7))
        return bytes(frame)
    return draw(st.binary(max_size=40)) + bytes(frame) + draw(st.binary(max_size=40))


API_HANDLED = [d.MAVLINK_MSG_ID_HEARTBEAT, d.MAVLINK_MSG_ID_COMMAND_LONG, d.MAVLINK_MSG_ID_COMMAND_INT,
               d.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, d.MAVLINK_MSG_ID_PARAM_REQUEST_READ, d.MAVLINK_MSG_ID_PARAM_SET,
               d.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED, d.MAVLINK_MSG_ID_TIMESYNC]
"""What the stub's API link acts on (the vehicle hovers in HOLD, which ignores offboard setpoints)."""
API_COMMANDS = [d.MAV_CMD_REQUEST_MESSAGE, d.MAV_CMD_SET_MESSAGE_INTERVAL, d.MAV_CMD_GET_HOME_POSITION,
                d.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES]
HIL_HANDLED = [d.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS, d.MAVLINK_MSG_ID_HEARTBEAT, d.MAVLINK_MSG_ID_COMMAND_LONG]
"""What the simulator's side of the HIL link acts on."""
_ALL_IDS = sorted(d.mavlink_map)


@st.composite
def known_command(draw, commands: list[int]) -> bytes:
    """COMMAND_LONG of one of `commands` for this vehicle with extreme parameters (the first
    one now and then a message id the link acts on)."""
    params = [draw(st.one_of(_EXTREME_FLOATS, st.floats(width=32))) for _ in range(7)]
    if draw(st.booleans()):
        params[0] = float(draw(st.sampled_from([d.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, *API_HANDLED, 30, 32, 242])))
    message = d.MAVLink_command_long_message(draw(st.sampled_from([0, 1])), 1, draw(st.sampled_from(commands)), 0,
                                             *params)
    return mavlink.FrameEncoder(245, 190).pack(type(message), *[getattr(message, f) for f in message.ordered_fieldnames])


def _inputs(handled: list[int], commands: list[int], any_ids: list[int]) -> st.SearchStrategy[list[bytes]]:
    frames = st.one_of(extreme_frame(handled), extreme_frame(any_ids))
    return st.lists(st.one_of(frames, known_command(commands), garbled(frames)), min_size=1, max_size=12)


# --- the API link ---------------------------------------------------------------------------------
@pytest.fixture
def api_hover(vehicle):  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    advance(2.0)
    hold = np.array(harness.position_ned_m, dtype=float)
    return harness, api, peer, advance, hold


@FUZZ
@given(batch=_inputs(API_HANDLED, API_COMMANDS, _ALL_IDS))
def test_api_link_fuzz_keeps_the_hover(api_hover, batch: list[bytes]) -> None:
    harness, api, peer, advance, hold = api_hover
    for data in batch:
        peer.send_raw(data)
    advance(0.1)
    peer.backlog.clear()
    drift = float(np.linalg.norm(np.array(harness.position_ned_m) - hold))
    assert drift < HOLD_RADIUS_M, f"{drift:.2f} m off the hold"
    assert harness.autopilot.armed and (harness.autopilot.commander.main_mode,
                                        harness.autopilot.commander.sub_mode) == HOLD


def _random_burst(count: int, seed: int) -> list[bytes]:
    """`count` datagrams: valid frames of random ids with random payload bytes (any float bit
    pattern, NaNs included), and the same cut, flipped or as plain junk."""
    rng = random.Random(seed)
    ids = [i for i in sorted(d.mavlink_map) if i not in (d.MAVLINK_MSG_ID_COMMAND_LONG, d.MAVLINK_MSG_ID_COMMAND_INT)]
    encoder = mavlink.FrameEncoder(245, 190)
    out = []
    for _ in range(count):
        cls = d.mavlink_map[rng.choice(ids)]
        frame = bytearray(encoder.frame(cls.id, cls.crc_extra, rng.randbytes(cls.unpacker.size)))
        kind = rng.randrange(4)
        if kind == 1:
            frame = frame[:rng.randrange(1, len(frame))]
        elif kind == 2:
            frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        elif kind == 3:
            frame = bytearray(rng.randbytes(rng.randrange(1, 280)))
        out.append(bytes(frame))
    return out


def test_api_link_still_answers_after_a_fuzz_burst(api_hover) -> None:
    harness, api, peer, advance, hold = api_hover
    for k, data in enumerate(_random_burst(3000, seed=7)):
        peer.send_raw(data)
        if k % 100 == 99:
            advance(0.02)   # read as it comes (a full socket buffer would drop datagrams)
    advance(0.5)
    peer.send(command_long(d.MAV_CMD_REQUEST_MESSAGE, float(d.MAVLINK_MSG_ID_AUTOPILOT_VERSION)))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    assert api.stats.garbage_datagrams > 500 and api.stats.frames > 500
    assert float(np.linalg.norm(np.array(harness.position_ned_m) - hold)) < HOLD_RADIUS_M


# --- the HIL link ---------------------------------------------------------------------------------
class HilHover:
    """The stub flying through the real HIL link in lockstep, hovering in HOLD."""

    def __init__(self, instance: int) -> None:
        self.sim = Simulation(WORLD, seed=0)
        self.link = HilLink(instance, step_us=self.sim.step_us)
        self.vehicle = StubVehicle(instance, ground_truth_estimate=True, api=False)
        assert self.vehicle.connect(2.0) and self.link.accept(2.0)
        suite = SensorSuite(WORLD.home, seed=1, step_us=self.sim.step_us)
        self.lockstep = Lockstep(self.sim, [suite], [self.link], speed_factor=0, pumps=[self.vehicle.pump],
                                 actuator_timeout_s=5.0)
        self.lockstep.run_for(0.5)
        ap = self.vehicle.autopilot
        assert ap.arm() is CommandResult.ACCEPTED and ap.takeoff() is CommandResult.ACCEPTED
        self.lockstep.run_for(8.0)
        assert (ap.commander.main_mode, ap.commander.sub_mode) == HOLD
        self.hold = np.array(self.sim.state(0).position_ned_m, dtype=float)

    def to_simulator(self, data: bytes) -> None:
        """Bytes on the wire from the autopilot to the simulator (the stub's own socket)."""
        self.vehicle.hil._sock.sendall(data)  # noqa: SLF001 (the fault is on this very connection)

    def to_autopilot(self, data: bytes) -> None:
        """Bytes on the wire from the simulator to the autopilot (the link's accepted socket)."""
        self.link._client.sendall(data)  # noqa: SLF001

    def drift_m(self) -> float:
        return float(np.linalg.norm(np.array(self.sim.state(0).position_ned_m) - self.hold))

    def close(self) -> None:
        self.vehicle.close()
        self.link.close()
        self.sim.close()


@pytest.fixture
def hil_hover(free_instance: int):
    hover = HilHover(free_instance)
    try:
        yield hover
    finally:
        hover.close()


_TO_AUTOPILOT_IDS = [i for i in _ALL_IDS if i not in SENSOR_MESSAGES]


@FUZZ
@given(to_simulator=_inputs(HIL_HANDLED, [d.MAV_CMD_SET_MESSAGE_INTERVAL, *API_COMMANDS], _ALL_IDS),
       to_autopilot=_inputs([d.MAVLINK_MSG_ID_HEARTBEAT, d.MAVLINK_MSG_ID_COMMAND_LONG], API_COMMANDS,
                            _TO_AUTOPILOT_IDS))
def test_hil_link_fuzz_keeps_the_hover(hil_hover, to_simulator: list[bytes], to_autopilot: list[bytes]) -> None:
    for data in to_simulator:
        hil_hover.to_simulator(data)
    for data in to_autopilot:
        hil_hover.to_autopilot(data)
    hil_hover.lockstep.run_for(0.1)
    assert hil_hover.link.connected and hil_hover.vehicle.hil.connected
    drift = hil_hover.drift_m()
    assert drift < HOLD_RADIUS_M, f"{drift:.2f} m off the hold"
    assert hil_hover.vehicle.autopilot.armed
