"""Reverse-mode gradients of a whole (checkpointed) rollout against central finite differences."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem

CELL_TYPES = ["hexahedron", "tetra"]


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def rollout_loss_fn(cell_type):
    """(c10, density, load scale) → Σ_frames |tip displacement|² of a viscoelastic 3×1×1 cantilever."""
    base = fem.mooney_rivlin(5e3, 1e3, 4e-5, density=1.0, g=(0.3, 0.49), tau=(0.2, 0.5))
    pts, cells = fem.box_hex_mesh((3.0, 1.0, 1.0), (3, 1, 1))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    n_frames = 3
    # n_sub fixed (the automatic choice depends on c10 and density, which would make the loss discontinuous)
    prob = fem.setup(pts, cells, material=base, frame_dt=0.02, n_frames=n_frames, n_sub=12,
                     clamped=np.where(pts[:, 0] < 1e-9)[0], load_interp="linear")
    tip = np.where(pts[:, 0] > 3.0 - 1e-9)[0]
    nodal = np.zeros((n_frames, len(pts), 3))
    nodal[:, tip, 1] = 50.0 / len(tip)
    nodal[:, tip, 2] = -20.0 / len(tip)

    def loss(params):
        c10, rho, scale = params
        m = base._replace(c10=c10, density=rho)
        res = fem.simulate(prob, m, fem.Loads(nodal=scale * jnp.asarray(nodal)))
        u = res.q[1:, tip] - prob.arrays.points[tip]
        return jnp.sum(u ** 2)

    return loss


@pytest.mark.parametrize("cell_type", [pytest.param("hexahedron", marks=pytest.mark.long), "tetra"])
def test_rollout_gradient_matches_central_finite_differences(cell_type):
    """d(loss)/d(c10, density, load scale) by jax.grad through the checkpointed sub-step scans equals central
    finite differences to 1e-4 relative (float64, step 1e-5 relative: truncation and round-off ≲ 1e-9)."""
    loss = rollout_loss_fn(cell_type)
    p0 = jnp.array([5e3, 1.0, 1.0])
    value, grad = jax.value_and_grad(loss)(p0)
    assert float(value) > 0.0
    loss_jit = jax.jit(loss)
    for i in range(3):
        dp = 1e-5 * float(p0[i])
        e = jnp.zeros(3).at[i].set(dp)
        fd = (float(loss_jit(p0 + e)) - float(loss_jit(p0 - e))) / (2 * dp)
        assert float(grad[i]) == pytest.approx(fd, rel=1e-4), f"parameter {i}: grad {float(grad[i])!r}, fd {fd!r}"
        assert abs(fd) * abs(float(p0[i])) > 1e-3 * float(value)   # every parameter really matters
