"""The systemd unit's sandbox, applied to the real daemon without systemd.

The unit sets MemoryDenyWriteExecute=yes, NoNewPrivileges=yes and
SystemCallFilter=~@privileged @resources. No systemd runs as PID 1 here, so this test applies
the same rules to a `netpose run` child itself, through the kernel's own interfaces: the MDWE
prctl (what systemd 254 and later use where the kernel has it; bookworm's systemd 252 uses a
stricter seccomp filter, which a review applied by hand to the daemon with Debian's OpenCV and
FFmpeg: it ran) and a seccomp filter built with libseccomp (what systemd uses for
SystemCallFilter). The filter answers any listed system
call with EPERM, as the unit does (SystemCallErrorNumber=EPERM): OpenBLAS, for one, asks for
mbind() on its buffers and carries on when refused. The daemon must run the demo to a tracked
net and stop cleanly under these rules. Skipped where the kernel or libseccomp lacks the
interface.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PR_SET_NO_NEW_PRIVS = 38
PR_SET_MDWE = 65
PR_MDWE_REFUSE_EXEC_GAIN = 1
SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_ACT_ERRNO_EPERM = 0x00050000 | 1  # SCMP_ACT_ERRNO(EPERM)
# systemd 252's @privileged and @resources sets, flattened (`systemd-analyze syscall-filter`).
DENIED = (
    "_sysctl", "acct", "bpf", "capset", "chroot", "fanotify_init", "fanotify_mark",
    "nfsservctl", "open_by_handle_at", "pivot_root", "quotactl", "quotactl_fd", "setdomainname",
    "setfsuid", "setfsuid32", "setgroups", "setgroups32", "sethostname", "setresuid",
    "setresuid32", "setreuid", "setreuid32", "setuid", "setuid32", "vhangup", "chown",
    "chown32", "fchown", "fchown32", "fchownat", "lchown", "lchown32", "adjtimex",
    "clock_adjtime", "clock_adjtime64", "clock_settime", "clock_settime64", "settimeofday",
    "delete_module", "finit_module", "init_module", "ioperm", "iopl", "pciconfig_iobase",
    "pciconfig_read", "pciconfig_write", "kexec_file_load", "kexec_load", "reboot", "swapoff",
    "swapon", "ioprio_set", "mbind", "migrate_pages", "move_pages", "nice", "sched_setaffinity",
    "sched_setattr", "sched_setparam", "sched_setscheduler", "set_mempolicy",
    "set_mempolicy_home_node", "setpriority", "setrlimit",
)


def _libs() -> tuple[ctypes.CDLL, ctypes.CDLL]:
    libc = ctypes.CDLL(None, use_errno=True)
    name = ctypes.util.find_library("seccomp") or "libseccomp.so.2"
    try:
        seccomp = ctypes.CDLL(name)
    except OSError:
        pytest.skip("libseccomp is not installed (Debian: libseccomp2)")
    if libc.prctl(PR_SET_MDWE, 0, 0, 0, 0) != 0 and ctypes.get_errno() == 22:  # EINVAL
        pytest.skip("this kernel has no PR_SET_MDWE (Linux >= 6.3)")
    return libc, seccomp


def _sandbox(libc: ctypes.CDLL, seccomp: ctypes.CDLL) -> None:
    """Runs in the child between fork and exec (async-signal-safe enough: only syscalls)."""
    if libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        os._exit(90)
    if libc.prctl(PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN, 0, 0, 0) != 0:
        os._exit(91)
    seccomp.seccomp_init.restype = ctypes.c_void_p
    ctx = seccomp.seccomp_init(ctypes.c_uint32(SCMP_ACT_ALLOW))
    for name in DENIED:
        nr = seccomp.seccomp_syscall_resolve_name(name.encode())
        if nr < 0:
            continue  # not a system call on this architecture
        if seccomp.seccomp_rule_add(ctypes.c_void_p(ctx), ctypes.c_uint32(SCMP_ACT_ERRNO_EPERM),
                                    nr, 0) != 0:
            os._exit(92)
    if seccomp.seccomp_load(ctypes.c_void_p(ctx)) != 0:
        os._exit(93)


@pytest.mark.timeout(120)
def test_the_daemon_runs_under_the_units_memory_and_syscall_rules() -> None:
    libc, seccomp = _libs()
    cmd = [sys.executable, "-m", "service.cli", "run", "--config",
           str(REPO / "config" / "demo.toml"), "--duration", "8",
           "--set", "mavlink.url=udpout:127.0.0.1:9", "--set", "telemetry.enabled=true"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=90,
                          preexec_fn=lambda: _sandbox(libc, seccomp),
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    # numpy, OpenCV (pyramids, warps, DFTs), filterpy, Zenoh and pymavlink all ran: the net was
    # found and tracked.
    assert "net acquired" in proc.stderr
    assert "stopped cleanly" in proc.stderr


# Device classes the unit allows whose kernel driver is a module loaded when the first such
# device appears, and that module.
_LATE_DRIVERS = {"ttyACM": "cdc_acm", "ttyUSB": "usbserial", "video4linux": "videodev"}


def _unit_values(key: str) -> list[str]:
    values = []
    for line in (REPO / "systemd" / "netpose.service").read_text().splitlines():
        name, _, value = line.partition("=")
        if name.strip() == key:
            values += value.split()
    return values


def test_device_classes_whose_driver_loads_late_are_loaded_before_the_unit_starts() -> None:
    """systemd resolves DeviceAllow=char-NAME when the unit starts, and drops a name the kernel
    does not know yet: on a Pi whose autopilot is plugged in after boot, cdc_acm was not loaded
    then, and every open of /dev/ttyACM0 failed with EPERM until the service was restarted by
    hand. modprobe@MODULE.service loads the driver first (a built-in one is no error)."""
    allowed = {v.removeprefix("char-") for v in _unit_values("DeviceAllow") if v != "rw"}
    wants, after = set(_unit_values("Wants")), set(_unit_values("After"))
    for device_class, module in _LATE_DRIVERS.items():
        assert device_class in allowed
        assert f"modprobe@{module}.service" in wants, module
        assert f"modprobe@{module}.service" in after, module


@pytest.mark.skipif(not Path("/usr/bin/systemd-analyze").exists(),
                    reason="systemd-analyze not installed")
def test_the_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    unit = tmp_path / "netpose.service"
    # ExecStart's binary must exist for verify: the installed path, pointed at this venv's.
    unit.write_text((REPO / "systemd" / "netpose.service").read_text().replace(
        "/opt/netpose/venv/bin/netpose", str(Path(sys.executable).parent / "netpose")))
    result = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True,
                            text=True, timeout=60)
    problems = [line for line in (result.stdout + result.stderr).splitlines()
                if "netpose.service" in line]
    assert result.returncode == 0 and not problems, result.stdout + result.stderr
