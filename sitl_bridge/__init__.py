"""sitl-bridge: a fast lockstep drone simulator for reinforcement learning that speaks PX4's
simulator MAVLink protocol.

Data flow: world YAML -> physics -> sensors -> HIL link -> (PX4 | stub) -> MAVLink API ->
MAVSDK client -> env -> agent/trainer -> logs -> plots/rules.
"""

__version__ = "0.1.0"
