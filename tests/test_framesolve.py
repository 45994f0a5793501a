"""The frame_solve integrator and the linear_prior: the FEM's rest linearisation against `jax.jvp`, the W
transform and its inverse, the untrained prior model against the linear backward-Euler recurrence and the
implicit FEM, training, saving and the errors for bad use."""
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem
from fem import implicit
from fem.generate import run_cases
from fem.meshes import mesh_edges
from fem.scenes import Scene
from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import evaluate as EV
from tignn_jax import framesolve as FS
from tignn_jax import model as M
from tignn_jax import train as T

H, FRAMES, ALPHA = 0.05, 8, 2.0
MATERIAL = dict(c10=0.26, c01=0.0, d1=0.049, density=1e-3)   # the bunny's material and data density


def _scene():
    pts, cells = fem.box_hex_mesh((6.0, 2.0, 2.0), (6, 2, 2))
    cells = fem.hex_to_tet(cells)
    node_type = (pts[:, 0] < 1e-9).astype(np.int8)
    return Scene("bar", pts, cells, "tetra", mesh_edges(cells), node_type, fem.mooney_rivlin(**MATERIAL), H,
                 FRAMES, ALPHA, "linear")


def _problem(scene):
    return fem.setup(scene.points, scene.cells, material=scene.material, frame_dt=H, n_frames=FRAMES,
                     clamped=np.where(scene.node_type == 1)[0], damping=ALPHA, load_interp="linear", n_sub=1)


@pytest.fixture(scope="module")
def bar_data(tmp_path_factory):
    """Six implicit runs of a clamped tet bar under small tip loads (the linear regime), as a data-set file."""
    scene = _scene()
    problem = _problem(scene)
    rng = np.random.default_rng(0)
    tip = np.where(scene.points[:, 0] > 6.0 - 1e-9)[0]
    forces = np.zeros((6, FRAMES, len(scene.points), 3))
    ramp = np.minimum(np.arange(1, FRAMES + 1) / 4.0, 1.0)
    for c in range(6):
        forces[c][:, tip] = 2e-3 * rng.normal(size=3) * ramp[:, None, None] / len(tip)
    out = tmp_path_factory.mktemp("fs") / "bar.npz"
    run_cases(scene, problem, forces, out, progress=False, velocity="solver", integrator="implicit",
              metadata={"scene": "bar"})
    return out


def test_rest_linearization_matches_jvp():
    scene = _scene()
    problem = _problem(scene)
    lin = implicit.rest_linearization(problem, scene.material)
    norm = {k: jnp.asarray(v) for k, v in FS.norm_entries(lin).items()}
    n = len(scene.points)
    d = jnp.asarray(np.random.default_rng(1).normal(size=(n, 3)), jnp.float32)
    force = implicit._force_fn(problem.arrays, scene.material, problem.config,
                               fem.solver._hourglass_for(problem.arrays, scene.material, problem.config))
    stress = lambda u: fem.solver._nodal_stress(problem.arrays, fem.solver._element_stress(
        problem.arrays, scene.material, u, (), problem.config))
    u0 = jnp.zeros((n, 3), jnp.float32)
    k_ref = jax.jvp(force, (u0,), (d,))[1]
    s_ref = jax.jvp(stress, (u0,), (d,))[1]
    assert float(jnp.abs(FS.apply_k(norm, d) - k_ref).max()) < 1e-4 * float(jnp.abs(k_ref).max())
    assert float(jnp.abs(FS.apply_s(norm, d) - s_ref).max()) < 1e-4 * float(jnp.abs(s_ref).max())
    K = np.zeros((n, n, 3, 3))
    K[lin.k_rows, lin.k_cols] = lin.k_blocks
    K = K.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    np.testing.assert_allclose(lin.mass.sum(), MATERIAL["density"] * 6.0 * 2.0 * 2.0, rtol=1e-5)
    assert lin.alpha == ALPHA and lin.free.sum() == n - (scene.node_type == 1).sum()


@functools.lru_cache(maxsize=None)
def _ops(path):
    """(data, rest linearisation, its norm entries) of a data file; built once per file (about 7 s for the bar)
    and shared by the tests, which only read them."""
    lin = FS.operators_from_file(path)
    data = D.load(path)
    norm = {k: jnp.asarray(v, jnp.float32) for k, v in FS.norm_entries(lin).items()}
    norm["dt"] = jnp.asarray([data.dt], jnp.float32)
    return data, lin, norm


