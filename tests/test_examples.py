"""Every script in examples/ runs on its own, quickly, writing only where it is told."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples").glob("*.py"))


def test_there_are_examples() -> None:
    assert [p.name[:2] for p in EXAMPLES] == ["01", "02", "03", "04", "05"]


@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.name)
def test_example_runs(script: Path, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    env["ROS_DOMAIN_ID"] = str(1 + (os.getpid() + 37) % 100)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["TMPDIR"] = str(tmp_path)
    out_dir = tmp_path / "out"
    done = subprocess.run([sys.executable, str(script), str(out_dir)], cwd=tmp_path, env=env,
                          check=False, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip(), "an example says what it did"
    assert "Traceback" not in done.stderr
    # nothing written outside the temporary folder given to it
    assert not (Path(script).parent / "out").exists()
