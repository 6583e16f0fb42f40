""".ci/system-deps without root: one line saying what to install; a failure only where the
tests need the packages (CI=true), else the tests that need them skip."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / ".ci" / "system-deps"
BASH = shutil.which("bash")


@pytest.mark.skipif(BASH is None, reason="no bash")
@pytest.mark.parametrize(("ci", "status"), [("", 0), ("true", 1)])
def test_system_deps_without_root_says_what_to_install(tmp_path, ci, status):
    bin_ = tmp_path / "bin"  # no chromium, no sudo; id says an ordinary user
    bin_.mkdir()
    (bin_ / "id").write_text("#!/bin/sh\necho 1000\n")
    (bin_ / "id").chmod(0o755)
    env = {"PATH": str(bin_), "ROBID_CHROMIUM": str(tmp_path / "none"), "CI": ci,
           "HOME": str(tmp_path)}
    out = subprocess.run([BASH, str(SCRIPT)], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == status, out
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and out.stdout == "", out
    assert lines[0].startswith("system-deps: missing chromium") and "neither root nor sudo" \
        in lines[0] and "apt-get install chromium" in lines[0], lines
    assert ("CI needs them" in lines[0]) == bool(ci)
    assert os.access(SCRIPT, os.X_OK)
