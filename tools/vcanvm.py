#!/usr/bin/env python3
"""Real SocketCAN (vcan, can-raw, the kernel's ISO-TP) where the running kernel has none.

The SocketCAN tests need a kernel with ``vcan``, ``can-raw`` and ``can-isotp``.  Where the
kernel running the suite has them (``ip link add ... type vcan`` works) they run directly;
otherwise this script boots Debian's stock kernel in a small QEMU virtual machine and runs
one command inside it:

* the kernel is Debian's ``linux-image-amd64`` (its version resolved from the archive at
  set-up time, since Debian drops old versions from its mirror), downloaded with
  ``apt-get download`` and unpacked with ``dpkg -x``, never installed into /boot; only the
  kernel image and the few modules the VM loads are kept in the cache directory;
* the initramfs is busybox-static and those modules; its init loads them, mounts the
  host's root filesystem read-only over 9p (virtio) under a tmpfs overlay (so the guest can
  write anywhere and nothing reaches the host), creates ``vcan0`` (MTU 72, CAN FD), runs
  the command in the caller's directory with the caller's environment, and powers off;
* the command's output streams to this process's standard output through the serial
  console, and its exit status comes back through a second, writable 9p share;
* KVM is used where it works; where ``/dev/kvm`` is missing or cannot run a stock kernel
  (a nested variant that aborts on MSR 0x10a), QEMU's software emulation (TCG) runs the
  VM, about 20× slower for Python.  The verdict on KVM is cached.

Usage::

    python tools/vcanvm.py status            # what runs the SocketCAN tests here, and why
    python tools/vcanvm.py setup             # kernel + initramfs into the cache (idempotent)
    python tools/vcanvm.py run [--] CMD ...  # boot, run CMD in the current directory
    python tools/vcanvm.py pytest [ARGS]     # the SocketCAN tests (pytest -m socketcan):
                                             # on this kernel if it has vcan, else in the VM

The Debian packages it needs (qemu-system-x86, busybox-static, kmod, can-utils, iproute2)
are installed by ``make debs``; ``make test-vcan`` runs the ``pytest`` subcommand.  Where
the VM's own (qemu-system-x86, busybox-static, kmod) are missing, ``setup`` and ``pytest``
install them with apt-get as ``make debs`` does when run as root with apt-get at hand.
Exit status: the command's; 2 on a set-up error (one line on stderr); ``pytest`` exits 0
with a SKIPPED line naming the reason only where neither the kernel nor a VM can give
vcan (the packages missing and not installable here: not root, or no apt-get).
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import io
import json
import os
import re
import select
import shlex
import shutil
import stat
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CACHE = Path(os.environ.get("CATC_VM_CACHE")
             or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
             / "catc-hil" / "vcan-vm")
#: Modules the guest loads, each after what it depends on (``modinfo -F depends``).
MODULES = ("virtio_pci", "9pnet_virtio", "9p", "overlay", "vcan", "can-raw", "can-isotp")
#: Environment variables passed into the guest as they are here (plus CATC_*, PYTEST_*).
PASS_ENV = ("PATH", "VIRTUAL_ENV", "CI", "LANG", "LC_ALL", "OPENBLAS_NUM_THREADS",
            "OMP_NUM_THREADS", "PYTHONPATH", "TERM")
MEMORY_MB = 2048
#: How long one VM may run before it is killed (s); ``--timeout`` overrides.
DEFAULT_TIMEOUT = 1200
SOCKETCAN_MARK = "socketcan"


class SetupError(Exception):
    """The VM cannot be set up here; ``str()`` is one line."""


def log(text: str) -> None:
    print(f"vcanvm: {text}", file=sys.stderr, flush=True)


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, **kw)
    except OSError as exc:
        return subprocess.CompletedProcess(cmd, 127, "", str(exc))


# --- what this machine has ------------------------------------------------------------

def host_has_vcan() -> tuple[bool, str]:
    """Whether a vcan interface can be created on the running kernel (tried, then deleted)."""
    name = f"catcprobe{os.getpid() % 100000}"
    made = _run(["ip", "link", "add", "dev", name, "type", "vcan"], timeout=10)
    if made.returncode != 0:
        return False, (made.stderr.strip() or made.stdout.strip() or "ip failed")
    _run(["ip", "link", "del", "dev", name], timeout=10)
    return True, "vcan on the running kernel"


#: The Debian packages the VM needs, as the Makefile's ``debs`` target names them, by the
#: program each gives; and apt-get and dpkg themselves (for the kernel package).
VM_PACKAGES = {"qemu-system-x86_64": "qemu-system-x86", "busybox": "busybox-static",
               "modinfo": "kmod"}
_APT = {"apt-get": "apt", "dpkg": "dpkg"}


def _missing_tools(apt: bool = True) -> list[str]:
    """The Debian packages of :data:`VM_PACKAGES` (and, with ``apt``, apt and dpkg, which
    the set-up needs) whose program is not here; busybox counts only statically linked."""
    missing = [pkg for tool, pkg in {**VM_PACKAGES, **(_APT if apt else {})}.items()
               if shutil.which(tool) is None]
    if "busybox-static" not in missing and _static_busybox() is None:
        missing.append("busybox-static")
    return missing


def install_missing(apt: bool = True) -> tuple[list[str], str]:
    """Install the missing packages of the VM (:func:`_missing_tools`) with apt-get where
    this process can (root, apt-get at hand), as ``make debs`` does; ``(still missing,
    why)``: empty when all are here, else the packages and one phrase saying why they
    are not installed."""
    missing = _missing_tools(apt)
    if not missing:
        return [], ""
    if shutil.which("apt-get") is None or shutil.which("dpkg") is None:
        return missing, "no apt-get here to install them"
    if os.geteuid() != 0:
        return missing, "not root, so not installed (make debs, as root)"
    log(f"installing the Debian packages {' '.join(missing)} (apt-get)")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    _run(["apt-get", "update", "-q"], timeout=600, env=env)
    got = _run(["apt-get", "install", "-y", "-q", "--no-install-recommends", *missing],
               timeout=1800, env=env)
    still = _missing_tools(apt)
    if still:
        last = (got.stderr.strip() or got.stdout.strip()).splitlines()[-1:] or ["?"]
        return still, f"apt-get install failed: {last[0]}"
    return [], ""


def _is_static(path: Path) -> bool:
    """An ELF64 executable without a program interpreter (PT_INTERP)."""
    head = path.read_bytes()[:65536]
    if head[:5] != b"\x7fELF\x02":
        return False
    phoff, = struct.unpack_from("<Q", head, 0x20)
    phentsize, phnum = struct.unpack_from("<HH", head, 0x36)
    return all(struct.unpack_from("<I", head, phoff + i * phentsize)[0] != 3
               for i in range(phnum))


def _static_busybox() -> Path | None:
    """A statically linked busybox (busybox-static installs it as /bin/busybox)."""
    for candidate in ("/bin/busybox", "/usr/bin/busybox"):
        path = Path(candidate)
        if path.exists() and _is_static(path):
            return path
    return None


def _busybox() -> Path:
    path = _static_busybox()
    if path is None:
        raise SetupError("no static busybox: install the Debian package busybox-static "
                         "(make debs)")
    return path


# --- set-up: the kernel and the initramfs --------------------------------------------

def _kernel_package() -> str:
    """The versioned kernel package that ``linux-image-amd64`` depends on today."""
    out = _run(["apt-cache", "depends", "linux-image-amd64"], timeout=60)
    found = re.findall(r"Depends:\s*(linux-image-[0-9][^\s]*-amd64)", out.stdout)
    if not found:
        upd = _run(["apt-get", "update", "-q"], timeout=600)
        if upd.returncode != 0:
            raise SetupError("apt-get update failed: "
                             + (upd.stderr.strip().splitlines() or ["?"])[-1])
        out = _run(["apt-cache", "depends", "linux-image-amd64"], timeout=60)
        found = re.findall(r"Depends:\s*(linux-image-[0-9][^\s]*-amd64)", out.stdout)
    if not found:
        raise SetupError("cannot resolve linux-image-amd64 from the Debian archive: "
                         + (out.stderr.strip() or "no Depends line"))
    return found[0]


def _module_order(root: Path, release: str) -> list[Path]:
    """The .ko files of :data:`MODULES` and their dependencies, dependencies first."""
    tree = root / "lib" / "modules" / release
    files = {p.name.removesuffix(".ko"): p for p in tree.rglob("*.ko")}
    order: list[Path] = []

    def visit(name: str, depth: int = 0) -> None:
        name_dash = name.replace("_", "-")
        key = name if name in files else name_dash if name_dash in files \
            else name.replace("-", "_")
        if key not in files:
            raise SetupError(f"kernel {release} has no module {name}")
        path = files[key]
        if path in order or depth > 20:
            return
        deps = _run(["modinfo", "-F", "depends", str(path)]).stdout.strip()
        for dep in filter(None, deps.split(",")):
            visit(dep, depth + 1)
        if path not in order:
            order.append(path)

    for name in MODULES:
        visit(name)
    return order


INIT = r"""#!/bin/busybox sh
# catc-hil vcan VM init: modules, the host's root read-only under a tmpfs overlay, vcan0,
# one command, its exit status into the exchange share, power off.
/bin/busybox --install -s /bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
echo "vcanvm: guest up"
for m in $(cat /modules.order); do insmod "/modules/$m" || echo "vcanvm: insmod $m failed"; done
mkdir -p /host /rw /newroot /exchange
opts=trans=virtio,version=9p2000.L,msize=512000
mount -t 9p -o "$opts,ro,cache=loose" hostroot /host || echo "vcanvm: no host root"
mount -t 9p -o "$opts" exchange /exchange || echo "vcanvm: no exchange share"
mount -t tmpfs -o size=75% tmpfs /rw
mkdir -p /rw/upper /rw/work
if ! mount -t overlay overlay -o lowerdir=/host,upperdir=/rw/upper,workdir=/rw/work /newroot
then
  echo "vcanvm: overlay failed"; echo 125 > /exchange/status; poweroff -f