def test_solve_inverts_forward(bar_data):
    data, _, norm = _ops(bar_data)
    norm = {**norm, "fs_ainv": jnp.asarray(FS.inverse(norm, data.node_type))}
    nt = jnp.asarray(data.node_type)
    dz = jnp.asarray(np.random.default_rng(2).normal(size=(len(data.q0), 12)), jnp.float32)
    dz = dz.at[:, :6].multiply(jnp.asarray(data.node_type == 0)[:, None])   # clamped nodes keep q and v
    back = FS.solve(norm, FS.forward(norm, dz, nt), nt)
    assert float(jnp.abs(back - dz).max()) < 1e-3 * float(jnp.abs(dz).max())


def test_operator_is_what_the_inverse_inverts_and_a_factor_solve_steps_alike(bar_data):
    """``operator`` is the A₀ of the velocity solve (symmetric, identity on the clamped DOFs, A₀ A₀⁻¹ = I), and
    ``prior_step`` with ``solve_a`` = a Cholesky solve of it (the real-time benchmark's variant) is the default
    step by the product with A₀⁻¹."""
    from jax.scipy.linalg import cho_solve

    data, _, norm = _ops(bar_data)
    A = FS.operator(norm, data.node_type)
    clamped = np.repeat(data.node_type != 0, 3)
    np.testing.assert_array_equal(A[clamped][:, clamped], np.eye(int(clamped.sum())))
    assert np.abs(A[clamped][:, ~clamped]).max() == 0.0
    np.testing.assert_allclose(A, A.T, rtol=0, atol=1e-6 * np.abs(A).max())
    ainv = FS.inverse(norm, data.node_type)
    assert np.abs(A @ ainv.astype(np.float64) - np.eye(len(A))).max() < 1e-4
    norm = {**norm, "fs_ainv": jnp.asarray(ainv)}
    nt, x0 = jnp.asarray(data.node_type), jnp.asarray(data.q0, jnp.float32)
    z, f = (jnp.asarray(a, jnp.float32) for a in (data.z[2, 3], data.f[2, 3]))
    e = jnp.zeros_like(z)
    chol = jnp.asarray(np.linalg.cholesky(A), jnp.float32)
    by_factor = FS.prior_step(norm, z, f, e, nt, x0, solve_a=lambda r: cho_solve((chol, True), r))
    by_product = FS.prior_step(norm, z, f, e, nt, x0)
    assert float(jnp.abs(by_factor - by_product).max()) < 1e-3 * float(jnp.abs(by_product).max())


def test_linear_step_without_the_k_product_is_the_prior_step_with_no_network(bar_data):
    """``linear_step`` (A₀⁻¹K₀ = I − c A₀⁻¹M: no product by K₀) is ``prior_step`` with e = 0: to float64
    rounding in float64, and to float32 rounding in float32, along states of the data and from a moving state."""
    data, _, norm = _ops(bar_data)
    nt, x0 = jnp.asarray(data.node_type), jnp.asarray(data.q0, jnp.float32)
    norm32 = {**norm, "fs_ainv": jnp.asarray(FS.inverse(norm, data.node_type))}
    jax.config.update("jax_enable_x64", True)
    try:
        norm64 = {k: jnp.asarray(np.asarray(v, np.float64)) for k, v in norm.items()}
        norm64["fs_ainv"] = jnp.asarray(np.linalg.inv(FS.operator(norm, data.node_type)))
        for k in (2, 5):
            z, f = jnp.asarray(data.z[1, k], jnp.float64), jnp.asarray(data.f[1, k], jnp.float64)
            x64 = jnp.asarray(data.q0, jnp.float64)
            ref = FS.prior_step(norm64, z, f, jnp.zeros_like(z), nt, x64)
            got = FS.linear_step(norm64, z, f, nt, x64)
            assert got.dtype == jnp.float64
            np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=0,
                                       atol=1e-9 * float(jnp.abs(ref).max()))
    finally:
        jax.config.update("jax_enable_x64", False)
    for k in (2, 5):
        z, f = jnp.asarray(data.z[1, k], jnp.float32), jnp.asarray(data.f[1, k], jnp.float32)
        ref = FS.prior_step(norm32, z, f, jnp.zeros_like(z), nt, x0)
        got = FS.linear_step(norm32, z, f, nt, x0)
        scale = jnp.abs(ref).max(axis=0) + 1e-30
        assert float(jnp.max(jnp.abs(got - ref) / scale)) < 1e-3


