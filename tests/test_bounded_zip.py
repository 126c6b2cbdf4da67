"""A shared agent.zip cannot make a command read more than the ceiling (a 5 MB file inflating to 3 GiB had
been read whole, to a MemoryError)."""

from __future__ import annotations

import zipfile

import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.bounded_zip import read_members


def _zip(path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)


def test_a_member_that_inflates_thousands_of_times_is_refused_before_it_is_read(tmp_path) -> None:
    _zip(tmp_path / "a.zip", {"policy.pth": b"\0" * (64 * 1024 * 1024)})  # 64 MiB of zeros: about 64 kB zipped
    with zipfile.ZipFile(tmp_path / "a.zip") as z:
        with pytest.raises(UserInputError, match=r"'policy.pth' inflates [\d,]+x"):
            read_members(z, ["policy.pth"], "agent a.zip")


def test_a_member_over_the_ceiling_is_refused_and_one_under_it_is_read(tmp_path) -> None:
    payload = bytes(range(256)) * 4096  # 1 MiB, barely compressible
    _zip(tmp_path / "a.zip", {"data": b'{"a": 1}', "policy.pth": payload})
    with zipfile.ZipFile(tmp_path / "a.zip") as z:
        with pytest.raises(UserInputError, match=r"'policy.pth' claims 1,048,576 bytes; allowed: up to 1,000,000"):
            read_members(z, ["policy.pth"], "agent a.zip", max_bytes=1_000_000)
        assert read_members(z, ["data", "policy.pth"], "agent a.zip") == {"data": b'{"a": 1}', "policy.pth": payload}


def test_a_directory_that_understates_a_member_stops_at_the_stated_size(tmp_path) -> None:
    """The central directory says 10 bytes; the member inflates to 1 MiB: reading stops, it is not believed."""
    path = tmp_path / "a.zip"
    _zip(path, {"policy.pth": b"x" * (1024 * 1024)})
    raw = bytearray(path.read_bytes())
    central = raw.rfind(b"PK\x01\x02")  # the member's central directory entry: uncompressed size at +24
    raw[central + 24:central + 28] = (10).to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as z, pytest.raises((UserInputError, zipfile.BadZipFile)):
        read_members(z, ["policy.pth"], "agent a.zip")


def test_a_steps_file_claiming_more_rows_than_an_episode_has_is_refused_before_it_is_read(tmp_path) -> None:
    """A 1.3 MB steps Parquet of 2.1 million rows had made export use 5.9 GB: the footer's count is checked first."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from genesis_rl.campaigns.campaign_files import read_steps
    from genesis_rl.core import limits

    path = tmp_path / "scene_0000.parquet"
    pq.write_table(pa.table({"step": pa.array(range(limits.SIM_STEPS.value() + 2))}), path)
    with pytest.raises(UserInputError, match=r"claims 100,002 step rows; an episode has at most 100,001"):
        read_steps(path)
    pq.write_table(pa.table({"step": pa.array(range(71))}), path)
    assert len(read_steps(path)) == 71
