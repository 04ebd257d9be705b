"""Run a command under the system-call policy of a systemd unit file, as systemd applies it:
``python tests/unit_jail.py UNIT_FILE -- COMMAND...``.

``SystemCallFilter=`` (an allow list, then ``~`` denials; groups expanded by
``systemd-analyze syscall-filter``; refused calls fail with EPERM as
``SystemCallErrorNumber=EPERM`` says), ``RestrictAddressFamilies=`` (other families fail
with EAFNOSUPPORT) and ``MemoryDenyWriteExecute=`` (the kernel's PR_SET_MDWE, where it has
it) are loaded with libseccomp, then the command is executed. Used by tests/test_deploy.py to
show that each service starts under its unit's filter without a service manager.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import os
import socket
import subprocess
import sys

SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_CMP_EQ = 4
PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN = 65, 1
AF_MAX = 46


def scmp_act_errno(code: int) -> int:
    return 0x00050000 | (code & 0xFFFF)


class ArgCmp(ctypes.Structure):  # struct scmp_arg_cmp
    _fields_ = [("arg", ctypes.c_uint), ("op", ctypes.c_int), ("datum_a", ctypes.c_uint64), ("datum_b", ctypes.c_uint64)]


def syscall_groups() -> dict[str, list[str]]:
    """``@group`` -> its members (system calls and nested groups), from systemd-analyze."""
    out = subprocess.run(["systemd-analyze", "syscall-filter", "--no-pager"], capture_output=True, text=True, check=True).stdout
    groups: dict[str, list[str]] = {}
    current = None
    for line in out.splitlines():
        if line.startswith("@"):
            current = line.split()[0]
            groups[current] = []
        elif current and line.strip() and not line.strip().startswith("#"):
            groups[current].append(line.strip())
    return groups


def expand(items: list[str], groups: dict[str, list[str]]) -> set[str]:
    @functools.cache
    def one(name: str) -> frozenset[str]:
        return frozenset(expand(groups[name], groups)) if name.startswith("@") else frozenset({name})
    return set().union(*(one(i) for i in items)) if items else set()


def policy(unit_text: str) -> tuple[set[str], set[int], bool]:
    """(allowed system calls, allowed address families, memory deny write execute) of a unit."""
    filters, families, mdwe = [], "", False
    for line in unit_text.splitlines():
        key, _, value = line.partition("=")
        if key == "SystemCallFilter":
            filters.append(value)
        elif key == "RestrictAddressFamilies":
            families = value
        elif key == "MemoryDenyWriteExecute":
            mdwe = value == "yes"
    if not filters or filters[0].startswith("~") or not families:
        raise SystemExit("unit_jail: the unit needs an allow list SystemCallFilter= and RestrictAddressFamilies=")
    groups = syscall_groups()
    allowed = expand(filters[0].split(), groups)
    for entry in filters[1:]:
        names = entry.removeprefix("~").split()
        allowed = allowed - expand(names, groups) if entry.startswith("~") else allowed | expand(names, groups)
    return allowed, {getattr(socket, f) for f in families.split()}, mdwe


def load(allowed: set[str], families: set[int], mdwe: bool) -> None:
    lib = ctypes.CDLL("libseccomp.so.2")
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_rule_add_array.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint, ctypes.c_void_p]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    ctx = lib.seccomp_init(scmp_act_errno(errno.EPERM))
    for name in sorted(allowed - {"socket"}):
        number = lib.seccomp_syscall_resolve_name(name.encode())
        if number >= 0:  # names of other architectures resolve to nothing here
            lib.seccomp_rule_add_array(ctx, SCMP_ACT_ALLOW, number, 0, None)
    if "socket" in allowed:
        number = lib.seccomp_syscall_resolve_name(b"socket")
        for family in range(AF_MAX):
            action = SCMP_ACT_ALLOW if family in families else scmp_act_errno(errno.EAFNOSUPPORT)
            if lib.seccomp_rule_add_array(ctx, action, number, 1, (ArgCmp * 1)(ArgCmp(0, SCMP_CMP_EQ, family, 0))) != 0:
                raise SystemExit("unit_jail: libseccomp refused the socket rule")
    if mdwe:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN, 0, 0, 0) != 0:
            print("unit_jail: this kernel has no PR_SET_MDWE; MemoryDenyWriteExecute not applied", file=sys.stderr)
    if lib.seccomp_load(ctx) != 0:
        raise SystemExit("unit_jail: seccomp_load failed")


def main(argv: list[str]) -> None:
    unit_file, command = argv[0], argv[argv.index("--") + 1:]
    with open(unit_file) as f:
        allowed, families, mdwe = policy(f.read())
    load(allowed, families, mdwe)
    os.execv(command[0], command)


if __name__ == "__main__":
    main(sys.argv[1:])
