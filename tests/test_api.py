"""The public API, as a user calls it: names, promises, errors."""
import ast
import inspect
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax as T
from tignn_jax import graph as G

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def beam():
    return T.load_pretrained("beam")


def tip_forces(params, scale=1.0):
    q0 = params["mesh"]["q0"]
    f = np.zeros((len(q0), 3), np.float32)
    f[q0[:, 0] > q0[:, 0].max() - 1e-3, 2] = -scale * float(params["envelope"]["f_max"][0])
    return f


def test_public_names_are_listed_and_documented():
    assert len(T.__all__) == len(set(T.__all__)) and 15 <= len(T.__all__) <= 25
    for name in T.__all__:
        obj = getattr(T, name)
        doc = inspect.getdoc(obj) or ""
        assert len(doc) > 40, f"{name} has no real docstring"
        if inspect.isfunction(obj) and len(inspect.signature(obj).parameters) > 1:
            assert "Args:" in doc or "Returns" in doc or "``fn(" in doc, f"{name}: no Args/Returns"


def test_default_model_is_the_demos_beam():
    params, graph = T.load_pretrained()
    assert isinstance(params["model"], T.CorotationalGeneric)
    assert graph.nodes["z"].shape == (756, 12)


def test_step_rollout_and_stepper_give_the_same_states(beam):
    params, graph = beam
    f = tip_forces(params)
    fn = T.stepper(params)
    z, g = graph.nodes["z"], graph
    for _ in range(3):
        z, g = fn(z, jnp.asarray(f)), T.step(params, g, f)
    states = T.rollout(params, graph, np.stack([f] * 3))
    assert np.array_equal(np.asarray(z), np.asarray(g.nodes["z"]))
    assert np.allclose(np.asarray(states[-1]), np.asarray(z), rtol=0, atol=1e-5 * float(np.abs(z).max()))
    assert float(np.abs(np.asarray(z)[:, :3] - params["mesh"]["q0"]).max()) > 0.05   # it moved


def test_each_model_steps_with_its_own_arrays_and_a_gradient_reaches_them(beam):
    # step compiles a model's arrays into its program: a model with other arrays gets its own program, and the
    # first model still steps as before; with traced arrays (a gradient with respect to them) it takes them as
    # arguments
    import jax

    params, graph = beam
    f = tip_forces(params)
    q0 = np.asarray(params["mesh"]["q0"])
    z1 = np.asarray(T.step(params, graph, f).nodes["z"])

    def scaled(s):
        return {**params, "arrays": {**params["arrays"], "ainv": params["arrays"]["ainv"] * s}}

    z2 = np.asarray(T.step(scaled(0.5), graph, f).nodes["z"])
    assert np.abs(z2[:, :3] - q0).max() < 0.9 * np.abs(z1[:, :3] - q0).max()
    assert np.array_equal(np.asarray(T.step(params, graph, f).nodes["z"]), z1)

    def drop(s):
        return jnp.sum(T.step(scaled(s), graph, f).nodes["z"][:, 2] - q0[:, 2])

    g, fd = float(jax.grad(drop)(1.0)), float((drop(1.1) - drop(0.9)) / 0.2)
    assert abs(g - fd) <= 1e-3 * abs(fd) and abs(fd) > 0


def test_stepper_inside_a_callers_jit_and_scan_steps_as_at_the_top_level(beam):
    # the frame is compiled with its own compiler options only where it is called at the top level; inside a
    # user's jit or scan (where JAX refuses them) it becomes part of the user's program and steps the same
    import jax

    params, graph = beam
    f = jnp.asarray(tip_forces(params))
    fn = T.stepper(params)
    top = fn(fn(graph.nodes["z"], f), f)
    twice = jax.jit(lambda z: fn(fn(z, f), f))(graph.nodes["z"])
    scanned = jax.lax.scan(lambda z, _: (fn(z, f), None), graph.nodes["z"], None, length=2)[0]
    # float32 round-off of another program's summation order: 1e-3 of each column's largest value (the stress
    # readout's sums are the most sensitive, a few 1e-4; positions a few 1e-7)
    scale = np.abs(np.asarray(top)).max(axis=0)
    for z in (twice, scanned):
        assert np.all(np.abs(np.asarray(z) - np.asarray(top)).max(axis=0) <= 1e-3 * scale)
    assert T.api.FRAME_COMPILER_OPTIONS in ({}, {"xla_cpu_experimental_ynn_fusion_type": ""})


