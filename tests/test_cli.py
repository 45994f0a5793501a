"""The `tignn` command as a user runs it: help on everything, one-line errors, a tiny model end to end."""
import argparse
import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from tignn_jax.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def _parsers(parser, path=("tignn",)):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, path + (name,))


def test_every_subcommand_has_a_description_and_every_option_a_help_line():
    found = list(_parsers(build_parser()))
    names = {" ".join(p) for p, _ in found}
    assert {"tignn train", "tignn evaluate", "tignn rollout", "tignn demo", "tignn fem-example",
            "tignn generate bunny", "tignn generate beam-reference", "tignn generate two-beams"} <= names
    for path, parser in found[1:]:
        assert parser.description, f"{' '.join(path)} has no description"
        for action in parser._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"{' '.join(path)} {action.option_strings} has no help"


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    """A data file of a 4×1×1 hex bar clamped at x = 0, made by a hidden linear GENERIC model under tip loads
    (`test_train_linear.synthetic`), with train / val / test splits."""
    from test_train_linear import bar, synthetic

    jax.config.update("jax_enable_x64", True)
    try:
        return synthetic(tmp_path_factory.mktemp("data"), *bar("hex"), cases=6,
                         splits={"train": [1, 2, 3, 4], "val": [5], "test": [6]})
    finally:
        jax.config.update("jax_enable_x64", False)


@pytest.mark.long   # CI time: tests/test_user_mesh.py runs generate → train linear → evaluate → rollout
def test_a_tiny_linear_model_trains_evaluates_and_rolls_out(tmp_path, tiny_data, capsys):
    run = tmp_path / "run"
    assert main(["train", "--config", str(ROOT / "configs" / "tiny_linear.py"), "--data", str(tiny_data),
                 "--run-dir", str(run), "--no-progress"]) == 0
    model = run / "model" / "model.npz"
    assert model.exists()
    assert main(["evaluate", "--model", str(model.parent), "--data", str(tiny_data), "--splits", "val,test",
                 "--no-structure", "--out", str(tmp_path / "eval")]) == 0
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert np.isfinite(report["test"]["all"]["u"]["mean"])
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["train_loss"] < records[0]["train_loss"]     # six Adam steps already fit better
    assert main(["rollout", "--model", str(model), "--data", str(tiny_data), "--sims", "6",
                 "--out", str(tmp_path / "r.npz")]) == 0
    with np.load(tmp_path / "r.npz") as r:
        assert r["z"].shape == (1, 6, 20, 12) and r["sim_id"].tolist() == [6]


