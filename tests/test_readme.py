"""The README runs as written: every ```python block of README.md is a complete program.

Each block runs on its own in a fresh interpreter (this environment's, importing this checkout's
packages), with an empty temporary folder as its working directory: a block reads only what
the package ships (``converters/data``) or builds, never the checkout's ``tests/data``, and
writes nowhere but its own temporary folders (the checkout is left as it was). A block
that cannot run here (e.g. one that needs a live ROS graph) is preceded by the HTML comment
``<!-- readme-test: skip REASON -->``; the test then reports that reason as its skip reason.

What the prose names must exist too: every path of this checkout it quotes (```code``` or a
link) and every ``make`` target.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"

_FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```\s*$", re.S | re.M)
_SKIP = re.compile(r"<!--\s*readme-test:\s*skip\s+(.*?)\s*-->\s*$", re.S)


def python_blocks(text: str) -> list[tuple[int, str, str | None]]:
    """``(line, code, skip_reason)`` of every ```python block (line: 1-based, of the fence)."""
    blocks = []
    for match in _FENCE.finditer(text):
        if match.group(1) != "python":
            continue
        before = text[:match.start()].rstrip("\n")
        skip = _SKIP.search(before.rsplit("\n", 1)[-1])
        blocks.append((text.count("\n", 0, match.start()) + 1, match.group(2),
                       skip.group(1) if skip else None))
    return blocks


BLOCKS = python_blocks(README.read_text(encoding="utf-8"))


def test_the_extraction_finds_every_block_and_its_skip_reason() -> None:
    text = ("intro\n```python\na = 1\n```\n<!-- readme-test: skip needs a robot -->\n"
            "```python\nb = 2\n```\n```bash\nls\n```\n```python\n```\n")
    assert python_blocks(text) == [(2, "a = 1\n", None), (6, "b = 2\n", "needs a robot"),
                                   (12, "", None)]
    # the README has blocks, and skips stay rare
    assert len(BLOCKS) >= 6
    assert sum(reason is not None for _, _, reason in BLOCKS) <= 1


@pytest.mark.parametrize(("line", "code", "skip"), BLOCKS,
                         ids=[f"README.md:{line}" for line, _, _ in BLOCKS])
def test_readme_block_runs(line: int, code: str, skip: str | None, tmp_path: Path) -> None:
    if skip is not None:
        pytest.skip(f"README.md:{line}: {skip}")
    work, scratch = tmp_path / "work", tmp_path / "tmp"
    work.mkdir()
    scratch.mkdir()
    script = tmp_path / f"readme_{line}.py"
    script.write_text(code, encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    env["TMPDIR"] = str(scratch)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get(
        "PYTHONPATH", "").split(os.pathsep) if p])
    before = _checkout_state()
    done = subprocess.run([sys.executable, str(script)], cwd=work, env=env, check=False,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"README.md:{line}\n{code}\n{done.stdout}\n{done.stderr}"
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stdout.strip(), f"README.md:{line}: the block prints what it made"
    assert list(work.iterdir()) == [], \
        f"README.md:{line} wrote into its working directory: {sorted(work.iterdir())}"
    assert _checkout_state() == before, f"README.md:{line} changed files of the checkout"


def _checkout_state() -> dict[str, float]:
    """Modification time of every file of this checkout a README block could write (the
    demo's output folder, and the checkout's top level)."""
    out = {p.name: p.stat().st_mtime for p in ROOT.iterdir() if p.is_file()}
    demo = ROOT / "demo_out"
    if demo.is_dir():
        out.update({f"demo_out/{p.name}": p.stat().st_mtime for p in demo.iterdir()})
    return out


def named_paths(text: str, top: set[str]) -> list[str]:
    """Paths the text quotes (`code` or a link target) whose first part is one of ``top``."""
    quoted = re.findall(r"`([^`\s]+)`", text) + re.findall(r"\]\(([^)#\s]+)", text)
    return sorted({q for q in quoted if "/" in q and q.split("/")[0] in top})


def test_every_path_the_readme_names_exists() -> None:
    ignored = {line.strip().strip("/") for line in
               (ROOT / ".gitignore").read_text(encoding="utf-8").splitlines()}
    top = {p.name for p in ROOT.iterdir()
           if not p.name.startswith(".") and p.name not in ignored}   # not demo_out/, build/
    assert named_paths("see `lidarscan/scan.py`, [x](msgs/README.md#a), `demo_out/`, `a/b`",
                       {"lidarscan", "msgs"}) == ["lidarscan/scan.py", "msgs/README.md"]
    paths = named_paths(README.read_text(encoding="utf-8"), top)
    assert len(paths) >= 20
    missing = [p for p in paths if not list(ROOT.glob(p.rstrip("/")))]
    assert not missing, f"README.md names paths this checkout does not have: {missing}"


def test_every_make_target_the_readme_names_exists() -> None:
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(encoding="utf-8"),
                             re.M))
    named = set(re.findall(r"(?:^|`)make ([a-z][\w-]*)", README.read_text(encoding="utf-8"),
                           re.M))
    assert {"demo", "test", "install"} <= named
    assert named <= targets, f"README.md names make targets the Makefile lacks: {named - targets}"