fi
mount -t proc proc /newroot/proc
mount -t sysfs sys /newroot/sys
mount -t devtmpfs dev /newroot/dev
mkdir -p /newroot/dev/pts /newroot/dev/shm /newroot/run /newroot/tmp /newroot/vcanvm
mount -t devpts devpts /newroot/dev/pts
mount -t tmpfs tmpfs /newroot/dev/shm
mount -t tmpfs tmpfs /newroot/run
# /tmp stays the overlay's (host files, writes to the tmpfs): a checkout under /tmp shows
mount --bind /exchange /newroot/vcanvm
ip link set lo up
chroot /newroot /bin/sh -c 'ip link add dev vcan0 type vcan && ip link set dev vcan0 mtu 72 up' \
  || echo "vcanvm: cannot create vcan0"
chroot /newroot /bin/sh /vcanvm/run.sh
echo $? > /exchange/status
sync
poweroff -f
"""


def _cpio(entries: list[tuple[str, int, bytes]]) -> bytes:
    """A ``newc`` cpio archive of (path, mode, data); directories have empty data."""
    out = io.BytesIO()
    for ino, (name, mode, data) in enumerate([*entries, ("TRAILER!!!", 0, b"")], 1):
        encoded = name.encode() + b"\0"
        fields = (ino, mode, 0, 0, 1, 0, len(data), 0, 0, 0, 0, len(encoded), 0)
        out.write(b"070701" + b"".join(b"%08X" % f for f in fields) + encoded)
        out.write(b"\0" * (-(110 + len(encoded)) % 4))
        out.write(data + b"\0" * (-len(data) % 4))
    return out.getvalue()


def _cached() -> bool:
    done = CACHE / "current"
    return (done / "vmlinuz").exists() and (done / "initramfs.cpio.gz").exists()


def setup(quiet: bool = False) -> Path:
    """Kernel image, modules and initramfs in the cache; returns their directory."""
    done = CACHE / "current"
    if _cached():
        return done.resolve()
    missing, why = install_missing()
    if missing:
        raise SetupError(f"missing Debian packages: {' '.join(missing)} ({why})")
    busybox = _busybox()
    package = _kernel_package()
    release = package.removeprefix("linux-image-")
    target = CACHE / release
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=CACHE) as tmp:
        if not quiet:
            log(f"downloading {package} (Debian's kernel, about 70 MB, once)")
        got = _run(["apt-get", "download", package], cwd=tmp, timeout=900)
        debs = list(Path(tmp).glob("*.deb"))
        if got.returncode != 0 or not debs:
            raise SetupError(f"apt-get download {package} failed: "
                             + (got.stderr.strip().splitlines() or ["?"])[-1])
        tree = Path(tmp) / "x"
        unpacked = _run(["dpkg", "-x", str(debs[0]), str(tree)], timeout=600)
        if unpacked.returncode != 0:
            raise SetupError(f"dpkg -x failed: {unpacked.stderr.strip()}")
        modules = _module_order(tree, release)
        staging = Path(tmp) / "out"
        staging.mkdir()
        shutil.copy(tree / "boot" / f"vmlinuz-{release}", staging / "vmlinuz")
        entries: list[tuple[str, int, bytes]] = [
            (d, stat.S_IFDIR | 0o755, b"") for d in
            ("bin", "dev", "proc", "sys", "modules", "host", "rw", "newroot", "exchange")]
        entries.append(("bin/busybox", stat.S_IFREG | 0o755, busybox.read_bytes()))
        entries.append(("modules.order", stat.S_IFREG | 0o644,
                        "".join(f"{m.name}\n" for m in modules).encode()))
        entries += [(f"modules/{m.name}", stat.S_IFREG | 0o644, m.read_bytes())
                    for m in modules]
        (staging / "initramfs.cpio.gz").write_bytes(gzip.compress(_cpio(entries), 6))
        (staging / "kernel.json").write_text(json.dumps(
            {"package": package, "release": release,
             "modules": [m.name for m in modules]}, indent=1))
        if target.exists():
            shutil.rmtree(target)
        staging.rename(target)
    tmp_link = CACHE / "current.tmp"
    with contextlib.suppress(FileNotFoundError):
        tmp_link.unlink()
    tmp_link.symlink_to(release)
    tmp_link.replace(done)
    if not quiet:
        size = sum(p.stat().st_size for p in target.iterdir()) / 1e6
        log(f"kernel {release}: {size:.1f} MB kept in {target}")
    return target


# --- booting ------------------------------------------------------------------------

def _kvm_verdict() -> str | None:
    """``"ok"``, ``"broken: why"`` or None (not tried yet)."""
    path = CACHE / "kvm.status"
    return path.read_text().strip() if path.exists() else None


def _kvm_usable() -> bool:
    if os.environ.get("CATC_VM_ACCEL") in ("tcg", "kvm"):
        return os.environ["CATC_VM_ACCEL"] == "kvm"
    if not os.access("/dev/kvm", os.R_OK | os.W_OK):
        return False
    return not (_kvm_verdict() or "").startswith("broken")


def _qemu(kernel_dir: Path, exchange: Path, accel: str, initrd: Path) -> list[str]:
    cpu = ["-accel", "kvm", "-cpu", "host"] if accel == "kvm" else \
        ["-accel", "tcg,thread=multi,tb-size=512", "-cpu", "max"]
    return [
        "qemu-system-x86_64", "-machine", "q35", *cpu, "-smp", str(os.cpu_count() or 1),
        "-m", str(MEMORY_MB), "-display", "none", "-monitor", "none", "-serial", "stdio",
        "-no-reboot", "-nic", "none",
        "-kernel", str(kernel_dir / "vmlinuz"), "-initrd", str(initrd),
        "-append", "console=ttyS0 quiet loglevel=3 panic=-1 rdinit=/init",
        "-virtfs", "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,"
                   "multidevs=remap",
        "-virtfs", f"local,path={exchange},mount_tag=exchange,security_model=none",
    ]


def _script(cmd: list[str], cwd: Path, env: dict[str, str]) -> str:
    lines = ["export HOME=/tmp/home MPLBACKEND=Agg PYTHONDONTWRITEBYTECODE=1",
             "mkdir -p /tmp/home"]
    lines += [f"export {k}={shlex.quote(v)}" for k, v in sorted(env.items())]
    lines += [f"cd {shlex.quote(str(cwd))} || exit 126", shlex.join(cmd)]
    return "\n".join(lines) + "\n"


def _guest_env() -> dict[str, str]:
    env = {k: os.environ[k] for k in PASS_ENV if k in os.environ}
    env.update({k: v for k, v in os.environ.items()
                if k.startswith(("CATC_", "PYTEST_")) and k != "CATC_VM_ACCEL"})
    env["CATC_IN_VCAN_VM"] = "1"
    return env


class _NoBoot(Exception):
    pass


#: What the init prints first, and how long a guest may take to print it (s).
BOOTED = b"vcanvm: guest up"
BOOT_TIMEOUT = {"kvm": 30.0, "tcg": 120.0}


def _remember_broken_kvm(why: str) -> None:
    (CACHE / "kvm.status").write_text(f"broken: {why}\n")
    log(f"KVM cannot run this kernel here ({why}); falling back to TCG (remembered)")


def boot(cmd: list[str], timeout: float = DEFAULT_TIMEOUT, accel: str | None = None) -> int:
    """Run ``cmd`` in the VM in the current directory; its exit status."""
    kernel_dir = setup()
    missing, why = install_missing(apt=False)  # QEMU, where it went since the set-up
    if missing:
        raise SetupError(f"missing Debian packages: {' '.join(missing)} ({why})")
    if accel is None:
        accel = "kvm" if _kvm_usable() else "tcg"
    with tempfile.TemporaryDirectory(prefix="catc-vm-") as exchange:
        ex = Path(exchange)
        (ex / "run.sh").write_text(_script(cmd, Path.cwd(), _guest_env()))
        # The cached archive (busybox, modules) and, appended, the init of this version of
        # the script: the kernel unpacks concatenated cpio archives in order.
        initrd = ex / "initrd"
        cached = (kernel_dir / "initramfs.cpio.gz").read_bytes()
        initrd.write_bytes(cached + b"\0" * (-len(cached) % 4)  # archives start 4-aligned
                           + _cpio([("init", stat.S_IFREG | 0o755, INIT.encode())]))
        t0 = time.monotonic()
        log(f"booting Debian's kernel {kernel_dir.name} under QEMU ({accel.upper()}"
            + (", software emulation" if accel == "tcg" else "") + ")")
        proc = subprocess.Popen(_qemu(kernel_dir, ex, accel, initrd), stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        stderr, booted, tail = b"", False, b""
        try:
            assert proc.stdout is not None
            # Stream the console (CRLF from the serial line) until QEMU exits; a guest that
            # has not said it is up within BOOT_TIMEOUT is stopped (KVM that hangs on a
            # stock kernel spins at 100 % CPU without a word).
            while True:
                ready, _, _ = select.select([proc.stdout], [], [], 1.0)
                elapsed = time.monotonic() - t0
                if ready:
                    chunk = proc.stdout.read1(65536)
                    if not chunk:
                        break
                    sys.stdout.buffer.write(chunk.replace(b"\r\n", b"\n"))
                    sys.stdout.flush()
                    tail = (tail + chunk)[-64:]
                    booted = booted or BOOTED in tail
                if not booted and elapsed > BOOT_TIMEOUT[accel]:
                    raise _NoBoot
                if elapsed > timeout:
                    raise TimeoutError
            proc.wait(timeout=30)
        except _NoBoot:
            proc.kill()
            proc.wait()
            if accel == "kvm":
                _remember_broken_kvm(f"no guest output within {BOOT_TIMEOUT['kvm']} s")
                return boot(cmd, timeout, "tcg")
            raise SetupError(f"the VM did not boot within {BOOT_TIMEOUT[accel]} s") from None
        except (TimeoutError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()
            log(f"the VM ran longer than {timeout:.0f} s and was stopped")
            return 124
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            stderr = proc.stderr.read() if proc.stderr else b""
        status = ex / "status"
        if not status.exists():
            err = stderr.decode(errors="replace").strip()
            if accel == "kvm" and not booted:
                _remember_broken_kvm((err.splitlines() or ["no exit status"])[-1][:200])
                return boot(cmd, timeout, "tcg")
            raise SetupError("the VM gave no exit status"
                             + (f": {err.splitlines()[-1]}" if err else ""))
        if accel == "kvm" and _kvm_verdict() is None:
            (CACHE / "kvm.status").write_text("ok\n")
        log(f"VM done in {time.monotonic() - t0:.1f} s")
        return int(status.read_text().strip() or 1)


# --- commands ------------------------------------------------------------------------

def _can_vm(install: bool = False) -> tuple[bool, str]:
    """Whether a VM can run here, and why; ``install``: install its missing Debian
    packages first where root with apt-get (:func:`install_missing`)."""
    apt = not _cached()  # the set-up downloads the kernel with apt-get
    if install:
        missing, why = install_missing(apt)
    else:
        missing = _missing_tools(apt)
        why = "make debs, as root, or vcanvm.py pytest as root installs them"
    if missing:
        return False, f"missing Debian packages {' '.join(missing)} ({why})"
    return True, "QEMU " + ("KVM" if _kvm_usable() else "TCG (software emulation)")


def cmd_status(_args: argparse.Namespace) -> int:
    native, why = host_has_vcan()
    vm_ok, vm_why = _can_vm()
    print(json.dumps({"host_vcan": native, "host_reason": why, "vm": vm_ok,
                      "vm_reason": vm_why, "kvm": _kvm_verdict(),
                      "cache": str(CACHE)}, indent=1))
    return 0


def cmd_setup(_args: argparse.Namespace) -> int:
    print(setup())
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        raise SetupError("run: no command given")
    return boot(command, args.timeout)


def _socketcan_files() -> list[str]:
    """The test files that hold SocketCAN tests, as ``tests/conftest.py`` lists them (its
    collection hook checks the list): collecting the whole suite under software emulation
    takes a minute, these files ten seconds."""
    import ast

    tree = ast.parse((REPO / "tests" / "conftest.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.AnnAssign | ast.Assign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(getattr(t, "id", None) == "SOCKETCAN_FILES" for t in targets):
                return list(ast.literal_eval(node.value))
    raise SetupError("tests/conftest.py has no SOCKETCAN_FILES")


def cmd_pytest(args: argparse.Namespace) -> int:
    """The SocketCAN tests, where vcan exists: this kernel, else the VM."""
    pytest_cmd = [sys.executable, "-m", "pytest", "-m", SOCKETCAN_MARK, "-p",
                  "no:cacheprovider", *args.pytest_args]
    os.environ["CATC_REQUIRE_VCAN"] = "1"  # inside, a missing vcan fails, never skips
    native, why = host_has_vcan()
    if native:
        if args.if_needed:
            log("the running kernel has vcan: the SocketCAN tests ran in the main suite")
            return 0
        log("the running kernel has vcan: running the SocketCAN tests here")
        return subprocess.call(pytest_cmd)
    vm_ok, vm_why = _can_vm(install=True)
    if not vm_ok:
        print(f"SKIPPED: SocketCAN tests: no vcan on this kernel ({why}) and no VM: {vm_why}",
              flush=True)
        return 0
    log(f"no vcan on this kernel ({why}): running the SocketCAN tests in a VM")
    if not any(a.startswith("tests") for a in args.pytest_args):
        pytest_cmd += _socketcan_files()
    return boot(pytest_cmd, args.timeout)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vcanvm", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("status", help="what runs the SocketCAN tests here").set_defaults(
        func=cmd_status)
    sub.add_parser("setup", help="kernel and initramfs into the cache").set_defaults(
        func=cmd_setup)
    r = sub.add_parser("run", help="run a command in the VM, in this directory")
    r.add_argument("command", nargs=argparse.REMAINDER)
    r.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT)
    r.set_defaults(func=cmd_run)
    t = sub.add_parser("pytest", help="the SocketCAN tests: on this kernel, else in the VM")
    t.add_argument("--if-needed", action="store_true",
                   help="do nothing when this kernel has vcan (the main suite ran them)")
    t.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT)
    t.set_defaults(func=cmd_pytest)
    args, rest = p.parse_known_args(argv)
    if rest and args.cmd != "pytest":
        p.error(f"unrecognized arguments: {' '.join(rest)}")
    args.pytest_args = rest  # everything else goes to pytest
    try:
        return args.func(args)
    except SetupError as err:
        print(f"vcanvm: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
