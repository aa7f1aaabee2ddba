"""Run every benchmark in bench/ (each prints medians and ratios against its own baselines)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SKIP = {"run_all.py", "fuzz.py", "soak.py"}  # long runs: start them on their own


def main() -> int:
    failed = []
    for script in sorted(Path(__file__).parent.glob("bench_*.py")):
        if script.name in SKIP:
            continue
        print(f"\n=== {script.name} ===", flush=True)
        if subprocess.run([sys.executable, str(script)], check=False).returncode:
            failed.append(script.name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