@pytest.mark.parametrize("argv,message", [
    (["train", "--config", "no/such/recipe.py", "--data", "x.npz", "--run-dir", "r"], "no recipe file"),
    (["evaluate", "--data", "no-such.npz"], "--data no-such.npz: no such file"),
    (["evaluate", "--model", "no-such-model", "--data", "x.npz"], "no model named 'no-such-model'"),
    (["generate", "bunny", "--out", "x.npz", "--cases", "0"], "--cases must be positive, got 0"),
    (["generate", "bunny", "--out", "x.npz", "--worker", "3/2"], "--worker must be K/N"),
    (["generate", "beam-reference", "--out", "x.npz", "--damping", "-1"], "--damping must be a finite number >= 0"),
    (["generate", "beam-reference", "--out", "x.npz", "--damping", "nan"], "--damping must be a finite number >= 0"),
    (["generate", "beam-reference", "--out", "x.npz", "--density", "0"], "--density"),
    (["generate", "two-beams", "--out", "x.npz", "--integrator", "implicit"],
     "--integrator implicit on two-beams: implicit dynamics does not support contact"),
    (["generate", "bunny", "--out", "x.npz", "--loads-per-case", "0"], "--loads-per-case must be >= 1, got 0"),
    (["generate", "bunny", "--out", "x.npz", "--exclude-loads-of", "y.npz"],
     "--exclude-loads-of applies only with --loads-per-case > 1"),
    (["generate", "bunny", "--out", "x.npz", "--load-nodes", "3,4", "--loads-per-case", "2"],
     "--load-nodes cannot be combined"),
    (["generate", "bunny", "--out", "x.npz", "--load-radius", "5", "--loads-per-case", "2"],
     "--load-radius applies only to single-load"),
    (["generate", "beam-reference", "--out", "x.npz", "--newton-iterations", "0", "--integrator", "implicit"],
     "--newton-iterations must be positive, got 0"),
    (["generate", "beam-reference", "--out", "x.npz", "--newton-iterations", "30"],
     "--newton-iterations applies only with --integrator"),
    (["generate", "bunny", "--out", "x.npz", "--cases", "1", "--rise-frames", "-3"],
     "--rise-frames must be in 0..20, got -3"),
    (["generate", "bunny", "--out", "x.npz", "--cases", "1", "--load-radius", "-1"],
     "--load-radius must be a finite number >= 0, got -1.0"),
    (["generate", "two-beams", "--out", "x.npz", "--cases", "100"], "--cases 100: the two-beams scene has 6 cases"),
])
def test_bad_input_is_one_line_and_exit_code_2(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not Path("x.npz").exists()


@pytest.mark.parametrize("argv,message", [
    (["demo", "--frames", "abc"], "tignn demo: error: argument --frames: invalid int value: 'abc'"),
    (["generate", "bunny"], "tignn generate bunny: error: the following arguments are required: --out"),
    (["generate", "beam-reference", "--out", "x.npz", "--seed", "3"], "unrecognized arguments: --seed 3"),
])
def test_argument_errors_are_one_line_and_exit_code_2(argv, message, capsys):
    # argparse's own errors too: one line naming the option and where the help is, no usage block
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and message in err and len(err.splitlines()) == 1 and "--help" in err, err


RECIPE = str(ROOT / "configs" / "tiny_gnn.py")


@pytest.mark.parametrize("argv,message", [
    (["track", "--mediapipe", "nohand.jsonl", "--size", "64x48", "--focal", "50", "--out", "."], ".: Is a directory"),
    (["track", "--mediapipe", "list.jsonl", "--size", "64x48", "--focal", "50", "--out", "t.jsonl"],
     "list.jsonl:1: not a hand record (a JSON list, not an object)"),
    (["track", "--mediapipe", "empty.jsonl", "--size", "64x48", "--focal", "inf", "--out", "t.jsonl"],
     "--focal must be a positive number, got inf"),
    (["demo", "--scene", "beam", "--stand-in", "--frames", "2", "--track", "list.jsonl", "--out", "o"],
     "list.jsonl:1: not a track record (a JSON list, not an object)"),
    (["demo", "--scene", "beam", "--stand-in", "--frames", "2", "--track", "empty.jsonl", "--out", "o"],
     "empty.jsonl: no track records (an empty file)"),
    (["track", "--mediapipe", "empty.jsonl", "--size", "64x48", "--focal", "50", "--out", "t.jsonl"],
     "empty.jsonl: no hand records (an empty file)"),
    (["train", "--config", "syntax.py", "--data", "d.npz", "--run-dir", "r"],
     "cannot run the recipe (SyntaxError: '(' was never closed"),
    (["train", "--config", RECIPE, "--data", "d.npz", "--run-dir", "r", "--set", "lr=abc"],
     "lr must be a positive number, got 'abc'"),
    (["train", "--config", RECIPE, "--data", "d.npz", "--run-dir", "r", "--set", "epochs=0"],
     "--set epochs=0: epochs must be a positive integer, got 0"),
    (["train", "--config", "linear", "--data", "text.txt", "--run-dir", "r"], "--data text.txt: not a data file"),
    (["demo", "--scene", "beam", "--model", "text.txt", "--out", "o"],
     "text.txt is not a tignn-jax model file (not a .npz archive)"),
    (["demo", "--scene", "beam", "--model", "noconfig.npz", "--out", "o"],
     "noconfig.npz is not a tignn-jax model file (its 'model' entry names no class and config)"),
    (["generate", "bunny", "--out", "x.npz", "--loads-per-case", "2", "--exclude-loads-of", "d.npz"],
     "--exclude-loads-of d.npz: not a generated bunny data set"),
])
def test_bad_files_and_paths_are_one_line_and_exit_code_2(argv, message, capsys, tmp_path, monkeypatch):
    # a file of the wrong kind or content, or a path that cannot be written, is named in one line (no traceback)
    monkeypatch.chdir(tmp_path)
    Path("text.txt").write_text("hello\n")
    Path("empty.jsonl").write_text("")
    Path("nohand.jsonl").write_text('{"frame": 0, "hands": []}\n')
    Path("list.jsonl").write_text("[1, 2, 3]\n")
    Path("syntax.py").write_text("CONFIG = (\n")
    np.savez("d.npz", x=np.zeros(1))
    np.savez("noconfig.npz", model=np.array('{"class": "linear"}'))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not Path("x.npz").exists() and not Path("r").exists()


def test_a_bunny_option_on_another_scene_is_not_an_option_there(capsys):
    # each scene's subcommand has only its own options: argparse names the stray one and exits with 2
    with pytest.raises(SystemExit) as stop:
        main(["generate", "beam-reference", "--out", "x.npz", "--load-radius", "5"])
    assert stop.value.code == 2 and "unrecognized arguments: --load-radius 5" in capsys.readouterr().err


def test_a_split_the_data_lack_is_named(tiny_data, capsys):
    assert main(["evaluate", "--model", "beam", "--data", str(tiny_data), "--splits", "nope"]) == 2
    assert "--splits: ['nope'] not in the data file" in capsys.readouterr().err


def test_a_model_of_another_mesh_is_refused(tiny_data, capsys):
    assert main(["rollout", "--model", "beam", "--data", str(tiny_data), "--sims", "test", "--out", "x.npz"]) == 2
    assert "another mesh" in capsys.readouterr().err


def test_help_and_usage_errors_do_not_load_jax():
    # `tignn --help`, a subcommand's help and argparse's usage errors answer before JAX is imported (it takes
    # seconds to load); the package's public names load on first use
    code = ("import sys\nfrom tignn_jax.cli import main\nimport tignn_jax\n"
            "for argv in (['--help'], ['demo', '--help'], ['demo', '--frames', 'x']):\n"
            "    try:\n        main(argv)\n    except SystemExit as e:\n        assert e.code in (0, 2), e.code\n"
            "print('jax' in sys.modules, tignn_jax.DEFAULT_MODEL)\n"
            "tignn_jax.step\nprint('jax' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[-3:] == ["False beam-corot", "True", ""], out.stdout
    assert "invalid int value: 'x'" in out.stderr


def test_debug_shows_the_traceback():
    out = subprocess.run([sys.executable, "-m", "tignn_jax.cli", "--debug", "evaluate", "--data", "no-such.npz"],
                         capture_output=True, text=True)
    assert out.returncode != 0 and "Traceback" in out.stderr


def test_a_tiny_graph_network_trains_by_the_cli(tmp_path, tiny_data):
    run = tmp_path / "gnn"
    assert main(["train", "--config", str(ROOT / "configs" / "tiny_gnn.py"), "--data", str(tiny_data),
                 "--run-dir", str(run), "--no-progress"]) == 0
    import tignn_jax as T

    params, graph = T.load_pretrained(str(run / "model"))
    assert isinstance(params["model"], T.GenericGNN)
    z = T.rollout(params, graph, np.zeros((3, 20, 3), np.float32))
    assert np.all(np.isfinite(np.asarray(z)))
