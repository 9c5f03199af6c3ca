"""`sitl-bridge stub` as a user starts it: it says where it waits, and exits when the simulator
goes away (PX4 does not reconnect either) unless told to wait for the next session."""

from __future__ import annotations

import subprocess
import sys
import time

from sitl_bridge.hil import HilLink
from sitl_bridge.ports import vehicle_ports


def start_stub(instance: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sitl_bridge", "stub", "-i", str(instance), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_stub_banner_then_exit_when_the_simulator_closes_the_link(free_instance: int) -> None:
    with HilLink(free_instance) as link:
        stub = start_stub(free_instance)
        try:
            banner = stub.stdout.readline()
            ports = vehicle_ports(free_instance)
            assert f"waiting for the simulator on tcp 127.0.0.1:{ports.hil}" in banner
            assert f"MAVLink API udp {ports.api_bind} -> {ports.api_client}" in banner
            assert link.accept(30.0), "the stub never connected"
            link.disconnect()  # the simulator goes away
            assert stub.wait(timeout=30) == 0
            assert "the simulator closed the link; exiting" in stub.stdout.read()
        finally:
            if stub.poll() is None:
                stub.kill()
                stub.wait()


def test_stub_keep_alive_waits_for_the_next_session(free_instance: int) -> None:
    with HilLink(free_instance) as link:
        stub = start_stub(free_instance, "--keep-alive")
        try:
            stub.stdout.readline()
            assert link.accept(30.0)
            link.disconnect()
            assert link.accept(30.0), "the stub did not come back for a second session"
            time.sleep(0.2)
            assert stub.poll() is None
        finally:
            stub.terminate()
            stub.wait(timeout=30)
