"""benchmarks/bodies_one_program.py: the five layouts step two bodies to the same states (checked inside)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bodies_one_program as bop  # noqa: E402


def test_layouts_agree_and_are_timed():
    row = bop.child(1, repeats=1)   # raises if a layout's states differ from one body's step
    assert set(row["p50_ms"]) == set(bop.LAYOUTS) and all(v > 0 for v in row["p50_ms"].values())
    md = bop.format_md({"machine": {"cpu": "x", "cores": 2, "jax": "j", "load_average_1m": 0.0}, "repeats": 1,
                        "rows": {"one device, two cores": row}})
    assert md.count("\n| one device") == 2 and "(1.00×)" in md   # the two-body table and the copies table
    assert set(row["copies"]) == set(bop.COPIES) and "8 copies: one graph" in md
