"""fem: a jit-compiled, differentiable, total-Lagrangian explicit-dynamics FEM in JAX (the ground truth)."""
from .material import Material, cauchy_stress, mooney_rivlin, relaxation_modulus, strain_energy_density
from .mesh import box_hex_mesh, hex_to_tet, read_mesh, von_mises, write_series
from .meshes import beam_mesh, bunny_mesh
from .solver import (ElementInversionError, Energies, Loads, Problem, Result, check, internal_energy,
                     internal_force, lumped_mass, setup, simulate, simulate_batch, stable_time_step)

__all__ = [
    "Material", "mooney_rivlin", "cauchy_stress", "relaxation_modulus", "strain_energy_density",
    "box_hex_mesh", "hex_to_tet", "beam_mesh", "bunny_mesh", "read_mesh", "write_series", "von_mises",
    "Problem", "Loads", "Result", "Energies", "ElementInversionError",
    "setup", "simulate", "simulate_batch", "check", "internal_energy", "internal_force", "lumped_mass",
    "stable_time_step",
]
