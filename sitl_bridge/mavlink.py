"""The one place that imports pymavlink.

pymavlink picks its dialect from the environment at import time; importing the MAVLink 2
`common` dialect module directly pins MAVLink 2 for the whole package. Everything else imports
`dialect` (messages, enums, CRCs) and `new_codec` from here.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import common as dialect  # noqa: E402

MAVLink = dialect.MAVLink
MAVLinkMessage = dialect.MAVLink_message


class _NullFile:
    """pymavlink's codec wants a file to write to; we send the bytes ourselves."""

    def write(self, data: bytes) -> None:  # pragma: no cover - never used for output
        pass


def new_codec(system_id: int, component_id: int) -> dialect.MAVLink:
    """A MAVLink 2 encoder/decoder with the given sender ids, robust to garbage bytes."""
    codec = dialect.MAVLink(_NullFile(), srcSystem=system_id, srcComponent=component_id)
    codec.robust_parsing = True
    return codec