def test_energy_balance_of_the_linear_step_is_its_dissipation(bar_data):
    """Along a float64 rollout of ``linear_step`` under a load that is ramped, held and released, the dissipation
    D = W − ΔE of ``energy_balance`` is the backward-Euler step's αΔt|v₁|²_M + ½|Δv|²_M + ½|Δu|²_K (to rounding),
    so it is ≥ 0 and the entropy S (its running sum) never decreases; from rest E starts at 0 and, released, decays."""
    data, _, norm = _ops(bar_data)
    nt = jnp.asarray(data.node_type)
    free = np.asarray(data.node_type) == 0
    jax.config.update("jax_enable_x64", True)
    try:
        norm64 = {k: jnp.asarray(np.asarray(v, np.float64)) for k, v in norm.items()}
        norm64["fs_ainv"] = jnp.asarray(np.linalg.inv(FS.operator(norm, data.node_type)))
        x64 = jnp.asarray(data.q0, jnp.float64)
        f = np.zeros((30,) + data.f.shape[2:])
        f[:10] = np.asarray(data.f[0, -1]) * np.minimum(np.arange(1, 11) / 5.0, 1.0)[:, None, None]  # then 0
        zs = [jnp.concatenate([x64, jnp.zeros((len(x64), 9), jnp.float64)], axis=1)]
        for fk in f:
            zs.append(zs[-1] + FS.linear_step(norm64, zs[-1], jnp.asarray(fk), nt, x64))
        z = np.asarray(jnp.stack(zs))
    finally:
        jax.config.update("jax_enable_x64", False)
    bal = FS.energy_balance(norm, z, f, data.node_type, data.q0)
    h, alpha = float(np.asarray(norm["dt"]).reshape(-1)[0]), float(np.asarray(norm["fs_alpha"]).reshape(-1)[0])
    m = np.asarray(norm["fs_mass"], np.float64)[:, None] * free[:, None]
    u, v = (z[..., :3] - np.asarray(data.q0)) * free[:, None], z[..., 3:6] * free[:, None]
    A = FS.operator(norm, data.node_type)
    K = A - np.diag((1 + alpha * h) / h ** 2 * np.repeat(np.asarray(norm["fs_mass"], np.float64), 3))
    K[~np.repeat(free, 3)] = 0.0
    K[:, ~np.repeat(free, 3)] = 0.0
    du, dv = np.diff(u, axis=0).reshape(len(f), -1), np.diff(v, axis=0)
    expected = (alpha * h * np.sum(m * v[1:] ** 2, axis=(1, 2)) + 0.5 * np.sum(m * dv ** 2, axis=(1, 2))
                + 0.5 * np.einsum("ti,ij,tj->t", du, K, du))
    assert bal["E"].shape == (31,) and bal["D"].shape == (30,) and bal["E"][0] == 0.0
    assert bal["E"].max() > 0 and np.all(expected > 0)
    np.testing.assert_allclose(bal["D"], expected, rtol=1e-6, atol=1e-9 * np.abs(bal["W"]).max())
    assert np.all(np.diff(bal["S"]) >= 0)
    assert bal["E"][-1] < bal["E"][10]   # released: the energy decays


def test_residual_is_the_increment_that_reproduces_the_data(bar_data):
    """e* = W Δz − Δt (J₀ z + B f): the prior step with e = e* lands on the data's next state, and the merged
    ``prior_step`` equals ``solve(prior_rate + e)``."""
    data, _, norm = _ops(bar_data)
    norm = {**norm, "fs_ainv": jnp.asarray(FS.inverse(norm, data.node_type))}
    nt, x0 = jnp.asarray(data.node_type), jnp.asarray(data.q0, jnp.float32)
    z, z_next, f = (jnp.asarray(a, jnp.float32) for a in (data.z[1, 3], data.z[1, 4], data.f[1, 3]))
    e_star = FS.residual(norm, z, z_next, f, nt, x0)
    got = z + FS.prior_step(norm, z, f, e_star, nt, x0)
    scale = jnp.abs(z_next - z).max(axis=0)
    assert float(jnp.max(jnp.abs(got - z_next) / scale)) < 1e-3
    e = jnp.asarray(np.random.default_rng(3).normal(size=z.shape), jnp.float32) * 1e-4
    merged = FS.prior_step(norm, z, f, e, nt, x0)
    split = FS.solve(norm, FS.prior_rate(norm, z, f, nt, x0) + e, nt)
    assert float(jnp.abs(merged - split).max()) < 1e-4 * float(jnp.abs(split).max())
    batch = FS.residuals(norm, data.z[1:2], data.f[1:2], data.node_type, data.q0)
    np.testing.assert_allclose(batch[0, 3], np.asarray(e_star), rtol=1e-3, atol=1e-4 * float(jnp.abs(e_star).max()))


def _zero_model(data, norm_np, config):
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = M.model_topology(config, data.edges[0], data.edges[1], len(data.node_type), data.q0)
    normj = {k: jnp.asarray(v) for k, v in norm_np.items()}
    w = M.init_weights(jax.random.PRNGKey(0), config, normj, jnp.asarray(data.z[0, 0]), jnp.asarray(data.f[0, 0]),
                       nt, topo)
    return api.make_params(config, norm_np, jax.tree.map(jnp.zeros_like, w), data.q0, data.edges, data.node_type)