def test_several_bodies_step_each_as_alone(beam):
    params, graph = beam
    f = tip_forces(params)
    two = G.batch([graph, graph])
    out = np.asarray(T.step(params, two, np.concatenate([f, 0.5 * f])).nodes["z"])
    one = np.asarray(T.step(params, graph, f).nodes["z"])
    half = np.asarray(T.step(params, graph, 0.5 * f).nodes["z"])
    # other programs than the single body's: float32 round-off of their summation order, within 1e-4 of each
    # column's largest value (as in test_stepper_inside_a_callers_jit_and_scan_steps_as_at_the_top_level)
    tol = 1e-4 * np.abs(one).max(axis=0)
    assert np.all(np.abs(out[:756] - one) <= tol) and np.all(np.abs(out[756:] - half) <= tol)
    fn = T.stepper(params, copies=2)
    assert np.all(np.abs(np.asarray(fn(two.nodes["z"], jnp.asarray(np.concatenate([f, 0.5 * f])))) - out) <= tol)


def test_a_batched_rest_graph_is_known_by_its_arrays_and_any_other_checked_by_value(beam, monkeypatch):
    # step checks a several-body graph's edges against the mesh: rest_graph's own arrays (and the graphs step
    # returns, which carry them) at once, an equal graph built otherwise by value, a wrong one is refused
    params, graph = beam
    two = T.rest_graph(params, 2)
    f = np.zeros((2 * 756, 3), np.float32)
    calls, real = [], np.array_equal
    monkeypatch.setattr(np, "array_equal", lambda *a, **k: calls.append(1) or real(*a, **k))
    after = T.step(params, T.step(params, two, f), f)
    assert not calls and after.senders is two.senders      # known by identity: nothing compared
    T.step(params, G.batch([graph, graph]), f)             # the same edges in other arrays: compared
    assert calls
    monkeypatch.undo()
    wrong = two._replace(senders=jnp.roll(two.senders, 1))
    with pytest.raises(ValueError, match="edges of the model's mesh"):
        T.step(params, wrong, f)


def test_non_finite_forces_are_refused_and_huge_finite_ones_are_not(beam):
    # the finiteness check reads a sum of squares first: a NaN or an infinity anywhere (in the float32 forces a
    # real-time loop hands over, in float64, in a jax array, in a sequence) is refused; finite forces whose squares
    # overflow float32 are still accepted
    params, graph = beam
    for bad_value in (np.nan, np.inf, -np.inf):
        for dtype in (np.float32, np.float64):
            bad = np.zeros((756, 3), dtype)
            bad[700, 2] = bad_value
            with pytest.raises(ValueError, match="forces contains NaN or infinite values"):
                T.step(params, graph, bad)
            with pytest.raises(ValueError, match="forces contains NaN or infinite values"):
                T.step(params, graph, jnp.asarray(bad))
    seq = np.zeros((3, 756, 3), np.float32)
    seq[2, 5, 0] = np.nan
    with pytest.raises(ValueError, match="forces_seq contains NaN or infinite values"):
        T.rollout(params, graph, seq)
    huge = np.zeros((756, 3), np.float32)
    huge[:3] = 1e30                       # Σ f² overflows float32; every entry is finite
    assert T.step(params, graph, huge).nodes["z"].shape == (756, 12)


