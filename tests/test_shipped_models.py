"""Every shipped model, loaded as a user loads it, responds like the FEM from the rest graph it comes with."""
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax as T

# name: (the FEM's rest linearisation of its scene, which preconditions the FEM's Newton step, u / σ tolerance)
SHIPPED = {"beam": ("beam-linear", 0.05, 0.06), "beam-linear": ("beam-linear", 0.05, 0.06),
           "bunny": ("bunny-linear", 0.05, 0.25), "bunny-linear": ("bunny-linear", 0.05, 0.25)}


def test_the_shipped_models_are_the_documented_ones():
    assert sorted(T.shipped_models()) == sorted(SHIPPED)
    assert T.api.DEFAULT_MODEL == "beam"


def press(params, frames=20):
    """A load ramped over 10 frames and held: on the beam's free end (its x = 40 face, downwards, the reference
    data's largest tip load), on the bunny over six nodes at its top (a fingertip-sized press, half the largest
    training nodal force each)."""
    q0 = params["mesh"]["q0"]
    f = np.zeros((frames, len(q0), 3), np.float32)
    ramp = np.minimum(np.arange(1, frames + 1) / 10.0, 1.0)[:, None]
    f_max = float(params["envelope"]["f_max"][0])
    if q0[:, 0].max() > 39:
        tip = np.where(q0[:, 0] > q0[:, 0].max() - 1e-3)[0]
        f[:, tip, 2] = -ramp * f_max
    else:
        top = np.argsort(q0[:, 2])[-6:]
        f[:, top, 2] = -ramp * f_max / 2
    return f


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_shipped_model_follows_the_fem_from_rest(name):
    # the model's own rest graph and the public step: the body must deflect as the FEM's backward-Euler step
    # (Newton iterations on the exact internal force) does, not stay put (a model that learned a first velocity)
    linear_name, u_tol, s_tol = SHIPPED[name]
    params, graph = T.load_pretrained(name)
    fem = T.fem_stepper(T.load_pretrained(linear_name)[0])
    forces = press(params)
    z_fem = [graph.nodes["z"]]
    for f in forces:
        z_fem.append(fem(z_fem[-1], jnp.asarray(f)))
    z_fem = np.stack([np.asarray(z) for z in z_fem])
    z = [graph]
    for f in forces:
        z.append(T.step(params, z[-1], f))
    z = np.stack([np.asarray(g.nodes["z"]) for g in z])
    q0 = params["mesh"]["q0"]
    u, u_fem = z[..., :3] - q0, z_fem[..., :3] - q0
    peak = np.sqrt((u_fem ** 2).sum((-2, -1))).max()
    assert peak > 0.1, "the press must move the body"
    assert np.sqrt(((u - u_fem) ** 2).sum((-2, -1))).mean() < u_tol * peak
    s_peak = np.sqrt((z_fem[..., 6:] ** 2).sum((-2, -1))).max()
    assert np.sqrt(((z[..., 6:] - z_fem[..., 6:]) ** 2).sum((-2, -1))).mean() < s_tol * s_peak


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_shipped_model_has_a_one_screen_card(name):
    card = (T.api.PRETRAINED_DIR / name / "MODEL_CARD.md").read_text()
    lines = card.splitlines()
    assert len(lines) <= 45 and max(map(len, lines)) <= 120
    for section in ("What it is", "Data", "Recipe", "Test errors", "Step time", "Limits"):
        assert f"## {section}" in card