def test_untrained_prior_is_the_linear_backward_euler_map(bar_data):
    """With the network's weights zero the step is the FEM's linearised backward-Euler frame: its rollouts
    follow the dense recurrence A₀ u_{k+1} = f_k + c M u_k + M v_k / h to float32 precision, and the implicit
    FEM (non-linear, small loads) to 1 %, with the stress from S₀."""
    data, lin, norm = _ops(bar_data)
    norm_np = {**D.normalization(data, np.arange(len(data.sim_id))),
               **{k: np.asarray(v) for k, v in norm.items()}}
    config = M.ModelConfig(hidden=8, passes=1, frame_solve=True, linear_prior=True)
    params = _zero_model(data, norm_np, config)
    pred = EV.rollout_cases(params, data, np.arange(len(data.sim_id)))
    n = len(data.q0)
    K = np.zeros((n, n, 3, 3))
    K[lin.k_rows, lin.k_cols] = lin.k_blocks
    K = K.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    m = np.repeat(lin.mass, 3)
    free = np.repeat(lin.free, 3)
    c = (1 + ALPHA * H) / H ** 2
    A = (K + np.diag(c * m))[np.ix_(free, free)]
    for case in range(len(data.sim_id)):
        u = v = np.zeros(free.sum())
        for k in range(FRAMES):
            u_new = np.linalg.solve(A, data.f[case, k].reshape(-1)[free] + c * m[free] * u + m[free] * v / H)
            u, v = u_new, (u_new - u) / H
            got = (pred[case, k + 1, :, :3] - data.q0).reshape(-1)[free]
            assert np.abs(got - u).max() < 2e-3 * np.abs(u).max() + 1e-9
    rel = EV.relative_errors(pred, data.z, data.q0)   # [cases, frames, variables q v sigma u]
    means = np.nanmean(rel.reshape(-1, rel.shape[-1]), axis=0)
    assert means[EV.VARIABLES.index("u")] < 0.01 and means[EV.VARIABLES.index("v")] < 0.01
    assert means[EV.VARIABLES.index("sigma")] < 0.02


@pytest.mark.parametrize("prior", [True, False])
def test_training_saving_and_loading(bar_data, tmp_path, prior):
    data, lin, _ = _ops(bar_data)
    cfg = T.CONFIGS["tiny"]._replace(frame_solve=True, linear_prior=prior, edge_strain=True, epochs=2, lr=1e-3)
    params = T.train(data, cfg, tmp_path / "run", train_split="all", val_split="all", progress=False,
                     log=lambda *_: None, frame_ops=lin)
    log = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["loss"]) for r in log) and np.isfinite(log[-1]["val_u"])
    path = api.save_model(params, tmp_path / "m.npz")
    with np.load(path) as npz:
        assert "norm/fs_ainv" not in npz.files and "norm/fs_k" in npz.files   # the dense inverse is rebuilt
    loaded = api.load_model(path)
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    a = api.stepper(params)(z, f)
    b = api.stepper(loaded)(z, f)
    assert float(jnp.abs(a - b).max()) <= 1e-5 * float(jnp.abs(a).max())


@pytest.fixture(scope="module")
def bar_large(tmp_path_factory):
    """Twelve implicit runs of the bar under tip loads 50× those of ``bar_data``: the non-linear range, where
    the rest linearisation misses (its rollouts' u error is about 5 %)."""
    scene = _scene()
    rng = np.random.default_rng(0)
    tip = np.where(scene.points[:, 0] > 6.0 - 1e-9)[0]
    forces = np.zeros((12, FRAMES, len(scene.points), 3))
    ramp = np.minimum(np.arange(1, FRAMES + 1) / 4.0, 1.0)
    for c in range(12):
        forces[c][:, tip] = 0.1 * rng.normal(size=3) * ramp[:, None, None] / len(tip)
    out = tmp_path_factory.mktemp("fs") / "bar_large.npz"
    run_cases(scene, _problem(scene), forces, out, progress=False, velocity="solver", integrator="implicit",
              metadata={"scene": "bar"})
    return out