def test_bad_input_is_named(beam):
    params, graph = beam
    with pytest.raises(ValueError, match=r"forces has shape \[756, 2\]"):
        T.step(params, graph, np.zeros((756, 2)))
    bad = np.zeros((756, 3))
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        T.step(params, graph, bad)
    with pytest.raises(ValueError, match=r"forces_seq has shape \[756, 3\]"):
        T.rollout(params, graph, np.zeros((756, 3)))
    other = G.from_state(np.zeros((10, 12)), np.array([[0, 1], [1, 0]]), np.zeros(10))
    with pytest.raises(ValueError, match="756 nodes"):
        T.step(params, other, np.zeros((10, 3)))
    shuffled = graph._replace(senders=graph.receivers, receivers=graph.senders + 0)
    shuffled = shuffled._replace(senders=jnp.roll(shuffled.senders, 1))
    with pytest.raises(ValueError, match="edges of the model's mesh"):
        T.step(params, shuffled, np.zeros((756, 3)))
    with pytest.raises(ValueError, match="copies must be a positive integer, got 0"):
        T.stepper(params, copies=0)
    with pytest.raises(ValueError, match="stepper takes z"):
        T.stepper(params)(jnp.zeros((10, 12)), jnp.zeros((10, 3)))
    with pytest.raises(ValueError, match="no model named 'no-such-model'; shipped models"):
        T.load_pretrained("no-such-model")


def test_a_saved_model_loads_as_it_was(tmp_path, beam):
    params, graph = beam
    path = T.save_model(params, tmp_path / "m" / "model.npz", info={"note": "copy"})
    again, g2 = T.load_pretrained(str(path.parent))
    assert again["model"] == params["model"] and again["info"] == {"note": "copy"}
    f = tip_forces(params)
    assert np.array_equal(np.asarray(T.step(again, g2, f).nodes["z"]), np.asarray(T.step(params, graph, f).nodes["z"]))


def test_a_file_that_is_no_model_is_refused(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a tignn-jax model file"):
        T.load_model(tmp_path / "x.npz")


def _imports(path: Path, package: str) -> set[str]:
    """Modules of this project that a file imports anywhere (function-level imports included)."""
    tree = ast.parse(path.read_text())
    parts = path.relative_to(ROOT).with_suffix("").parts
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = parts[:-node.level] if parts[-1] != "__init__" else parts[:len(parts) - node.level + 1]
                base = ".".join(pkg) + ("." + base if base else "")
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return {m for m in out if m.split(".")[0] in ("tignn_jax", "fem")}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_cycles_and_data_flows_from_fem_to_tignn_jax():
    files = sorted((ROOT / "tignn_jax").rglob("*.py")) + sorted((ROOT / "fem").rglob("*.py"))
    modules = {_module_name(p): p for p in files}
    graph = {}
    for name, path in modules.items():
        deps = set()
        for imp in _imports(path, name):
            while imp and imp not in modules:
                imp = imp.rpartition(".")[0]
            if imp and imp != name and not name.startswith(imp + "."):   # a package's own __init__ is no cycle
                deps.add(imp)
        graph[name] = deps
    assert not [m for m in graph if m.startswith("fem") and any(d.startswith("tignn_jax") for d in graph[m])]
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for d in graph[m]:
            if state.get(d) == "open":
                raise AssertionError(f"import cycle: {' -> '.join(stack[stack.index(d):] + [d])}")
            if d not in state:
                visit(d, stack + [d])
        state[m] = "done"

    for m in graph:
        if m not in state:
            visit(m, [m])


def test_library_docstrings_say_what_not_history():
    # docstrings carry what and why; sessions, this machine's timings and result files belong to docs/ and
    # benchmarks/results/
    for path in sorted((ROOT / "tignn_jax").rglob("*.py")) + sorted((ROOT / "fem").rglob("*.py")):
        text = path.read_text()
        for word in ("session", "benchmarks/results", "lab_notes", "this machine", "this CPU", "this 2-core"):
            assert word.lower() not in text.lower(), f"{path.relative_to(ROOT)} mentions {word!r}"
