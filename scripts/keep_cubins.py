"""Zero, in place, the GPU code of a shared library's CUDA fat binaries for every architecture but the ones kept.

    python scripts/keep_cubins.py LIBRARY --keep 90        # sm_90: the H100 and H200 the GPU machine has

Why: the GPU smoke (scripts/gpu-smoke.sh) carries warp-lang to a machine that takes 64 MiB a call, and warp.so does
not fit as it is: its `.nv_fatbin` section (65 MB) holds Warp's precompiled kernels as SASS for seven architectures
(sm_75 to sm_120) and PTX for two. The CUDA driver runs the SASS of the GPU's own architecture where there is one,
so on an sm_90 machine the other six are never read; zeroed, they compress to nothing (about 5 MB saved after xz).

What changes: only the payload bytes of the ELF (SASS) entries of the architectures not kept. The fat binaries'
headers, every entry's header, the PTX entries, the kept SASS and everything outside `.nv_fatbin` stay byte for
byte, and so does the file's size. The library then runs on the kept architectures' GPUs only (elsewhere, on the
PTX, if the driver compiles it). Refuses a file whose `.nv_fatbin` does not parse as a sequence of fat binaries
whose entries fill them exactly.
"""

from __future__ import annotations

import argparse
import struct
import sys
from pathlib import Path

FATBIN_MAGIC = 0xBA55ED50
KIND_PTX, KIND_ELF = 1, 2


def section(data: bytes | bytearray, name: str) -> tuple[int, int]:
    """(file offset, size) of section `name` of a 64-bit little-endian ELF file."""
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        raise ValueError("not a 64-bit little-endian ELF file")
    (shoff,) = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    headers = [struct.unpack_from("<IIQQQQ", data, shoff + i * shentsize) for i in range(shnum)]
    names_at = headers[shstrndx][4]
    for sh_name, _type, _flags, _addr, offset, size in headers:
        end = data.index(b"\0", names_at + sh_name)
        if data[names_at + sh_name : end].decode() == name:
            return offset, size
    raise ValueError(f"no {name} section")


def entries(data: bytes | bytearray, start: int, size: int) -> list[tuple[int, int, int, int]]:
    """(kind, architecture, payload offset, payload size) of each entry of the fat binaries in that range."""
    found, at, end = [], start, start + size
    magic_bytes = struct.pack("<I", FATBIN_MAGIC)
    while at < end:
        next_at = data.find(magic_bytes, at, end)
        gap = (next_at if next_at >= 0 else end) - at
        if data.count(0, at, at + gap) != gap:  # padding between or after fat binaries is zeros
            raise ValueError(f"offset {at:#x}: no fat binary where one should start")
        if next_at < 0:
            break
        _magic, _version, header, fat = struct.unpack_from("<IHHQ", data, next_at)
        entry, stop = next_at + header, next_at + header + fat
        while entry + 32 <= stop:
            kind, _, entry_header, payload = struct.unpack_from("<HHIQ", data, entry)
            (arch,) = struct.unpack_from("<I", data, entry + 28)
            if entry_header < 32:
                break
            found.append((kind, arch, entry + entry_header, payload))
            entry += entry_header + payload
        if entry != stop or stop > end:
            raise ValueError(f"offset {next_at:#x}: the fat binary's entries do not fill it")
        at = stop
    return found


def keep_only(data: bytearray, keep: set[int]) -> tuple[int, int]:
    """Zero the SASS of the architectures not in `keep`; (bytes zeroed, SASS entries kept)."""
    if not keep:
        raise ValueError("keep at least one architecture")
    start, size = section(data, ".nv_fatbin")
    zeroed = kept = 0
    for kind, arch, at, payload in entries(data, start, size):
        if kind == KIND_ELF and arch not in keep:
            data[at : at + payload] = bytes(payload)
            zeroed += payload
        elif kind == KIND_ELF:
            kept += 1
    if not kept:
        raise ValueError(f"no SASS for sm_{', sm_'.join(map(str, sorted(keep)))} in the library: nothing would run")
    return zeroed, kept


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("library", type=Path)
    parser.add_argument("--keep", default="90", help="comma-separated SM architectures whose SASS stays (default 90)")
    args = parser.parse_args(argv)
    data = bytearray(args.library.read_bytes())
    try:
        zeroed, kept = keep_only(data, {int(a) for a in args.keep.split(",")})
    except ValueError as e:
        print(f"error: {args.library}: {e}", file=sys.stderr)
        return 2
    args.library.write_bytes(data)
    print(f"{args.library}: {zeroed / 2**20:.1f} MiB of SASS zeroed, {kept} entries of sm_{args.keep} kept")
    return 0


if __name__ == "__main__":
    sys.exit(main())