def test_residual_scale_lets_the_correction_learn(bar_large, tmp_path):
    """With ``residual_scale`` the correction's output is scaled like the prior's residual (a stiff force in the
    velocity rows, ≫ the state's increments) and whole-rollout training reduces the training cases' rollout
    error below the prior's (the untrained model's first epoch)."""
    data, lin, norm = _ops(bar_large)
    cfg = T.CONFIGS["tiny"]._replace(frame_solve=True, linear_prior=True, residual_scale=True, correction_scale=0.05,
                                     edge_strain=True, epochs=16, lr=3e-3, noise=0.0, warmup_steps=5, batch_size=1,
                                     unroll=FRAMES, bptt=True, snapshot_loss=True, eval_every=16)
    params = T.train(data, cfg, tmp_path / "run", train_split=list(range(1, 11)), val_split=[11, 12],
                     progress=False, log=lambda *_: None, frame_ops=lin)
    rows = np.arange(10)
    e_star = FS.residuals({**norm, "dt": np.array([data.dt], np.float32)}, data.z[rows], data.f[rows],
                          data.node_type, data.q0)
    free = data.node_type == 0
    np.testing.assert_allclose(params["norm"]["dz_std"][3:6], np.sqrt(np.mean(e_star[:, :, free, 3:6] ** 2)), rtol=1e-3)
    assert params["norm"]["dz_std"][4] > 100 * params["norm"]["fs_dz_std"][4]   # a stiff force, not a velocity step
    log = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert log[-1]["rel2_u"] < 0.9 * log[0]["rel2_u"] and log[-1]["rel2_v"] < 0.9 * log[0]["rel2_v"]
    assert np.isfinite(log[-1]["val_u"])
    with pytest.raises(ValueError, match="residual_scale scales a linear_prior"):
        T.train(data, cfg._replace(linear_prior=False), tmp_path / "b", progress=False, frame_ops=lin)


def test_bad_use_is_a_clear_error(bar_data, tmp_path):
    data, lin, _ = _ops(bar_data)
    with pytest.raises(ValueError, match="linear_prior needs frame_solve"):
        T.train(data, T.CONFIGS["tiny"]._replace(linear_prior=True), tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="frame_ops"):
        T.train(data, T.CONFIGS["tiny"]._replace(frame_solve=True), tmp_path / "b", progress=False)
    plain = D.synthetic_beam()
    path = D.save(plain, tmp_path / "plain.npz")
    with pytest.raises(ValueError, match="cells"):
        FS.operators_from_file(path)
    params = _zero_model(data, {**D.normalization(data, np.arange(len(data.sim_id))),
                                **{k: np.asarray(v) for k, v in _ops(bar_data)[2].items()}},
                         M.ModelConfig(hidden=8, passes=1, frame_solve=True))
    with pytest.raises(ValueError, match="one body per call"):
        api.stepper(params, copies=2)
    with pytest.raises(ValueError, match="missing"):
        FS.inverse({"fs_mass": np.ones(4), "dt": np.array([0.05])}, np.zeros(4))


