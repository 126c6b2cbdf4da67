"""Reading a zip someone shared without believing the sizes it claims.

A zip's directory states each member's size, and a member can inflate far past it or past any sane size (a
5 MB agent whose ``policy.pth`` inflates to 3 GiB). Every member is checked before it is read (declared size,
compression ratio) and read in chunks that stop at the ceiling, so a lie costs at most the ceiling's memory.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterable

from genesis_rl.core.errors import UserInputError

#: the largest member read whole (an SB3 policy with its optimiser is a few MB; a large CNN some tens)
MAX_MEMBER_BYTES = 512 * 1024 * 1024
#: the largest inflated size over compressed size of a member over 1 MB (torch tensors compress about 1.1x,
#: JSON about 10x; a zip bomb thousands of times)
MAX_RATIO = 200.0
_RATIO_FROM_BYTES = 1024 * 1024
_CHUNK = 1024 * 1024


def read_members(archive: zipfile.ZipFile, names: Iterable[str], source: str, *,
                 max_bytes: int = MAX_MEMBER_BYTES, max_ratio: float = MAX_RATIO) -> dict[str, bytes]:
    """The members ``names`` of ``archive`` (a file named ``source`` in messages), each within the ceilings."""
    out: dict[str, bytes] = {}
    for name in names:
        info = archive.getinfo(name)
        if info.file_size > max_bytes:
            raise UserInputError(f"{source}: its member '{name}' claims {info.file_size:,} bytes; allowed: up to "
                                 f"{max_bytes:,}")
        if info.file_size > _RATIO_FROM_BYTES and info.file_size > max_ratio * max(info.compress_size, 1):
            ratio = info.file_size / max(info.compress_size, 1)
            raise UserInputError(f"{source}: its member '{name}' inflates {ratio:,.0f}x ({info.compress_size:,} -> "
                                 f"{info.file_size:,} bytes); allowed: up to {max_ratio:g}x")
        limit = min(info.file_size, max_bytes)
        chunks, read = [], 0
        with archive.open(info) as member:
            while chunk := member.read(min(_CHUNK, limit + 1 - read)):
                read += len(chunk)
                if read > limit:  # inflates past what the directory said (zipfile checks this too, not always)
                    raise UserInputError(f"{source}: its member '{name}' inflates past the {info.file_size:,} "
                                         "bytes its directory states")
                chunks.append(chunk)
        out[name] = b"".join(chunks)
    return out
