"""scripts/keep_cubins.py: zeroing the SASS of the GPU architectures not kept changes those bytes and nothing else,
on a fat binary built here by hand and on warp-lang's own warp.so where it is installed."""

from __future__ import annotations

import importlib.util
import platform
import struct
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("keep_cubins", ROOT / "scripts" / "keep_cubins.py")
keep_cubins = importlib.util.module_from_spec(spec)
sys.modules["keep_cubins"] = keep_cubins
spec.loader.exec_module(keep_cubins)


def _entry(kind: int, arch: int, payload: bytes, header: int = 64) -> bytes:
    fields = struct.pack("<HHIQ", kind, 0x101, header, len(payload)) + bytes(12) + struct.pack("<I", arch)
    return fields + bytes(header - len(fields)) + payload


def _fatbin(*entries: bytes) -> bytes:
    body = b"".join(entries)
    return struct.pack("<IHHQ", keep_cubins.FATBIN_MAGIC, 1, 16, len(body)) + body


def _elf(sections: dict[str, bytes]) -> bytearray:
    """A 64-bit little-endian ELF file of these sections (and its section-name table), nothing else."""
    names = b"\0" + b"".join(n.encode() + b"\0" for n in [*sections, ".shstrtab"])
    blobs = [*sections.values(), names]
    data = bytearray(64)
    data[:6] = b"\x7fELF\x02\x01"
    offsets = []
    for blob in blobs:
        offsets.append(len(data))
        data += blob
    shoff = len(data)
    headers = [bytes(64)]
    name_at = 1
    for name, blob, offset in zip([*sections, ".shstrtab"], blobs, offsets, strict=True):
        headers.append(struct.pack("<IIQQQQ", name_at, 1, 0, 0, offset, len(blob)) + bytes(24))
        name_at += len(name) + 1
    data += b"".join(headers)
    struct.pack_into("<Q", data, 0x28, shoff)
    struct.pack_into("<HHH", data, 0x3A, 64, len(headers), len(headers) - 1)
    return data


def test_only_the_sass_of_the_architectures_not_kept_is_zeroed():
    ptx, sass75, sass90, sass100 = b"P" * 40, b"7" * 96, b"9" * 80, b"X" * 72
    first = _fatbin(_entry(1, 75, ptx, 80), _entry(2, 75, sass75), _entry(2, 90, sass90), _entry(2, 100, sass100, 120))
    second = _fatbin(_entry(2, 75, sass75), _entry(2, 90, sass90))
    text = b"code that mentions sm_75" * 4
    before = _elf({".text": text, ".nv_fatbin": first + bytes(8) + second, ".rodata": b"R" * 32})
    after = bytearray(before)
    zeroed, kept = keep_cubins.keep_only(after, {90})
    assert (zeroed, kept) == (2 * len(sass75) + len(sass100), 2)
    assert len(after) == len(before)
    start, size = keep_cubins.section(after, ".nv_fatbin")
    seen = [(kind, arch, bytes(after[at : at + n])) for kind, arch, at, n in keep_cubins.entries(after, start, size)]
    assert seen == [
        (1, 75, ptx), (2, 75, bytes(96)), (2, 90, sass90), (2, 100, bytes(72)), (2, 75, bytes(96)), (2, 90, sass90)
    ]  # fmt: skip
    changed = [i for i in range(len(before)) if before[i] != after[i]]
    assert len(changed) == zeroed  # no payload byte was zero before; nothing else changed
    assert after.startswith(before[:start]) and after.endswith(before[start + size :])


def test_a_section_that_does_not_parse_or_keeps_nothing_is_refused():
    good = _fatbin(_entry(2, 75, b"7" * 16))
    with pytest.raises(ValueError, match="no SASS for sm_90"):
        keep_cubins.keep_only(_elf({".nv_fatbin": good}), {90})
    long = bytearray(good + bytes(48))
    struct.pack_into("<Q", long, 8, len(good) - 16 + 48)  # a fat binary declared longer than its entries
    with pytest.raises(ValueError, match="do not fill it"):
        keep_cubins.keep_only(_elf({".nv_fatbin": bytes(long)}), {75})
    with pytest.raises(ValueError, match="no fat binary where one should start"):
        keep_cubins.keep_only(_elf({".nv_fatbin": good + b"junk" * 8}), {75})
    with pytest.raises(ValueError, match="no .nv_fatbin section"):
        keep_cubins.keep_only(_elf({".text": b"x"}), {90})


def test_warp_so_keeps_its_sm_90_sass_and_ptx_and_changes_nowhere_else():
    warp = pytest.importorskip("warp")  # the project's warp extra: CI installs it
    if sys.platform != "linux" or platform.machine() != "x86_64":
        pytest.skip("warp-lang's Linux x86-64 build is the one the GPU machine takes")
    library = Path(warp.__file__).parent / "bin" / "warp.so"
    assert library.exists(), library
    before = library.read_bytes()
    start, size = keep_cubins.section(before, ".nv_fatbin")
    listed = keep_cubins.entries(before, start, size)
    assert {arch for kind, arch, _, _ in listed if kind == keep_cubins.KIND_ELF} >= {75, 80, 86, 89, 90}
    after = bytearray(before)
    zeroed, kept = keep_cubins.keep_only(after, {90})
    assert kept > 0 and zeroed > size // 2
    for kind, arch, at, n in listed:
        if kind == keep_cubins.KIND_PTX or arch == 90:
            assert after[at : at + n] == before[at : at + n]
    assert after[:start] == before[:start] and after[start + size :] == before[start + size :]