def test_exact_force_correction_is_the_ceiling_the_bunny_benchmark_measures(bar_data, bar_large):
    """`benchmarks/bunny_correction.py` on the bar (its material is the bunny's: nearly incompressible). The rest
    linearisation's force remainder K₀u − f_int(u) is second order (halving u quarters it). At small loads the
    W-method step with the FEM's own non-linear force cuts the prior's u error by more than a third, while its
    σ, carried as S₀u, gets far worse: S₀ applied to the true u is ≥ 10× further from the data's σ than S₀ applied
    to the prior's own u (the prior's σ is good because its u and σ are consistent). At 50× loads the explicit
    non-linear remainder makes u worse than the prior's."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import bunny_correction as BC

    scene = _scene()
    problem = _problem(scene)
    force, stress = (jax.jit(fn) for fn in implicit.force_and_stress(problem, scene.material))
    mean = {}
    for name, path in (("small", bar_data), ("large", bar_large)):
        data, _, norm = _ops(path)
        norm = {k: jnp.asarray(v) for k, v in FS.with_inverse(norm, data.node_type).items()}
        u = jnp.asarray(data.z[0, -1, :, :3] - data.q0)
        remainder = lambda x: float(jnp.linalg.norm(FS.apply_k(norm, x) - force(x)))
        assert remainder(0.0 * u) < 1e-2 * remainder(u)   # float32 rounding of f_int at rest
        assert 0.2 < remainder(0.5 * u) / remainder(u) < 0.3
        errs = [BC.case_errors(data.z[c], data.f[c], data.q0, data.node_type, data.dt, norm, force, stress, frame=4)
                for c in range(3)]
        mean[name] = {(m, k): np.mean([e[m][k] for e in errs]) for m in ("prior", "exact force")
                      for k in ("u", "sigma")}
        check = {k: np.mean([e["stress check"][k] for e in errs]) for k in errs[0]["stress check"]}
        assert check["σ(u_true)"] < 0.02   # the data's σ is the FEM's nodal stress of the data's u
        assert check["S0 u_true"] > 10 * check["S0 u_prior"]
    small, large = mean["small"], mean["large"]
    assert small["exact force", "u"] < 0.6 * small["prior", "u"]
    assert small["exact force", "sigma"] > 10 * small["prior", "sigma"]
    assert large["exact force", "u"] > large["prior", "u"]


def _untrained_net(data, config=M.ModelConfig(hidden=8, passes=1)):
    """(params, normalisation) of an untrained network on the data's mesh (forward Euler, 8×1 unless ``config``
    says otherwise), with the envelope."""
    norm_np = D.normalization(data, np.arange(len(data.sim_id)))
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = M.model_topology(config, data.edges[0], data.edges[1], len(data.node_type), data.q0)
    w = M.init_weights(jax.random.PRNGKey(0), config, {k: jnp.asarray(v) for k, v in norm_np.items()},
                       jnp.asarray(data.z[0, 0]), jnp.asarray(data.f[0, 0]), nt, topo)
    return api.make_params(config, norm_np, w, data.q0, data.edges, data.node_type), norm_np


@pytest.fixture(scope="module")
def bar_fallback(bar_data):
    """(untrained network, its normalisation, `framesolve.linear_model` of the bar for it, that model's info):
    the linearisation (about 8 s) done once for the fallback and consistency tests."""
    data, _, _ = _ops(bar_data)
    net, norm_np = _untrained_net(data)
    linear, info = FS.linear_model(net, _scene())
    return net, norm_np, linear, info


def test_fallback_stepper_hands_flagged_bodies_to_the_rest_linearised_fem(bar_data, bar_fallback):
    """`framesolve.linear_model` is the scene's linearised backward-Euler step (as the zero-network model built
    from the data file). `api.fallback_stepper` returns the network's step where nothing is flagged; a body
    whose network step leaves the envelope is stepped instead by that linear step from its state with σ = S₀u,
    and stays on it for ``hold`` more steps (the network not used), then the network resumes; the other body
    keeps its network step. Bad use is a clear error."""
    data, _, norm = _ops(bar_data)
    net, norm_np, linear, info = bar_fallback
    assert info["fem_damping"] == ALPHA and "not learned" in info["kind"]
    reference = _zero_model(data, {**norm_np, **{k: np.asarray(v) for k, v in norm.items()}},
                            M.ModelConfig(hidden=8, passes=1, frame_solve=True, linear_prior=True))
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    lin_step = api.stepper(linear)
    np.testing.assert_allclose(np.asarray(lin_step(z, f)), np.asarray(api.stepper(reference)(z, f)),
                               rtol=1e-4, atol=1e-6 * float(jnp.abs(z).max()))
    plain = api.stepper(net, 2)
    hold = 2
    fn = api.fallback_stepper(net, linear, copies=2, hold=hold)
    wild = np.array(data.z[0, 2], np.float32)
    wild[:, 3:] = norm_np["z_mean"][3:] + 50.0 * norm_np["z_dev_max"][3:] * norm_np["z_std"][3:]
    zz, ff = jnp.concatenate([z, jnp.asarray(wild)]), jnp.concatenate([f, f])
    n = len(data.q0)
    out, flagged, left = fn(zz, ff, jnp.zeros(2, jnp.int32))
    assert flagged.tolist() == [False, True] and left.tolist() == [0, hold]
    np.testing.assert_allclose(np.asarray(out[:n]), np.asarray(plain(zz, ff)[:n]), rtol=1e-6, atol=1e-6)
    free = (data.node_type == 0)[:, None]
    u = np.where(free, wild[:, :3] - data.q0, 0.0)
    start = np.concatenate([wild[:, :6], np.asarray(FS.apply_s(linear["norm"], jnp.asarray(u, jnp.float32)))], 1)
    expected = np.asarray(lin_step(jnp.asarray(start), f))
    np.testing.assert_allclose(np.asarray(out[n:]), expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())
    for k in range(hold):   # the flagged body stays on the linear step, the other on the network's
        prev = out
        out, flagged, left = fn(prev, ff, left)
        assert not flagged.any() and left.tolist() == [0, hold - 1 - k]
        np.testing.assert_allclose(np.asarray(out[n:]), np.asarray(lin_step(prev[n:], f)), rtol=1e-5,
                                   atol=1e-5 * float(jnp.abs(prev[n:]).max()))
    # then the network resumes: an in-envelope state with no steps left takes the network's step
    out, flagged, left = fn(jnp.concatenate([z, z]), ff, left)
    assert not flagged.any() and left.tolist() == [0, 0]
    np.testing.assert_allclose(np.asarray(out[n:]), np.asarray(plain(zz, ff)[:n]), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="rest-linearised"):
        api.fallback_stepper(net, net)
    with pytest.raises(ValueError, match="another mesh"):
        api.fallback_stepper(net, {**linear, "mesh": {**linear["mesh"], "q0": linear["mesh"]["q0"] + 1.0}})
    with pytest.raises(ValueError, match="hold"):
        api.fallback_stepper(net, linear, hold=-1)
    with pytest.raises(ValueError, match="left"):
        fn(zz, ff, jnp.zeros(3, jnp.int32))
    with pytest.raises(ValueError, match="not on the"):
        FS.linear_model(net, _scene()._replace(points=_scene().points * 2.0))
    # the linear map does not depend on the parent's architecture: a parent with a force port (whose gain is 1
    # at zero weights) and RK4 gives the same step (the port's B f would count the force twice)
    ported, _ = _untrained_net(data, M.ModelConfig(hidden=8, passes=1, force_port=True, integrator="rk4"))
    other, _ = FS.linear_model(ported, _scene())
    assert other["config"] == linear["config"]
    np.testing.assert_allclose(np.asarray(api.stepper(other)(z, f)), np.asarray(lin_step(z, f)), rtol=1e-5,
                               atol=1e-6 * float(jnp.abs(z).max()))


def test_consistency_bound_flags_a_step_that_departs_from_the_linear_one(bar_data, bar_fallback):
    """`api.consistency_bound` is the largest departure (per component, in stds, free nodes) of the learned step
    from the linear one over the given transitions; with it, `fallback_stepper` leaves those transitions to the
    network (tolerance ≥ 1) and hands over a step that departs further, here a network whose bound was measured
    ten times tighter than its departures. Bad bounds and shapes are clear errors."""
    data, _, _ = _ops(bar_data)
    net, norm_np, linear, _ = bar_fallback
    z, f = data.z[:2, :-1], data.f[:2]
    bound = api.consistency_bound(net, linear, z, f)
    assert bound.shape == (12,) and np.all(bound > 0)
    free = data.node_type == 0
    a, b = jnp.asarray(z[1, 3]), jnp.asarray(f[1, 3])
    d = np.abs(np.asarray(api.stepper(net)(a, b)) - np.asarray(api.stepper(linear)(a, b))) / norm_np["z_std"]
    assert np.all(d[free].max(axis=0) <= bound * (1 + 1e-4) + 1e-6)
    left = jnp.zeros(1, jnp.int32)
    loose = api.fallback_stepper(net, linear, tolerance=1e6, consistency=bound)
    assert not bool(loose(a, b, left)[1][0])
    calibrated = api.fallback_stepper(net, linear, tolerance=1.5, consistency=bound)
    np.testing.assert_allclose(np.asarray(calibrated(a, b, left)[0]), np.asarray(loose(a, b, left)[0]), atol=1e-6)
    tight = api.fallback_stepper(net, linear, tolerance=1e6, consistency=bound / 1e7)
    out, flagged, left_next = tight(a, b, left)
    assert bool(flagged[0]) and int(left_next[0]) == 30
    with pytest.raises(ValueError, match="consistency"):
        api.fallback_stepper(net, linear, consistency=-bound)
    with pytest.raises(ValueError, match="forces"):
        api.consistency_bound(net, linear, z, f[:, :-1])


def test_s_rows_layout_matches_block_list():
    """S₀ row by row in groups of rows (`s_rows_layout`, what `with_inverse` adds) applies the same map as the
    block list, with repeated node pairs, rows without blocks and rows of very different lengths (several
    groups), and its arrays are among those a saved model leaves out."""
    rng = np.random.default_rng(3)
    n = 40
    counts = np.concatenate([np.zeros(5, int), rng.integers(1, 4, 25), rng.integers(20, 30, 10)])
    rows = np.repeat(np.arange(n), counts)
    cols = rng.integers(0, n, len(rows))
    cols[:2] = cols[0]                                      # a repeated (row, col) pair
    blocks = rng.normal(size=(len(rows), 6, 3)).astype(np.float32)
    norm = {"fs_s_rows": rows.astype(np.float32), "fs_s_cols": cols.astype(np.float32), "fs_s": blocks}
    x = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    dense = np.zeros((n, 6, n, 3))
    np.add.at(dense, (rows, slice(None), cols, slice(None)), blocks.astype(np.float64))
    expected = dense.reshape(6 * n, 3 * n) @ np.asarray(x, np.float64).reshape(-1)
    np.testing.assert_allclose(np.asarray(FS.apply_s(norm, x)).reshape(-1), expected, rtol=1e-5, atol=1e-5)
    for groups in (1, 2, 4):
        layout = FS.s_rows_layout(norm, n, max_groups=groups, group_slots=0)
        found = sum(k.endswith("_cols") for k in layout)
        assert found == groups       # without a cost per group, every split that saves padding is taken
        slots = sum(v.shape[0] * v.shape[1] for k, v in layout.items() if k.endswith("_cols"))
        assert slots >= len(rows) and (groups == 1 or slots < n * counts.max())
        by_rows = np.asarray(FS.apply_s({**norm, **layout}, x)).reshape(-1)
        np.testing.assert_allclose(by_rows, expected, rtol=1e-5, atol=1e-5)
        assert set(layout) <= set(FS.DERIVED)
    with pytest.raises(ValueError, match="fs_s_rows reach node 39"):
        FS.s_rows_layout(norm, 39)


def test_ainv_blocks_multiply_like_the_dense_inverse():
    """`ainv_blocks` + `apply_ainv`: the upper-triangular blocks of a symmetric A⁻¹ give its product (each
    off-diagonal block used for itself and its transpose), split at node boundaries, for 1, 2, 4 and 7 blocks and
    a mesh whose node count does not divide evenly; a non-symmetric matrix keeps the dense product; bad input
    is named."""
    rng = np.random.default_rng(0)
    n_nodes = 13
    b = rng.normal(size=(3 * n_nodes, 3 * n_nodes))
    a = (b @ b.T + np.eye(3 * n_nodes)).astype(np.float32)
    r = jnp.asarray(rng.normal(size=3 * n_nodes), jnp.float32)
    dense = np.asarray(jnp.asarray(a) @ r)
    for k in (1, 2, 4, 7):
        blocks = FS.ainv_blocks(a, n_nodes, k=k)
        assert len(blocks) == k * (k + 1) // 2
        sizes = [blocks[f"fs_ainv_sb{i}_{i}"].shape[0] for i in range(k)]
        assert sum(sizes) == 3 * n_nodes and all(s % 3 == 0 for s in sizes)   # node boundaries
        got = np.asarray(FS.apply_ainv({**blocks, "fs_ainv": jnp.asarray(a)}, r))
        np.testing.assert_allclose(got, dense, rtol=1e-5, atol=1e-5 * np.abs(dense).max())
    skew = a.copy()
    skew[0, 1] += 1.0
    assert FS.ainv_blocks(skew, n_nodes) == {}
    np.testing.assert_array_equal(np.asarray(FS.apply_ainv({"fs_ainv": jnp.asarray(a)}, r)), dense)
    with pytest.raises(ValueError, match=r"shape \(39, 39\) does not match a mesh of 12 nodes"):
        FS.ainv_blocks(a, 12)
    with pytest.raises(ValueError, match="at least 1, got 0"):
        FS.ainv_blocks(a, n_nodes, k=0)
    assert set(FS.AINV_BLOCK_KEYS) <= set(FS.DERIVED)   # rebuilt when a model is loaded, never saved


def test_linear_step_with_the_blocks_matches_the_dense_product():
    """The learned linear `bunny` (A₀⁻¹ of 64 MB) is loaded with the blocks, `beam` (20.6 MB, below
    `AINV_BLOCK_MIN_BYTES`) with the dense product only; built with the blocks, its step equals the dense one to float32 rounding, from a moving state
    under a load."""
    from tignn_jax import api

    bunny, _ = api.load_pretrained("bunny")   # 64 MB: the demo's bunny steps with the blocks
    assert all(k in bunny["norm"] for k in FS.AINV_BLOCK_KEYS)
    params, graph = api.load_pretrained("beam")
    assert not any(k in params["norm"] for k in FS.AINV_BLOCK_KEYS)
    nt = jnp.asarray(params["mesh"]["node_type"], jnp.int32)
    x0 = jnp.asarray(params["mesh"]["q0"], jnp.float32)
    blocked = FS.with_inverse(params["norm"], np.asarray(nt), block_bytes=0)
    assert all(k in blocked for k in FS.AINV_BLOCK_KEYS)
    rng = np.random.default_rng(1)
    n = len(x0)
    z = jnp.asarray(np.concatenate([np.asarray(x0) + 0.05 * rng.normal(size=(n, 3)), rng.normal(size=(n, 9))],
                                   axis=1), jnp.float32)
    f = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    got = np.asarray(FS.linear_step({k: jnp.asarray(v) for k, v in blocked.items()}, z, f, nt, x0))
    ref = np.asarray(FS.linear_step(params["norm"], z, f, nt, x0))
    scale = np.abs(ref).max(axis=0) + 1e-30
    assert float(np.max(np.abs(got - ref) / scale)) < 1e-4
