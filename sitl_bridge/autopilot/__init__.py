"""Autopilots that plug into the HIL link: the built-in PX4-compatible stub (`stub/`)."""
