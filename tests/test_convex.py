"""The convex GENERIC model (``ModelConfig(convex=True)``, ``tignn_jax.convex``): static brackets that couple
neighbours and stay skew / PSD, convex E and concave S with their extremum at rest, the free-energy form, the
cache of the static part, saving, and a tiny training run."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import api
from tignn_jax import convex as CV
from tignn_jax import data as D
from tignn_jax import model as M
from tignn_jax import train as T
from test_model import _assert_gradients_match_finite_differences

CONVEX = M.ModelConfig(hidden=8, mlp_layers=2, convex=True)
FREE = CONVEX._replace(free_energy=True)
DYN = FREE._replace(dynamic_l=True)


pytestmark = pytest.mark.slow   # a research branch's checks: `pytest -m slow` (not in the default run)


@pytest.fixture(scope="module")
def bar():
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=3, frames=4)
    norm = {k: jnp.asarray(v) for k, v in D.normalization(data, D.split_rows(data, "train")).items()}
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), q0=data.q0)
    nt = jnp.asarray(data.node_type, jnp.int32)
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    weights = {c: M.init_weights(jax.random.PRNGKey(1), c, norm, z, f, nt, topo) for c in (CONVEX, FREE, DYN)}
    gate = weights[DYN]["bracket_gate"]["layer1"]   # zero at initialisation (the static brackets): perturb it
    gate["w"] = jax.random.normal(jax.random.PRNGKey(2), gate["w"].shape) * 0.5
    rest = jnp.concatenate([topo.x0, jnp.zeros((len(data.q0), 9))], axis=1)
    return dict(data=data, norm=norm, topo=topo, nt=nt, z=z, f=f, weights=weights, rest=rest)


def _args(bar, config, z=None, f=None):
    return (bar["weights"][config], config, bar["norm"], bar["z"] if z is None else z,
            bar["f"] if f is None else f, bar["nt"], bar["topo"])


@pytest.mark.parametrize("config", [CONVEX, FREE], ids=["convex", "free_energy"])
def test_brackets_are_skew_and_psd_couple_neighbours_and_do_not_depend_on_the_state(bar, config):
    big_l, big_m = (np.asarray(a, np.float64) for a in M.dense_operators(*_args(bar, config)))
    scale_l, scale_m = np.abs(big_l).max(), np.abs(big_m).max()
    assert scale_l > 0 and scale_m > 0
    assert np.abs(big_l + big_l.T).max() <= 1e-6 * scale_l
    assert np.abs(big_m - big_m.T).max() <= 1e-6 * scale_m
    assert np.linalg.eigvalsh(big_m).min() >= -1e-6 * scale_m
    # entries between different nodes: the edge blocks of L and M are there
    n = big_l.shape[0] // M.STATE_DIM
    off = ~np.kron(np.eye(n, dtype=bool), np.ones((M.STATE_DIM, M.STATE_DIM), bool))
    assert np.abs(big_l[off]).max() > 1e-3 * scale_l and np.abs(big_m[off]).max() > 1e-3 * scale_m
    # the clamped nodes' q and v are prescribed: their rows and columns are zero (P L P, P M P)
    fixed = np.asarray(M.prescribed(bar["nt"])).reshape(-1)
    assert fixed.any() and not np.abs(big_l[fixed]).any() and not np.abs(big_l[:, fixed]).any()
    assert not np.abs(big_m[fixed]).any() and not np.abs(big_m[:, fixed]).any()
    # static: the same operators at another state under another force
    other_l, other_m = M.dense_operators(*_args(bar, config, z=bar["rest"], f=jnp.zeros_like(bar["f"])))
    np.testing.assert_array_equal(np.asarray(other_l, np.float64), big_l)
    np.testing.assert_array_equal(np.asarray(other_m, np.float64), big_m)
    with pytest.raises(ValueError, match="dense_operators"):
        M.operators(*_args(bar, config))


@pytest.mark.parametrize("config", [CONVEX, FREE], ids=["convex", "free_energy"])   # (dynamic_l: FREE's F)
def test_energy_is_convex_and_entropy_concave_along_lines(bar, config):
    w, _, norm, z, f, nt, topo = _args(bar, config)
    potentials = jax.jit(jax.vmap(lambda zz: M.energy_entropy(w, config, norm, zz, f, nt, topo)))
    rng = np.random.default_rng(0)
    ts = jnp.linspace(-4.0, 4.0, 33)
    for _ in range(4):
        d = jnp.asarray(rng.normal(size=z.shape), jnp.float32) * norm["z_std"]
        vals = np.asarray(potentials(z[None] + ts[:, None, None] * d[None]), np.float64)
        second = vals[2:] - 2 * vals[1:-1] + vals[:-2]
        tol = 1e-4 * np.abs(vals).max()
        assert second[:, 0].min() >= -tol and second[:, 1].max() <= tol
        if config.free_energy:
            np.testing.assert_allclose(vals[:, 1], -vals[:, 0])


@pytest.mark.parametrize("config", [CONVEX, FREE, DYN], ids=["convex", "free_energy", "dynamic_l"])
def test_rest_is_the_extremum_of_the_potentials_and_a_fixed_point(bar, config):
    zero = jnp.zeros_like(bar["f"])
    rt = M.rates(*_args(bar, config, z=bar["rest"], f=zero))
    assert float(jnp.abs(rt.grad_e).max()) < 1e-5 and float(jnp.abs(rt.grad_s).max()) < 1e-5
    moved = M.step_state(*_args(bar, config, z=bar["rest"], f=zero)) - bar["rest"]
    assert float(jnp.abs(moved).max()) <= 1e-6 * float(jnp.abs(bar["rest"]).max())
    es = M.energy_entropy(*_args(bar, config, z=bar["rest"], f=zero))
    others = M.energy_entropy(*_args(bar, config))
    assert float(others[0]) >= float(es[0]) and float(others[1]) <= float(es[1])


@pytest.mark.parametrize("config", [CONVEX, FREE, DYN], ids=["convex", "free_energy", "dynamic_l"])
def test_gradients_match_finite_differences(bar, config):
    _assert_gradients_match_finite_differences(*_args(bar, config))


@pytest.mark.parametrize("config", [FREE, DYN], ids=["free_energy", "dynamic_l"])
def test_free_energy_form_produces_entropy_without_forces_or_clamps(bar, config):
    # dz/dt = (L − M)∇F: with no port and no clamped rows, ∇Sᵀ dw = ∇Fᵀ M ∇F ≥ 0 exactly (L(z) skew or not)
    w, _, norm, z, _, _, topo = _args(bar, config)
    free_nodes = jnp.zeros_like(bar["nt"])
    rt = M.rates(w, config, norm, z, jnp.zeros_like(bar["f"]), free_nodes, topo)
    assert float(rt.dissipation) > 0
    np.testing.assert_allclose(float(rt.entropy_rate), float(rt.dissipation), rtol=1e-4)


@pytest.mark.parametrize("config", [FREE, DYN], ids=["free_energy", "dynamic_l"])
def test_free_energy_rest_linearisation_is_damped_and_rk4_keeps_it(bar, config):
    """Linearised at rest, the free-energy form's rate (L − M)∇²F has eigenvalues with real part ≤ 0 (the
    model's continuous-time stability, clamps included); with the step scaled so that its stiffest mode sits at
    |λΔt| = 2.5, RK4's step at rest contracts every mode (|R(λΔt)| < 1), where forward Euler's grows along some
