"""Mooney–Rivlin hyperelasticity with a Prony-series viscoelastic relaxation, as Abaqus defines them.

Hyperelastic base (Abaqus ``*HYPERELASTIC, MOONEY-RIVLIN``)::

    U = C10 (Ī1 − 3) + C01 (Ī2 − 3) + (J − 1)² / D1,
    Ī1 = J^(−2/3) I1,  Ī2 = J^(−4/3) I2,  I1 = tr C,  I2 = ½ (I1² − tr C²),  C = Fᵀ F,
    μ0 = 2 (C10 + C01)  (initial shear modulus),  K0 = 2 / D1  (initial bulk modulus).

Second Piola–Kirchhoff stress, split into a volumetric and an isochoric part::

    S = S_vol + S_iso,   S_vol = J p C⁻¹,  p = dU/dJ = 2 (J − 1) / D1,
    S_iso = J^(−2/3) DEV[ 2 (C10 + C01 Ī1) I − 2 C01 C̄ ],  C̄ = J^(−2/3) C,
    DEV[A] = A − ⅓ (A : C) C⁻¹.

Cauchy stress σ = J⁻¹ F S Fᵀ (tension positive).

Viscoelasticity (Abaqus ``*VISCOELASTIC, TIME=PRONY`` with ḡ_i, τ_i and k̄_i = 0): the hyperelastic constants are
the instantaneous response and the shear relaxation modulus is g_R(t) = 1 − Σ ḡ_i (1 − exp(−t/τ_i)). The
isochoric stress is the hereditary integral of the instantaneous isochoric stress S⁰_iso, written in the
reference configuration (objective under rigid rotation)::

    S_iso(t) = g∞ S⁰_iso(t) + Σ_i ḡ_i H_i(t),   g∞ = 1 − Σ ḡ_i,
    H_i(t) = ∫₀ᵗ exp(−(t − s)/τ_i) dS⁰_iso/ds ds,

and each internal variable is advanced over a step Δt with the exact exponential recursion for a stress that
varies linearly within the step::

    H_i⁽ⁿ⁺¹⁾ = exp(−Δt/τ_i) H_iⁿ + (τ_i/Δt) (1 − exp(−Δt/τ_i)) (S⁰_iso⁽ⁿ⁺¹⁾ − S⁰_isoⁿ).

Under a held step of isochoric strain this gives S_iso(t) = g_R(t) S⁰_iso exactly. The volumetric response is
purely elastic (k̄ = 0). In the small-strain limit ḡ_i H_i is the stress in the i-th Maxwell branch (shear
modulus ḡ_i μ0, viscosity ḡ_i μ0 τ_i), which gives the stored energy |ḡ_i H_i|² / (4 ḡ_i μ0) and the dissipation
rate |ḡ_i H_i|² / (2 ḡ_i μ0 τ_i) ≥ 0 that the solver reports.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np


class Material(NamedTuple):
    """Mooney–Rivlin + Prony material. All entries are arrays so the material is a differentiable pytree.

    c10, c01: Mooney–Rivlin constants [stress]. d1: compressibility [1/stress]. density: [mass/volume].
    g, tau: Prony weights ḡ_i [-] and relaxation times τ_i [time], shape [n_terms] (n_terms may be 0).
    """

    c10: jnp.ndarray
    c01: jnp.ndarray
    d1: jnp.ndarray
    density: jnp.ndarray
    g: jnp.ndarray
    tau: jnp.ndarray

    @property
    def n_prony(self) -> int:
        return int(np.shape(self.g)[0])


def mooney_rivlin(c10, c01=0.0, d1=1e-3, density=1.0, g=(), tau=()) -> Material:
    """Build and validate a :class:`Material` (raises ``ValueError`` naming the bad value)."""
    c10f, c01f, d1f, rho = (float(np.asarray(x)) for x in (c10, c01, d1, density))
    g_arr = np.atleast_1d(np.asarray(g, dtype=float)) if np.size(g) else np.zeros(0)
    tau_arr = np.atleast_1d(np.asarray(tau, dtype=float)) if np.size(tau) else np.zeros(0)
    for name, val in (("c10", c10f), ("c01", c01f), ("d1", d1f), ("density", rho)):
        if not np.isfinite(val):
            raise ValueError(f"{name} must be finite, got {val!r}")
    if c10f + c01f <= 0.0:
        raise ValueError("c10 + c01 must be positive (initial shear modulus 2(c10+c01)), "
                         f"got c10={c10f!r}, c01={c01f!r}")
    if d1f <= 0.0:
        raise ValueError(f"d1 must be positive (bulk modulus 2/d1), got d1={d1f!r}")
    if rho <= 0.0:
        raise ValueError(f"density must be positive, got density={rho!r}")
    if g_arr.shape != tau_arr.shape:
        raise ValueError("Prony g and tau must have the same length, "
                         f"got g={g_arr.tolist()} and tau={tau_arr.tolist()}")
    if np.any(g_arr < 0.0) or not np.all(np.isfinite(g_arr)):
        raise ValueError(f"Prony weights g must be finite and non-negative, got g={g_arr.tolist()}")
    if g_arr.sum() >= 1.0:
        raise ValueError("Prony weights must sum to less than 1 (long-term modulus > 0), "
                         f"got sum(g)={float(g_arr.sum())!r}")
    if np.any(tau_arr <= 0.0) or not np.all(np.isfinite(tau_arr)):
        raise ValueError(f"Prony relaxation times tau must be positive, got tau={tau_arr.tolist()}")
    as_arr = lambda x: jnp.asarray(x, dtype=jnp.result_type(float))
    return Material(as_arr(c10f), as_arr(c01f), as_arr(d1f), as_arr(rho), as_arr(g_arr), as_arr(tau_arr))


def shear_modulus(m: Material):
    """Initial (instantaneous) shear modulus μ0 = 2 (C10 + C01)."""
    return 2.0 * (m.c10 + m.c01)


def bulk_modulus(m: Material):
    """Initial bulk modulus K0 = 2 / D1."""
    return 2.0 / m.d1


def relaxation_modulus(m: Material, t):
    """g_R(t) = 1 − Σ ḡ_i (1 − exp(−t/τ_i)), dimensionless."""
    t = jnp.asarray(t)[..., None]
    return 1.0 - jnp.sum(m.g * (1.0 - jnp.exp(-t / m.tau)), axis=-1)


# --- 3×3 algebra in "component-leading" layout ---------------------------------------------------------------
# The hot path stores a field of 3×3 tensors as [3, 3, ...] (components first, elements last) so that every
# operation is an elementwise loop over the elements that XLA fuses and vectorises; `[..., 3, 3]` arrays from
# users are moved to this layout at the public functions.

def det3(a):
    """Determinant of [3, 3, ...] → [...]."""
    return (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
            - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
            + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))


def cofactor3(a):
    """Cofactor matrix cof(A) = det(A) A⁻ᵀ of [3, 3, ...], written out (cheap and differentiable)."""
    c = cofactor3_rows([[a[i, j] for j in range(3)] for i in range(3)])
    return jnp.stack([jnp.stack(row) for row in c])


def cofactor3_rows(a):
    """`cofactor3` of a matrix given as rows of components, a[i][j] [...] each, as the same nested lists."""
    return [[a[(i + 1) % 3][(j + 1) % 3] * a[(i + 2) % 3][(j + 2) % 3]
             - a[(i + 1) % 3][(j + 2) % 3] * a[(i + 2) % 3][(j + 1) % 3] for j in range(3)] for i in range(3)]


def inv3(a):
    cof = cofactor3(a)
    det = a[0, 0] * cof[0, 0] + a[0, 1] * cof[0, 1] + a[0, 2] * cof[0, 2]
    return transpose3(cof) / det


def transpose3(a):
    return jnp.swapaxes(a, 0, 1)


def matmul3(a, b):
    """[3, 3, ...] @ [3, 3, ...] as an elementwise sum (XLA fuses it; a batched dot of 3×3 blocks does not)."""
    return a[:, 0, None] * b[None, 0] + a[:, 1, None] * b[None, 1] + a[:, 2, None] * b[None, 2]


def trace3(a):
    return a[0, 0] + a[1, 1] + a[2, 2]


def _eye_like(a):
    return jnp.eye(3, dtype=a.dtype).reshape((3, 3) + (1,) * (a.ndim - 2))


def _lead(F):
    return jnp.moveaxis(jnp.moveaxis(jnp.asarray(F), -1, 0), -1, 0)


def _trail(a):
    return jnp.moveaxis(jnp.moveaxis(a, 0, -1), 0, -1)


# --- stresses (component-leading layout) ---------------------------------------------------------------------

def isochoric_pk2(m: Material, F):
    """Instantaneous isochoric 2nd Piola–Kirchhoff stress S⁰_iso [3, 3, ...], J [...] and C⁻¹ from F [3, 3, ...]."""
    C = matmul3(transpose3(F), F)
    J = det3(F)
    Cinv = inv3(C)
    j23 = J ** (-2.0 / 3.0)
    I1b = j23 * trace3(C)
    Sbar = 2.0 * (m.c10 + m.c01 * I1b) * _eye_like(F) - 2.0 * m.c01 * (j23 * C)
    trace_term = sum(Sbar[i, j] * C[i, j] for i in range(3) for j in range(3))
    S = j23 * (Sbar - (trace_term / 3.0) * Cinv)
    return S, J, Cinv


def pressure(m: Material, J):
    """Volumetric (Kirchhoff-per-J) pressure p = dU/dJ = 2 (J − 1) / D1, tension positive."""
    return 2.0 * (J - 1.0) / m.d1


def volumetric_energy(m: Material, J):
    return (J - 1.0) ** 2 / m.d1


def isochoric_energy(m: Material, F):
    """C10 (Ī1 − 3) + C01 (Ī2 − 3) per unit reference volume, F [3, 3, ...]."""
    C = matmul3(transpose3(F), F)
    J = det3(F)
    I1 = trace3(C)
    I2 = 0.5 * (I1 ** 2 - sum(C[i, j] * C[i, j] for i in range(3) for j in range(3)))
    return m.c10 * (J ** (-2.0 / 3.0) * I1 - 3.0) + m.c01 * (J ** (-4.0 / 3.0) * I2 - 3.0)


# --- public functions on user layout [..., 3, 3] -------------------------------------------------------------

def strain_energy_density(m: Material, F):
    """Instantaneous hyperelastic energy density U(F) per unit reference volume; F [..., 3, 3]."""
    Ft = _lead(F)
    return isochoric_energy(m, Ft) + volumetric_energy(m, det3(Ft))


def cauchy_stress(m: Material, F):
    """Instantaneous (elastic) Cauchy stress [..., 3, 3] of the hyperelastic base; F [..., 3, 3]."""
    Ft = _lead(F)
    S_iso, J, Cinv = isochoric_pk2(m, Ft)
    S = S_iso + (J * pressure(m, J)) * Cinv
    return _trail(matmul3(matmul3(Ft, S), transpose3(Ft)) / J)


def to_voigt(s):
    """[3, 3, ...] symmetric → [..., 6] in the order S11, S22, S33, S12, S13, S23."""
    return jnp.stack([s[0, 0], s[1, 1], s[2, 2], s[0, 1], s[0, 2], s[1, 2]], -1)
