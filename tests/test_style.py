"""Repository style rules that a linter configuration does not cover."""
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINE = 120


def _tracked_files():
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--", "*.py", "*.md", "*.toml"], cwd=ROOT, check=True,
                             capture_output=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        pytest.skip(f"not a git checkout ({e})")
    paths = [p.decode() for p in out.split(b"\0") if p]
    return [p for p in paths if not p.startswith("benchmarks/results/") and Path(p).name != "LICENSE"]


def test_every_tracked_line_is_at_most_120_characters():
    long = []
    for rel in _tracked_files():
        path = ROOT / rel
        if not path.is_file():  # deleted in the working tree but still in the index
            continue
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if len(line) > MAX_LINE:
                long.append(f"{rel}:{i}: {len(line)} characters")
    assert not long, f"lines over {MAX_LINE} characters:\n" + "\n".join(long)
