"""Text from files and flags made safe to print: a campaign's strings must not drive a user's terminal."""

from __future__ import annotations

import re

#: C0 controls, DEL and the C1 controls: ESC and CSI sequences retitle, clear or rewrite a terminal
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def terminal_safe(text: str, keep: str = "") -> str:
    """``text`` with every control character written as an escape (``\\x1b``), but those in ``keep`` (a table's
    newlines), so that a policy or file name read from a shared file prints as what it is."""
    return _CONTROL.sub(lambda m: m.group() if m.group() in keep else f"\\x{ord(m.group()):02x}", text)
