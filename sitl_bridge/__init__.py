"""sitl-bridge: a fast lockstep drone simulator for reinforcement learning that speaks PX4's
simulator MAVLink protocol.

Data flow: world YAML -> physics -> sensors -> HIL link -> (PX4 | stub) -> MAVLink API ->
MAVSDK client -> env -> agent/trainer -> logs -> plots/rules.
"""

__version__ = "0.1.0"

__all__ = ["make_env", "make_parallel_env", "make_vec_env", "__version__"]


def __getattr__(name: str):
    # Lazy, so `import sitl_bridge` stays light (no pybullet/mavsdk) until an env is wanted.
    if name in ("make_env", "make_parallel_env", "make_vec_env"):
        from sitl_bridge import envs

        return getattr(envs, name)
    raise AttributeError(f"module 'sitl_bridge' has no attribute {name!r}")
