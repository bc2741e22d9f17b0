"""Set-up: `make demo` installs what the demo needs and never the browser; `make test` adds it;
every pip install is pinned by constraints.txt. The scripts run for real, with apt-get, id and
ldconfig replaced by stubs that record what would be installed on a machine without them."""

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _stub_env(tmp_path: Path, libs_present: bool) -> dict:
    """PATH holding only stubs and the few tools the scripts use: no chromium on it."""
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    log = tmp_path / "apt.log"
    stubs = {
        "apt-get": f'#!/bin/sh\necho "$@" >> {log}\n',
        "id": "#!/bin/sh\necho 0\n",  # as root, as a fresh container would run it
        "ldconfig": "#!/bin/sh\n" + ("/sbin/ldconfig \"$@\"\n" if libs_present else "exit 0\n"),
    }
    for name, text in stubs.items():
        (bin_ / name).write_text(text)
        (bin_ / name).chmod(0o755)
    for tool in ("bash", "sh", "grep", "ls", "cat"):
        real = subprocess.run(["bash", "-c", f"command -v {tool}"], capture_output=True, text=True).stdout.strip()
        os.symlink(real, bin_ / tool)
    return {"PATH": str(bin_), "HOME": str(tmp_path)}


@pytest.mark.parametrize("libs_present", [False, True])
def test_demo_setup_never_installs_chromium_and_test_setup_does(tmp_path, libs_present):
    env = _stub_env(tmp_path, libs_present)
    log = tmp_path / "apt.log"
    sysdeps = subprocess.run(["bash", str(ROOT / ".ci/system-deps")], capture_output=True, text=True, env=env)
    assert sysdeps.returncode == 0, sysdeps.stderr
    installed = log.read_text() if log.exists() else ""
    assert "chromium" not in installed
    if not libs_present:  # a bare machine: the GL libraries are installed, nothing else
        assert re.search(r"install -y -qq libegl1 libegl-mesa0 .*libgl1", installed)
    log.unlink(missing_ok=True)
    testdeps = subprocess.run(["bash", str(ROOT / ".ci/test-deps")], capture_output=True, text=True, env=env)
    assert testdeps.returncode == 0 and "install -y -qq chromium" in log.read_text()


def test_make_demo_runs_only_the_demo_setup_and_every_install_is_pinned(tmp_path):
    def plan(target):
        proc = subprocess.run(["make", "-n", target, f"VENV={tmp_path / 'venv'}"], cwd=ROOT, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        return proc.stdout

    demo, test = plan("demo"), plan("test")
    assert ".ci/system-deps" in demo and "test-deps" not in demo and "chromium" not in demo and "[test]" not in demo
    assert ".ci/test-deps" in test and "'.[test]'" in test
    for line in (demo + test).splitlines():
        if "pip install" in line:
            assert "-c constraints.txt" in line, line
    pins = [ln for ln in (ROOT / "constraints.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    assert all(re.fullmatch(r"[A-Za-z0-9_.\-]+==[\w.\-+]+", p) for p in pins), pins
    names = {p.split("==")[0].lower().replace("_", "-") for p in pins}
    for dep in ("numpy", "moderngl", "mpi4py", "zarr", "rasterio", "websockets", "pytest", "playwright"):
        assert dep in names
