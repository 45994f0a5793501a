"""scripts/drop_pass.py: removing a message pass whose update is zero leaves the model's function unchanged."""
import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import model as M

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("drop_pass", ROOT / "scripts" / "drop_pass.py")
drop_pass = importlib.util.module_from_spec(spec)
spec.loader.exec_module(drop_pass)

CONFIG = M.ModelConfig(hidden=8, mlp_layers=2, passes=3, edge_velocity=True)


@pytest.fixture(scope="module")
def toy():
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=3, frames=4)
    norm = D.normalization(data, D.split_rows(data, "train"))
    jnorm = {k: jnp.asarray(v) for k, v in norm.items()}
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    nt = jnp.asarray(data.node_type, jnp.int32)
    weights = M.init_weights(jax.random.PRNGKey(3), CONFIG, jnorm, z, f, nt, topo)
    params = api.make_params(CONFIG, norm, weights, data.q0, data.edges, data.node_type)
    return dict(params=params, z=z, f=f, nt=nt, norm=jnorm, topo=topo)


def _rate(params, t):
    config = M.ModelConfig(**params["config"])
    return np.asarray(M.rates(params["weights"], config, t["norm"], t["z"], t["f"], t["nt"], t["topo"]).dw)


@pytest.mark.parametrize("drop", [0, 1, 2])
def test_dropping_an_identity_pass_keeps_the_rates(toy, drop):
    # Zero the node MLP's output layer of pass `drop`: that pass then adds nothing to the latent (h ← h + 0), so
    # the model without it computes the same rates; a wrong renumbering of the later passes or the decoder would not.
    params = dict(toy["params"])
    w = jax.tree_util.tree_map(np.asarray, params["weights"])
    out = w[f"MLP_{drop + 1}"]["Dense_1"]
    w[f"MLP_{drop + 1}"] = dict(w[f"MLP_{drop + 1}"], Dense_1={k: np.zeros_like(v) for k, v in out.items()})
    params["weights"] = w
    smaller = drop_pass.drop_pass(params, drop)
    assert smaller["config"]["passes"] == 2
    assert sorted(k for k in smaller["weights"] if k.startswith("MLP_")) == ["MLP_0", "MLP_1", "MLP_2", "MLP_3"]
    full, short = _rate(params, toy), _rate(smaller, toy)
    assert np.abs(full).max() > 0
    np.testing.assert_allclose(short, full, rtol=1e-5, atol=1e-6 * np.abs(full).max())
    # and a pass that does update the latent is not an identity: dropping it changes the rates
    changed = _rate(drop_pass.drop_pass(toy["params"], drop), toy)
    assert np.abs(changed - _rate(toy["params"], toy)).max() > 1e-4 * np.abs(full).max()


def test_drop_pass_names_a_bad_pass_index(toy):
    with pytest.raises(ValueError, match="0..2, got 3"):
        drop_pass.drop_pass(toy["params"], 3)
    one = dict(toy["params"], config=dict(toy["params"]["config"], passes=1))
    with pytest.raises(ValueError, match="1 pass"):
        drop_pass.drop_pass(one, 0)
