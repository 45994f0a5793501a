"""The linear GENERIC model class: its structure measured on the shipped operators, its step exact."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax as T
from tignn_jax.simulators import linear as LG


@pytest.fixture(scope="module")
def beam():
    return T.load_pretrained("beam")[0]


def dense(arrays, key, rows):
    n = arrays["mass"].shape[0]
    out = np.zeros((n, n, rows, 3))
    out[np.asarray(arrays[f"{key}_rows"]), np.asarray(arrays[f"{key}_cols"])] = np.asarray(arrays[key])
    return out.transpose(0, 2, 1, 3).reshape(rows * n, 3 * n)


def test_stiffness_is_symmetric_psd_on_the_free_nodes(beam):
    # E = ½ uᵀKu is a convex potential: K symmetric with no negative eigenvalue on the free degrees of freedom
    arrays, free = beam["arrays"], np.repeat(beam["mesh"]["node_type"] == 0, 3)
    K = dense(arrays, "k", 3)[free][:, free]
    assert np.abs(K - K.T).max() < 1e-5 * np.abs(K).max()
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert eig.min() > -1e-6 * eig.max()
    assert float(arrays["alpha"][0]) >= 0 and np.all(np.asarray(arrays["mass"]) > 0)


def test_the_step_is_backward_euler(beam):
    # M (v' − v)/Δt = f − K u' − α M v', u' = u + Δt v', σ' = σ + Δt S v' on the free nodes (float64 reference)
    arrays, mesh = beam["arrays"], beam["mesh"]
    rng = np.random.default_rng(0)
    n = len(mesh["q0"])
    free = (mesh["node_type"] == 0)[:, None]
    z = np.concatenate([mesh["q0"] + 0.1 * rng.normal(size=(n, 3)) * free, rng.normal(size=(n, 3)) * free,
                        1e3 * rng.normal(size=(n, 6))], 1).astype(np.float32)
    f = (1e4 * rng.normal(size=(n, 3)) * free).astype(np.float32)
    nxt = np.asarray(beam["model"].step_state(arrays, jnp.asarray(z), jnp.asarray(f)), np.float64)
    h, alpha = float(arrays["dt"][0]), float(arrays["alpha"][0])
    m = np.repeat(np.asarray(arrays["mass"], np.float64), 3)
    K, S = dense(arrays, "k", 3), dense(arrays, "s", 6)
    fr = np.repeat(free[:, 0], 3)
    u1, v0, v1 = (nxt[:, :3] - mesh["q0"]).reshape(-1), z[:, 3:6].reshape(-1), nxt[:, 3:6].reshape(-1)
    residual = (m * (v1 - v0) / h - f.reshape(-1) + K @ u1 + alpha * m * v1)[fr]
    # float32: the step's one-product form, A⁻¹(c M w) − w / Δt, cancels about two digits
    assert np.abs(residual).max() < 1e-2 * np.abs(K @ u1)[fr].max()
    # v' itself, against the float64 solve of [(1 + αΔt) M / Δt² + K] v' = M v / Δt² + (f − K u) / Δt: within
    # 1e-5 (measured 7e-7), where leaving out the damping term would move it by 2 %
    u0 = (z[:, :3] - mesh["q0"]).reshape(-1).astype(np.float64)
    A = (np.diag((1.0 + alpha * h) * m / h ** 2) + K)[np.ix_(fr, fr)]
    v_ref = np.linalg.solve(A, (m * v0 / h ** 2 + (f.reshape(-1) - K @ u0) / h)[fr])
    assert np.linalg.norm(v1[fr] - v_ref) < 1e-5 * np.linalg.norm(v_ref)
    assert np.allclose(nxt[:, :3] - z[:, :3], h * nxt[:, 3:6], atol=1e-4)
    assert np.allclose((nxt[:, 6:] - z[:, 6:]).reshape(-1), h * S @ v1, rtol=1e-3, atol=1e-3 * np.abs(S @ v1).max())
    assert np.array_equal(nxt[~free[:, 0], :6], z[~free[:, 0], :6])    # clamped nodes keep q and v


def test_energy_is_never_created(beam):
    # with the forces' work counted, every step dissipates: D = W − ΔE ≥ 0, from random states and forces
    arrays, model, mesh = beam["arrays"], beam["model"], beam["mesh"]
    rng = np.random.default_rng(1)
    n = len(mesh["q0"])
    free = (mesh["node_type"] == 0)[:, None]
    diag = jax.jit(lambda z, f: model.diagnostics(arrays, z, f, model.step_state(arrays, z, f)))
    for _ in range(5):
        z = np.concatenate([mesh["q0"] + rng.normal(size=(n, 3)) * free, 10 * rng.normal(size=(n, 3)) * free,
                            np.zeros((n, 6))], 1)
        f = 1e4 * rng.normal(size=(n, 3)) * free
        d = diag(jnp.asarray(z, jnp.float32), jnp.asarray(f, jnp.float32))
        assert float(d["dissipation"]) >= -1e-4 * abs(float(d["energy"]))


def test_an_unloaded_body_comes_to_rest(beam):
    params, graph = T.load_pretrained("beam")
    f = np.zeros((60, 756, 3), np.float32)
    f[:10, params["mesh"]["q0"][:, 0] > 39.9, 2] = -float(params["envelope"]["f_max"][0])
    states = np.asarray(T.rollout(params, graph, f))
    energy = jax.vmap(lambda z: LG.energy(params["arrays"], z))(jnp.asarray(states))
    assert np.all(np.diff(np.asarray(energy)[10:]) <= 1e-6 * float(energy.max()))   # after the release: falls
    assert float(energy[-1]) < 0.05 * float(energy.max())


def test_bad_operators_are_refused(beam):
    stored = beam["model"].stored(beam["arrays"])
    with pytest.raises(ValueError, match="missing \\['alpha'\\]"):
        LG.LinearGeneric().prepare({k: v for k, v in stored.items() if k != "alpha"}, beam["mesh"])
    mesh = {**beam["mesh"], "node_type": beam["mesh"]["node_type"][:10]}
    with pytest.raises(ValueError, match="for 756 nodes, the mesh has 10"):
        LG.LinearGeneric().prepare(stored, mesh)


def test_large_inverse_in_blocks_gives_the_dense_product():
    # the bunny's A⁻¹ is kept as the upper blocks of a 4 × 4 split: the product is the dense one
    params = T.load_pretrained("bunny")[0]
    arrays = params["arrays"]
    assert "ainv_blocks" in arrays
    dense_inv = LG.inverse(params["model"].stored(arrays), params["mesh"]["node_type"])
    r = jnp.asarray(np.random.default_rng(2).normal(size=dense_inv.shape[0]), jnp.float32)
    assert np.allclose(np.asarray(LG.apply_ainv(arrays, r)), dense_inv @ np.asarray(r),
                       atol=1e-5 * np.abs(dense_inv @ np.asarray(r)).max())
