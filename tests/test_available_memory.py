"""rtsgt.allocator.available_memory: the system's available memory and a control group's room,
read from files laid out as Linux lays them out (cgroup v1 and v2, a container's view)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtsgt.allocator import NO_LIMIT_BYTES, available_memory

GB = 10**9


def _meminfo(tmp_path: Path, available_kb: int | None) -> Path:
    lines = ["MemTotal:       24683584 kB", "MemFree:        16970700 kB"]
    if available_kb is not None:
        lines.append(f"MemAvailable:   {available_kb} kB")
    path = tmp_path / "meminfo"
    path.write_text("\n".join(lines + ["Buffers:          12 kB"]) + "\n")
    return path


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_the_systems_available_memory_without_a_control_group_limit(tmp_path):
    cg = tmp_path / "cgroup"
    _write(cg, "0::/user.slice\n")
    _write(tmp_path / "sys" / "user.slice" / "memory.max", "max\n")
    out = available_memory(_meminfo(tmp_path, 19034524), cg, tmp_path / "sys")
    assert out == 19034524 * 1024


def test_a_cgroup_v2_limit_below_the_systems_memory_wins(tmp_path):
    cg = tmp_path / "cgroup"
    _write(cg, "0::/job\n")
    _write(tmp_path / "sys" / "job" / "memory.max", f"{4 * GB}\n")
    _write(tmp_path / "sys" / "job" / "memory.current", f"{1 * GB}\n")
    assert available_memory(_meminfo(tmp_path, 19034524), cg, tmp_path / "sys") == 3 * GB


@pytest.mark.parametrize("own_files", [True, False])
def test_a_cgroup_v1_limit_in_its_group_or_at_a_containers_root(tmp_path, own_files):
    """v1's memory controller line; where the group's path is not mounted (a container sees
    its group at the hierarchy's root) the root's files are the group's."""
    cg = tmp_path / "cgroup"
    _write(cg, "9:name=systemd:/\n4:memory:/process_api/abc\n1:cpu:/\n0::/\n")
    where = tmp_path / "sys" / "memory" / ("process_api/abc" if own_files else "")
    _write(where / "memory.limit_in_bytes", f"{8 * GB}\n")
    _write(where / "memory.usage_in_bytes", f"{6 * GB}\n")
    assert available_memory(_meminfo(tmp_path, 19034524), cg, tmp_path / "sys") == 2 * GB


def test_an_unlimited_group_and_unknown_files(tmp_path):
    cg = tmp_path / "cgroup"
    _write(cg, "4:memory:/\n")
    _write(tmp_path / "sys" / "memory" / "memory.limit_in_bytes", f"{NO_LIMIT_BYTES + 4096}\n")
    _write(tmp_path / "sys" / "memory" / "memory.usage_in_bytes", f"{6 * GB}\n")
    assert available_memory(_meminfo(tmp_path, 1000), cg, tmp_path / "sys") == 1000 * 1024
    # no MemAvailable line, no cgroup file: not known
    missing = tmp_path / "absent"
    assert available_memory(_meminfo(tmp_path, None), missing, missing) is None
    # the group's limit alone where the system's is not known
    _write(tmp_path / "sys" / "memory" / "memory.limit_in_bytes", f"{7 * GB}\n")
    assert available_memory(_meminfo(tmp_path, None), cg, tmp_path / "sys") == 1 * GB


@pytest.mark.skipif(not Path("/proc/meminfo").exists(), reason="Linux's /proc")
def test_this_machines_available_memory_is_a_part_of_its_total():
    total = next(int(line.split()[1]) * 1024 for line in
                 Path("/proc/meminfo").read_text().splitlines() if line.startswith("MemTotal:"))
    out = available_memory()
    assert out is not None and 0 < out <= total
