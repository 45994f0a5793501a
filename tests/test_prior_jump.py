"""benchmarks/prior_jump.py: the rest-linearised step from true states, against a known answer and the data."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import prior_jump as pj  # noqa: E402


@pytest.fixture(scope="module")
def linear():
    from tignn_jax import api

    return api.load_pretrained("beam-linear")


def test_a_rollout_of_the_prior_itself_has_no_jump(linear):
    # States made by the prior's own step (`api.stepper`, which `jump_ratios` runs) are its fixed answer: every
    # ratio is ~0 (float32 rounding of the q and σ increments against their positions and stresses: below 1e-2,
    # where the reference data give 3 to 2000).
    from tignn_jax import api

    params, graph = linear
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    f = np.zeros((4, len(q0), 3), np.float32)
    f[:, np.argmax(q0[:, 0]), 2] = -50.0             # a tip load
    step = api.stepper(params)                        # the step jump_ratios times: the same program, same rounding
    zs = [graph.nodes["z"]]
    for fk in f:
        zs.append(step(zs[-1], fk))
    z = np.asarray(np.stack(zs))
    ratios = pj.jump_ratios(params, z[None], f[None])
    assert ratios.shape == (4, 3) and np.all(ratios < 1e-2), ratios


def test_the_prior_jumps_from_deflected_reference_states(linear):
    # On the Abaqus train cases the prior's one-step velocity error from true states exceeds the increment and
    # grows with the deflection (the measured result); skipped where the reference file is not present.
    from tignn_jax import data as D

    path = D.reference_path()
    if not Path(path).exists():
        pytest.skip(f"{path} not present")
    data = D.load(path)
    rows = D.split_rows(data, "train")[:2]
    ratios = pj.jump_ratios(linear[0], np.asarray(data.z[rows], np.float32), np.asarray(data.f[rows], np.float32))
    v = ratios[:, 1]
    assert v[0] > 1.0 and v[-1] > 10 * v[0], v
    assert ratios[0, 0] < 0.2, ratios[0]      # positions: the first frame's step is close


def test_the_prior_stress_of_a_rigid_rotation_is_the_linearised_pressure(linear):
    # A rigid rotation by θ about z has no stress, but div u = 2(cos θ − 1), so the rest linearisation's stress S₀u
    # is the pressure (2/D1)·2(cos θ − 1) in every node (uniform strain: the nodal average is exact), with a
    # deviatoric part of the shear modulus' order, 2μ(cos θ − 1)·2/3 (the beam: D1 = 1e-7, μ = 2(C10 + C01)).
    params, _ = linear
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    theta = 0.1
    rot = np.array([[np.cos(theta), -np.sin(theta), 0.0], [np.sin(theta), np.cos(theta), 0.0], [0.0, 0.0, 1.0]])
    z = np.zeros((1, 2, len(q0), 12), np.float32)
    z[0, 0, :, :3] = q0
    z[0, 1, :, :3] = (q0 - q0.mean(0)) @ rot.T + q0.mean(0)
    split = pj.stress_split(params, z)
    assert split.shape == (2, 4)
    np.testing.assert_allclose(split[0], 0.0, atol=1e-6)     # at rest: nothing
    true_p, prior_p, true_dev, prior_dev = split[1]
    assert true_p == 0.0 and true_dev == 0.0                   # the stored (true) stress of a rigid motion
    pressure = (2 / 1e-7) * 2 * (np.cos(theta) - 1)
    np.testing.assert_allclose(prior_p, abs(pressure), rtol=0.02)
    mu = 2 * (1.5e5 + 5e3)
    assert prior_dev < 0.05 * abs(pressure) and prior_dev < 10 * mu * (1 - np.cos(theta))
