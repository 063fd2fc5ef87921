"""tools/vcanvm.py's choice between running the SocketCAN tests in a VM and skipping them:
it installs the VM's Debian packages (as ``make debs`` names them) where it is root with
apt-get, and skips, saying why, only where it cannot.  Nothing is installed here: apt-get
and the programs' presence are stand-ins."""

from __future__ import annotations

import argparse
import importlib.util
import os
import types
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "vcanvm.py"


@pytest.fixture
def vm(monkeypatch):
    spec = importlib.util.spec_from_file_location("vcanvm_under_test", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    installed = {"apt-get", "dpkg", "modinfo"}  # qemu and static busybox missing
    ran: list[list[str]] = []

    def which(tool):
        return f"/usr/bin/{tool}" if tool in installed else None

    def run(cmd, **_kw):
        ran.append(cmd)
        if cmd[:2] == ["apt-get", "install"]:
            names = {pkg: tool for tool, pkg in mod.VM_PACKAGES.items()}
            installed.update(names[p] for p in cmd if p in names)
        return types.SimpleNamespace(returncode=0, stdout="", stderr="")

    monkeypatch.setattr(mod, "shutil", types.SimpleNamespace(which=which))
    monkeypatch.setattr(mod, "_run", run)
    monkeypatch.setattr(mod, "_static_busybox",
                        lambda: Path("/bin/busybox") if "busybox" in installed else None)
    monkeypatch.setattr(mod, "host_has_vcan", lambda: (False, "no vcan here"))
    monkeypatch.setattr(mod, "_kvm_usable", lambda: False)
    monkeypatch.setattr(mod, "_cached", lambda: True)
    booted: list[list[str]] = []
    monkeypatch.setattr(mod, "boot", lambda cmd, _timeout: booted.append(cmd) or 0)
    monkeypatch.setenv("CATC_REQUIRE_VCAN", "")
    mod.test_state = types.SimpleNamespace(installed=installed, ran=ran, booted=booted)
    return mod


def _pytest(vm) -> int:
    return vm.cmd_pytest(argparse.Namespace(pytest_args=[], if_needed=False, timeout=60))


def test_as_root_with_apt_get_it_installs_the_missing_packages_and_runs(vm, monkeypatch,
                                                                         capsys):
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    assert _pytest(vm) == 0
    installs = [c for c in vm.test_state.ran if c[:2] == ["apt-get", "install"]]
    assert len(installs) == 1
    assert set(installs[0][2:]) == {"-y", "-q", "--no-install-recommends",
                                    "qemu-system-x86", "busybox-static"}
    assert vm.test_state.booted  # then the tests ran in the VM
    assert "SKIPPED" not in capsys.readouterr().out


@pytest.mark.parametrize("root, apt, reason", [
    (False, True, "not root"),
    (True, False, "no apt-get"),
])
def test_it_skips_only_where_nothing_can_install_them_and_says_why(vm, monkeypatch, capsys,
                                                                    root, apt, reason):
    monkeypatch.setattr(os, "geteuid", lambda: 0 if root else 1000)
    if not apt:
        vm.test_state.installed.discard("apt-get")
    assert _pytest(vm) == 0
    out = capsys.readouterr().out
    assert out.startswith("SKIPPED: SocketCAN tests") and reason in out, out
    assert "qemu-system-x86" in out and "busybox-static" in out
    assert not any(c[:2] == ["apt-get", "install"] for c in vm.test_state.ran)
    assert not vm.test_state.booted
