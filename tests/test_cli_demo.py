"""`tignn demo` (tignn_jax.cli.demo): bad input is one line without a traceback, the help names every option, and a
small run writes its GIF, timings and fingertip track."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tignn_jax import cli
from tignn_jax.api import shipped_models
from tignn_jax.cli import demo


def _all_cpus() -> str:
    # every CPU this process may use: `--cores` then pins nothing (JAX has already started in the test process)
    return str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1)


@pytest.mark.parametrize("argv, names", [
    (["--model", "no-such-model"], ["'no-such-model'", *shipped_models()]),
    (["--frames", "1"], ["--frames", "1"]),
    (["--size", "big"], ["--size", "'big'"]),
    (["--stand-in", "--model", "beam"], ["--stand-in", "--model beam"]),
    (["--track", "no-such-track.jsonl"], ["--track", "no-such-track.jsonl"]),
])
def test_bad_options_are_one_line_naming_the_value_and_exit_2(argv, names, tmp_path, capsys):
    assert cli.main(["demo", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("tignn demo: error: ")
    assert all(name in err for name in names), err
    assert not (tmp_path / "out").exists()   # refused before anything is written


def test_the_tignn_process_exits_2_on_an_unknown_model_without_a_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "tignn_jax.cli", "demo", "--model", "no-such-model", "--out",
                           str(tmp_path)], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"tignn demo: error: --model 'no-such-model': no such model; shipped models: {', '.join(shipped_models())} "
        "(or a model folder or .npz file, or 'fem-newton')"]


def test_a_model_on_another_mesh_is_refused_in_one_line(tmp_path, capsys):
    assert cli.main(["demo", "--scene", "bunny", "--model", "beam", "--frames", "2", "--cores", _all_cpus(),
                     "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "'beam'" in err and "mesh" in err


def test_help_lists_every_option_with_its_help(capsys):
    parser = cli.build_parser()
    with pytest.raises(SystemExit) as done:
        parser.parse_args(["demo", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    sub = next(a for a in parser._actions if a.dest == "command").choices["demo"]
    assert sub.description and " ".join(sub.description.split()) in text
    options = [a for a in sub._actions if a.option_strings and a.dest != "help"]
    assert {a.dest for a in options} >= {"scene", "out", "frames", "size", "model", "track", "stand_in", "cores"}
    for action in options:
        assert action.help and len(action.help) > 10, action.dest
        assert action.option_strings[0] in text
        assert " ".join(action.help.split("(default")[0].split())[:30] in text, action.dest


def test_small_run_of_the_default_beam_writes_gif_timings_and_track(tmp_path, capsys):
    assert cli.main(["demo", "--scene", "beam", "--frames", "3", "--size", "128x96", "--cores", _all_cpus(),
                     "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "beam_timings.json").read_text())
    assert summary["dynamics"] == "model beam-corot" and summary["image"] == [128, 96]
    assert summary["frames"] == 2 and summary["guard_trips"] == 0 and summary["guard"] == "reset"
    assert {"p50_ms", "p99_ms"} <= set(summary["render"])
    assert (tmp_path / "beam.gif").stat().st_size > 0
    assert len((tmp_path / "beam_track.jsonl").read_text().splitlines()) == 3
    assert "STAND-IN" not in out and "wrote" in out


def test_build_scene_refuses_an_unknown_scene():
    with pytest.raises(ValueError, match="'cube'"):
        demo.build_scene("cube", 2)