(this random model's spectrum is nearly imaginary: an undamped oscillator, which Euler amplifies)."""
    w, config, norm, _, _, nt, topo = _args(bar, config)
    shape, s = bar["rest"].shape, M.state_scale(norm)
    rate = lambda zf: (M._generic(w, config, norm, zf.reshape(shape), jnp.zeros_like(bar["f"]), nt, topo)[0]
                       * s).reshape(-1)
    jac = np.asarray(jax.jacrev(rate)(bar["rest"].reshape(-1)), np.float64)
    lam = np.linalg.eigvals(jac)
    radius = np.abs(lam).max()
    assert radius > 0 and lam.real.max() <= 1e-4 * radius
    x = lam * (2.5 / radius)
    euler, rk4 = np.abs(1 + x), np.abs(1 + x + x ** 2 / 2 + x ** 3 / 6 + x ** 4 / 24)
    assert rk4.max() <= 1 + 1e-4 and rk4[np.abs(x) > 0.5].max() < 0.999   # the clamped entries' zero modes: 1
    assert euler.max() > 1.05


def _stiff_rk4(bar, reach):
    """The free-energy model's RK4 step with its rate scaled so that the rest linearisation's stiffest mode sits
    at |λΔt| = ``reach`` (a step that many times longer), and F."""
    w, _, norm, z, f, nt, topo = _args(bar, FREE)
    rk4 = FREE._replace(integrator="rk4")
    shape, s = bar["rest"].shape, M.state_scale(norm)
    rate = lambda zf: (M._generic(w, rk4, norm, zf.reshape(shape), jnp.zeros_like(f), nt, topo)[0] * s).reshape(-1)
    k = reach / np.abs(np.linalg.eigvals(np.asarray(jax.jacrev(rate)(bar["rest"].reshape(-1)), np.float64))).max()
    scaled = lambda f_: lambda x: (lambda o: (k * o[0],) + o[1:])(M._generic(w, rk4, norm, x, f_, nt, topo))
    relaxed = rk4._replace(relaxation=True)
    gamma = lambda z_, f_, dw, st: CV.relaxation(w, relaxed, norm, z_, k * f_, dw, st, nt, topo)
    energy = lambda z_: M.energy_entropy(w, rk4, norm, z_, f, nt, topo)[0]
    return scaled, gamma, energy, s


def test_relaxation_keeps_the_discrete_second_law_and_leaves_accurate_steps_alone(bar):
    """The limited relaxation step z + γΔz: γ = 1 for a short step (the RK4 step unchanged), and for steps
    beyond RK4's stability region γ < 1 with F(z + γΔz) − F(z) ≤ γW (W: the forces' positive work over the
    stages), γ
    the largest such value to the bisection's resolution. Left alone without forces from a loaded state, the
    unlimited stiff step creates free energy and the limited one never does; two sub-steps of the same long
    step keep the dynamics inside RK4's region (γ = 1 throughout, F falling)."""
    z, f = bar["z"], bar["f"]
    tol = 1e-5
    for reach, short in ((0.05, True), (6.0, False), (12.0, False)):
        scaled, gamma, energy, s = _stiff_rk4(bar, reach)
        dw, stages = M.runge_kutta("rk4", scaled(f), z, s)
        g = float(gamma(z, f, dw, stages))
        port = CV._static(bar["weights"][FREE], FREE, bar["norm"], bar["nt"], bar["topo"])["convex_heads"]
        force = jnp.where(M.prescribed(bar["nt"]), 0.0, M.force_term(port[:, M.N_L + M.N_M:], f, bar["norm"]))
        work = max(float(sum(c * jnp.sum(o[1] * force) for c, o in zip(M.TABLEAUS["rk4"][1], stages))), 0.0)
        r = lambda t: float(energy(z + t * dw * s) - energy(z))
        scale_f = abs(float(energy(z))) + abs(work)
        assert r(g) <= g * work + tol * scale_f
        if short:
            assert g == 1.0
        else:
            assert g < 1.0
            above = min(g + 2.0 ** (1 - CV.RELAX_ITERS), 1.0)
            assert r(above) > above * work   # the largest admissible γ to the bisection's resolution
    scaled, gamma, energy, s = _stiff_rk4(bar, 4.0)
    none = jnp.zeros_like(f)

    def roll(limited, substeps=1):
        limit = (lambda z_, dw, st: gamma(z_, none, dw, st)) if limited else None
        one = jax.jit(lambda z_: z_ + M.runge_kutta("rk4", scaled(none), z_, s, substeps=substeps,
                                                        limit=limit)[0] * s)
        zs = [z]
        for _ in range(40):
            zs.append(one(zs[-1]))
        return np.array([float(energy(x)) for x in zs])

    free, limited, sub = roll(False), roll(True), roll(False, substeps=2)
    assert np.nanmax(free[1:]) > 1e3 * free[0]                       # the long step creates free energy
    assert (np.diff(limited) <= tol * limited[0]).all()                # the limited one never does
    assert (np.diff(sub) <= tol * sub[0]).all() and sub[-1] < 0.5 * sub[0]


def test_dynamic_l_is_skew_at_every_state_and_turns_with_it(bar):
    """With dynamic_l, L(z) is skew-symmetric at every state with the clamped rows and columns zero, differs
    between two states, and M stays static; an untrained model (zero gates) has the static model's L."""
    big = lambda z: tuple(np.asarray(a, np.float64) for a in M.dense_operators(*_args(bar, DYN, z=z)))
    (l_a, m_a), (l_b, m_b) = big(bar["z"]), big(bar["rest"])
    for l_op in (l_a, l_b):
        assert np.abs(l_op + l_op.T).max() <= 1e-6 * np.abs(l_op).max()
    fixed = np.asarray(M.prescribed(bar["nt"])).reshape(-1)
    assert not np.abs(l_a[fixed]).any() and not np.abs(l_a[:, fixed]).any()
    assert np.abs(l_a - l_b).max() > 1e-3 * np.abs(l_a).max()
    np.testing.assert_array_equal(m_a, m_b)
    w, _, norm, z, f, nt, topo = _args(bar, DYN)
    untrained = M.init_weights(jax.random.PRNGKey(1), DYN, norm, z, f, nt, topo)
    static_l, _ = M.dense_operators(bar["weights"][FREE], FREE, norm, z, f, nt, topo)
    np.testing.assert_allclose(np.asarray(M.dense_operators(untrained, DYN, norm, z, f, nt, topo)[0]),
                               np.asarray(static_l), rtol=1e-6, atol=1e-7)


def test_cached_static_part_and_a_saved_model_step_the_same(bar, tmp_path):
    w, config, norm, z, f, nt, topo = _args(bar, CONVEX)
    cached = M.with_rest(w, config, norm, nt, topo)
    assert {"convex_c", "convex_p", "convex_a"} <= set(cached)
    direct = M.step_state(w, config, norm, z, f, nt, topo)
    np.testing.assert_array_equal(np.asarray(M.step_state(w, config, cached, z, f, nt, topo)), np.asarray(direct))
    data = bar["data"]
    params = api.make_params(config, {k: np.asarray(v) for k, v in norm.items()}, w, data.q0, data.edges,
                             data.node_type)
    loaded, graph = api.load_pretrained(str(api.save_model(params, tmp_path / "model.npz")))
    graph = graph._replace(nodes={**graph.nodes, "z": z})
    np.testing.assert_allclose(np.asarray(api.step(loaded, graph, f).nodes["z"]), np.asarray(direct),
                               rtol=1e-6, atol=1e-6)


def test_options_it_does_not_combine_with_are_named():
    z, f, nt = jnp.zeros((2, 12)), jnp.zeros((2, 3)), jnp.zeros(2, jnp.int32)
    with pytest.raises(ValueError, match="force_port"):
        M.init_weights(jax.random.PRNGKey(0), CONVEX._replace(force_port=True), {}, z, f, nt, None)
    with pytest.raises(ValueError, match="needs convex"):
        M.init_weights(jax.random.PRNGKey(0), CONVEX._replace(convex=False, free_energy=True), {}, z, f, nt, None)
    with pytest.raises(ValueError, match="dynamic_l=True needs"):
        M.init_weights(jax.random.PRNGKey(0), CONVEX._replace(dynamic_l=True), {}, z, f, nt, None)


def test_tiny_convex_training_reduces_the_loss_and_rolls_out(bar, tmp_path):
    data = bar["data"]
    cfg = T.CONFIGS["tiny"]._replace(convex=True, free_energy=True, deg_weight=0.0, epochs=8, passes=1)
    quiet = dict(progress=False, log=lambda *a, **k: None)
    trained = T.train(data, cfg, tmp_path / "b", **quiet)
    lines = (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()
    mse = [json.loads(l)["mse"] for l in lines]
    assert mse[-1] < 0.7 * mse[0]
    best, graph = api.load_pretrained(str(tmp_path / "b" / "best" / "model.npz"))
    states = api.rollout(trained, graph, jnp.asarray(data.f[0]))
    assert np.isfinite(np.asarray(states)).all()
    assert trained["config"]["convex"] and trained["config"]["free_energy"]
    # a warm start may switch dynamic_l on: the parent's weights are kept, the gates start at zero, so the
    # untrained child steps as its parent (the run folder's best model)
    child = T.train(data, cfg._replace(dynamic_l=True), tmp_path / "c", stop_after_epoch=0,
                    init_from=tmp_path / "b", **quiet)
    assert set(child["weights"]) == set(best["weights"]) | {"bracket_basis", "bracket_gate"}
    z0, f0 = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    graph = graph._replace(nodes={**graph.nodes, "z": z0})
    np.testing.assert_allclose(np.asarray(api.step(child, graph, f0).nodes["z"]),
                               np.asarray(api.step(best, graph, f0).nodes["z"]), rtol=1e-5, atol=1e-6)


def test_training_with_substeps_and_relaxation_steps_as_the_model_does(bar, tmp_path):
    """A warm start may switch on rk4 with two sub-steps and relaxation (no new weights); one epoch trains with
    the step the model is used with, and the saved model steps by that step (``step_state``)."""
    data = bar["data"]
    cfg = T.CONFIGS["tiny"]._replace(convex=True, free_energy=True, deg_weight=0.0, epochs=2, passes=1)
    quiet = dict(progress=False, log=lambda *a, **k: None)
    T.train(data, cfg, tmp_path / "p", stop_after_epoch=1, **quiet)
    child_cfg = cfg._replace(integrator="rk4", substeps=2, relaxation=True, epochs=1)
    child = T.train(data, child_cfg, tmp_path / "c", init_from=tmp_path / "p", **quiet)
    line = json.loads((tmp_path / "c" / "metrics.jsonl").read_text().splitlines()[-1])
    assert np.isfinite(line["mse"]) and np.isfinite(line["val_u"])
    model = M.ModelConfig(**child["config"])
    assert model.substeps == 2 and model.relaxation
    z0, f0 = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    _, graph = api.load_pretrained(str(tmp_path / "c" / "best" / "model.npz"))
    graph = graph._replace(nodes={**graph.nodes, "z": z0})
    np.testing.assert_allclose(
        np.asarray(api.step(child, graph, f0).nodes["z"]),
        np.asarray(M.step_state(child["weights"], model, child["norm"], z0, f0, graph.nodes["node_type"],
                                child["topo"])), rtol=1e-5, atol=1e-6)
