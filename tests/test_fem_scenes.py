"""Scenes, load cases, body-body contact and data generation (issue: scenes and data)."""
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem
from fem import cases, scenes, solver
from fem.generate import run_cases

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "abaqus_beam.npz"


def test_beam_scene_is_the_papers_beam():
    """500 hex8, 756 nodes, 36 clamped on x = 0, the paper's Mooney–Rivlin and Prony constants."""
    sc = scenes.beam_scene(prony=True, tau_scale=1.0)
    assert sc.points.shape == (756, 3) and sc.cells.shape == (500, 8)
    assert sc.node_type.sum() == 36 and np.all(sc.points[sc.node_type == 1, 0] == 0)
    m = sc.material
    np.testing.assert_allclose([m.c10, m.c01, m.d1], [1.5e5, 5e3, 1e-7], rtol=1e-6)
    np.testing.assert_allclose(m.g, [0.3, 0.49]); np.testing.assert_allclose(m.tau, [0.2, 0.5])
    np.testing.assert_allclose(scenes.beam_scene(prony=True).material.tau, scenes.BEAM_TAU_SCALE * np.array([0.2, 0.5]))


@pytest.mark.skipif(not REFERENCE.exists(), reason="reference data ../shared/data/abaqus_beam.npz not present")
def test_reference_forces_equal_the_abaqus_forces():
    """Our 52 load cases are exactly the reference's nodal forces (same nodes, direction, ramp)."""
    ref = np.load(REFERENCE)
    ours = scenes.beam_reference_forces(scenes.beam_scene(), np.arange(1, 53))
    np.testing.assert_allclose(ours, ref["f"], rtol=0, atol=1e-3)


def test_reference_forces_continue_past_the_ramp():
    """after=K: the 20-frame ramp unchanged, then K frames of the final load (hold) or none (release)."""
    sc = scenes.beam_scene()
    ramp = scenes.beam_reference_forces(sc, [3, 30])
    hold = scenes.beam_reference_forces(sc, [3, 30], after=5, mode="hold")
    release = scenes.beam_reference_forces(sc, [3, 30], after=5, mode="release")
    assert hold.shape == (2, 25, 756, 3) and release.shape == hold.shape
    np.testing.assert_array_equal(hold[:, :20], ramp)
    np.testing.assert_array_equal(release[:, :20], ramp)
    np.testing.assert_array_equal(hold[:, 20:], np.repeat(ramp[:, -1:], 5, axis=1))
    assert not release[:, 20:].any() and ramp[:, -1].any()
    with pytest.raises(ValueError, match="'push'"):
        scenes.beam_reference_forces(sc, [3], after=5, mode="push")
    with pytest.raises(ValueError, match="-1"):
        scenes.beam_reference_forces(sc, [3], after=-1)


def test_face_maps_take_each_reference_case_to_its_images():
    """The isometry of face g maps the loads of sim s (face 0) onto those of sim 13g + s exactly, and the rest
    state onto itself (q = X, v = 0, σ = 0 at the permuted nodes); a map that is no symmetry of the mesh raises."""
    sc = scenes.beam_scene()
    f = scenes.beam_reference_forces(sc, np.arange(1, 14))
    rest = np.concatenate([sc.points, np.zeros((756, 9))], axis=1)
    for g, (rot, shift) in enumerate(scenes.BEAM_FACE_MAPS):
        z_m, f_m = scenes.mirror_case(np.broadcast_to(rest, (13, 756, 12)), f, sc.points, rot, shift)
        np.testing.assert_allclose(f_m, scenes.beam_reference_forces(sc, np.arange(13 * g + 1, 13 * g + 14)),
                                   atol=1e-9)
        np.testing.assert_allclose(z_m, np.broadcast_to(rest, z_m.shape), atol=1e-12)
    with pytest.raises(ValueError, match="does not map the mesh"):
        scenes.mirror_case(rest, f[0], sc.points, np.diag([-1.0, 1, 1]), np.zeros(3))   # x -> -x: off the mesh
    with pytest.raises(ValueError, match=r"\[\.\.\., 756, 12\]"):
        scenes.mirror_case(rest[:, :6], f[0], sc.points, *scenes.BEAM_FACE_MAPS[1])
    with pytest.raises(ValueError, match="orthogonal"):
        scenes.mirror_case(rest, f[0], sc.points, 2 * np.eye(3), np.zeros(3))


@pytest.mark.skipif(not REFERENCE.exists(), reason="reference data ../shared/data/abaqus_beam.npz not present")
def test_face_maps_reproduce_the_abaqus_cases():
    """The four face groups of the reference data are exact images: mapping sims 1..13 by the face maps
    reproduces sims 14..52 (q, v, σ relative L2 ≤ 1e-6, forces exactly)."""
    ref = np.load(REFERENCE)
    q0 = ref["q0"].astype(np.float64)
    for g, (rot, shift) in enumerate(scenes.BEAM_FACE_MAPS[1:], start=1):
        z_m, f_m = scenes.mirror_case(ref["z"][:13], ref["f"][:13], q0, rot, shift)
        truth = ref["z"][13 * g:13 * g + 13].astype(np.float64)
        for a, b in ((0, 3), (3, 6), (6, 12)):
            assert np.linalg.norm(z_m[..., a:b] - truth[..., a:b]) <= 1e-6 * np.linalg.norm(truth[..., a:b])
        np.testing.assert_array_equal(f_m, ref["f"][13 * g:13 * g + 13])


def test_fingertip_cases_are_patches_pushing_inwards():
    """Patches of 1–6 free surface nodes, direction within 30° of the inward normal, peak ≤ the reference max."""
    sc = scenes.beam_scene()
    f, described = cases.fingertip_forces(sc, 24, seed=3)
    f2, _ = cases.fingertip_forces(sc, 24, seed=3)
    np.testing.assert_array_equal(f, f2)
    nodes, normals = fem.meshes.surface_nodes_and_normals(sc.points, sc.cells)
    normal_of = dict(zip(nodes.tolist(), normals))
    assert {d["profile"] for d in described} <= set(cases.PROFILES)
    for c, d in enumerate(described):
        assert 1 <= len(d["nodes"]) <= 6
        assert np.all(sc.node_type[d["nodes"]] == 0)
        assert np.all(f[c][:, sc.node_type == 1] == 0)
        total = np.linalg.norm(f[c].sum(axis=1), axis=-1).max()
        assert total <= 600_000 * (1 + 1e-9)
        cosang = -np.dot(d["direction"], normal_of[d["nodes"][0]])
        assert cosang >= np.cos(np.radians(30)) - 1e-9


def test_smooth_fingertip_cases_keep_the_draws_and_have_no_jumps_in_loading_rate():
    """smooth=True draws the same patches, directions and peaks; its force histories have no kinks: the largest
    change of the per-frame force increment is a fraction of the piecewise-linear histories' (whose ramp starts
    from zero at full rate and whose release and move jump)."""
    sc = scenes.beam_scene()
    rough, described = cases.fingertip_forces(sc, 24, seed=3)
    smooth, described_s = cases.fingertip_forces(sc, 24, seed=3, smooth=True)
    assert described == described_s
    assert np.array_equal(np.abs(rough).sum(axis=1) > 0, np.abs(smooth).sum(axis=1) > 0)   # same loaded nodes
    for c, d in enumerate(described):
        peak = np.abs(smooth[c]).max()
        np.testing.assert_allclose(peak, np.abs(rough[c]).max(), rtol=1e-9)   # every profile reaches the peak
        padded = lambda f: np.concatenate([np.zeros_like(f[:2]), f])     # the force is 0 before frame 1
        kink = lambda f: np.abs(np.diff(padded(f), n=2, axis=0)).max() / peak
        assert kink(smooth[c]) < 0.75 * kink(rough[c]) + 1e-12, (d["profile"], kink(smooth[c]), kink(rough[c]))
        assert np.abs(np.diff(padded(smooth[c]), axis=0)).max() <= 0.6 * peak   # no jump (move: a cross-fade)


def test_bunny_point_loads_are_unit_and_normal():
    """Each case is one unit force on one free surface node, along the inward normal, over all frames."""
    sc = scenes.bunny_scene()
    f, picked = cases.point_load_forces(sc, 10, seed=1)
    assert len(set(picked.tolist())) == 10
    mags = np.linalg.norm(f, axis=-1)
    assert np.all((mags > 0).sum(axis=-1) == 1)
    np.testing.assert_allclose(mags.max(axis=-1), 1.0)
    with pytest.raises(ValueError, match="not free surface nodes"):
        cases.point_load_forces(sc, load_nodes=[int(np.where(sc.node_type == 1)[0][0])])


def test_bunny_point_load_rises_smoothly_then_holds():
    """A press that rises by the C¹ smooth step over R frames and then holds the unit load."""
    sc = scenes.bunny_scene()
    f, picked = cases.point_load_forces(sc, 3, seed=1, rise_frames=8)
    amp = np.linalg.norm(f[:, :, picked[0]], axis=-1)[0]
    s = np.minimum(np.arange(1, sc.n_frames + 1) / 8, 1.0)
    np.testing.assert_allclose(amp, s * s * (3 - 2 * s), atol=1e-12)
    assert np.all(np.diff(amp) >= 0) and amp[7] == 1.0 and amp[-1] == 1.0
    with pytest.raises(ValueError, match="rise_frames"):
        cases.point_load_forces(sc, 3, rise_frames=sc.n_frames + 1)


def _two_cubes(gap=0.5, contact=True):
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    pts_b = pts + np.array([0.0, 0.0, 1.0 + gap])
    points = np.concatenate([pts, pts_b])
    allc = np.concatenate([cells, cells + len(pts)])
    mat = fem.mooney_rivlin(10.0, 0.0, 0.01, density=1.0)
    ctc = dict(a=np.arange(len(pts)), b=np.arange(len(pts), 2 * len(pts)), r0=0.3, stiffness=500.0, skin=0.3,
               capacity=512) if contact else None
    return points, allc, mat, ctc


def test_contact_forces_are_equal_and_opposite():
    """Penalty contact is an internal force of the pair of bodies: the forces sum to zero (momentum)."""
    points, cells, mat, ctc = _two_cubes(gap=0.1)
    pb = fem.setup(points, cells, material=mat, frame_dt=0.01, n_frames=1, contact=ctc)
    pairs, over = solver._contact_pairs(pb.arrays, jnp.asarray(points), 512)
    f = solver._contact_force(pb.arrays, pairs, jnp.asarray(points))
    assert not bool(over)
    assert float(jnp.abs(f).max()) > 0
    np.testing.assert_allclose(np.asarray(f.sum(0)), 0.0, atol=1e-9 * float(jnp.abs(f).max()))


def test_contact_force_is_minus_gradient_of_contact_energy():
    """The penalty force derives from the potential ½k(r0−d)², so energy is conserved through contact."""
    with jax.enable_x64(True):
        points, cells, mat, ctc = _two_cubes(gap=0.1)
        pb = fem.setup(points, cells, material=mat, frame_dt=0.01, n_frames=1, contact=ctc)
        x = jnp.asarray(points) + 0.01 * jax.random.normal(jax.random.PRNGKey(0), points.shape)
        pairs, _ = solver._contact_pairs(pb.arrays, x, 512)
        g = jax.grad(lambda y: solver._contact_energy(pb.arrays, y))(x)
        np.testing.assert_allclose(np.asarray(solver._contact_force(pb.arrays, pairs, x)), -np.asarray(g), atol=1e-9)


def test_colliding_bodies_conserve_momentum_and_energy():
    """Two free cubes thrown at each other: total momentum is constant and the energy balance closes."""
    with jax.enable_x64(True):
        points, cells, mat, ctc = _two_cubes(gap=0.5)
        pb = fem.setup(points, cells, material=mat, frame_dt=0.05, n_frames=10, contact=ctc)
        n = len(points) // 2
        v0 = np.zeros_like(points)
        v0[:n, 2], v0[n:, 2] = 1.0, -1.0
        res = fem.simulate(pb, mat, fem.Loads(v0=jnp.asarray(v0)))
        m = np.asarray(fem.lumped_mass(pb, mat))[:, None]
        p = (m * np.asarray(res.v)).sum(axis=1)
        assert np.abs(p - p[0]).max() < 1e-9
        e = res.energies
        total = np.asarray(e.kinetic + e.strain + e.viscous + e.damping - e.external)
        assert np.abs(total - total[0]).max() < 1e-2 * total[0]
        assert float(e.strain.max()) > 0.05 * total[0], "the bodies never touched"
        gap_end = np.asarray(res.q[-1, n:, 2]).min() - np.asarray(res.q[-1, :n, 2]).max()
        assert gap_end > 0.0, "the bodies interpenetrated"
        assert not bool(res.contact_overflow)


def test_generation_writes_the_data_format_and_resumes(tmp_path, monkeypatch):
    """A generated file has the reference keys plus cells/cell_type/metadata; finished cases are not rerun."""
    pts, cells = fem.box_hex_mesh((4.0, 1.0, 1.0), (4, 1, 1))
    mat = fem.mooney_rivlin(100.0, 0.0, 0.01, density=1.0)
    node_type = (pts[:, 0] == 0).astype(np.int8)
    edges = fem.meshes.mesh_edges(cells)
    sc = scenes.Scene("bar", pts, cells, "hexahedron", edges, node_type, mat, 0.05, 3, 0.0, "step")
    pb = scenes.setup_scene(sc)
    forces = np.zeros((3, 3, len(pts), 3))
    forces[:, :, pts[:, 0] == 4.0, 1] = np.array([1.0, 2.0, 3.0])[:, None, None]
    out = run_cases(sc, pb, forces, tmp_path / "d.npz", batch_size=2, progress=False)
    d = np.load(out)
    assert d["z"].shape == (3, 4, len(pts), 12) and d["f"].shape == (3, 3, len(pts), 3)
    assert str(d["cell_type"]) == "hexahedron" and '"scene": "bar"' in str(d["metadata"])
    np.testing.assert_allclose(d["z"][:, :, :, 3:6], np.gradient(d["z"][:, :, :, :3], 0.05, axis=1, edge_order=2),
                               atol=1e-4)
    tip = np.abs(d["z"][:, -1, pts[:, 0] == 4.0, 1]).mean(1)
    assert tip[0] < tip[1] < tip[2]
    calls = []
    monkeypatch.setattr("fem.generate.simulate_batch", lambda *a, **k: calls.append(1))
    run_cases(sc, pb, forces, tmp_path / "d.npz", batch_size=2, progress=False)
    assert calls == []
    monkeypatch.undo()
    # The same parts assembled with the solver's velocity: z's v is v_solver, zero at the rest start.
    out = run_cases(sc, pb, forces, tmp_path / "d.npz", batch_size=2, progress=False, velocity="solver")
    d = np.load(out)
    np.testing.assert_array_equal(d["z"][..., 3:6], d["v_solver"])
    assert np.all(d["z"][:, 0, :, 3:6] == 0) and "v_solver" in str(d["metadata"])
    with pytest.raises(ValueError, match="velocity"):
        run_cases(sc, pb, forces, tmp_path / "d.npz", velocity="central")
    # Two workers share the cases (c mod 2); only the one that finds every part present writes the file.
    assert run_cases(sc, pb, forces, tmp_path / "w.npz", batch_size=1, progress=False, worker=(0, 2),
                     velocity="solver") is None
    assert sorted(p.name for p in (tmp_path / "w.npz.parts").iterdir()) == ["case_00000.npz", "case_00002.npz"]
    out = run_cases(sc, pb, forces, tmp_path / "w.npz", batch_size=1, progress=False, worker=(1, 2), velocity="solver")
    np.testing.assert_allclose(np.load(out)["z"], d["z"], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="worker"):
        run_cases(sc, pb, forces, tmp_path / "w.npz", worker=(2, 2))


def test_paraview_series_reads_back(tmp_path):
    """The .pvd + VTU frames written for ParaView hold the displacement, velocity and stress of each frame."""
    import meshio

    pts, cells = fem.box_hex_mesh((2.0, 1.0, 1.0), (2, 1, 1))
    T = 3
    q = pts[None] + np.arange(T)[:, None, None] * 0.1
    v = np.ones((T, len(pts), 3))
    sig = np.zeros((T, len(pts), 6))
    sig[..., 0] = 2.0
    pvd = fem.write_series(tmp_path / "run.pvd", pts, cells, "hexahedron", np.arange(T) * 0.5, q, v, sig)
    assert 'timestep="1.0"' in pvd.read_text()
    m = meshio.read(tmp_path / "run_frames" / "frame_0002.vtu")
    np.testing.assert_allclose(m.point_data["u"], 0.2)
    np.testing.assert_allclose(m.point_data["von_mises"], 2.0)
    assert m.cells[0].type == "hexahedron"


def test_bunny_fingertip_cases_stay_on_the_free_surface():
    """Fingertip patches on the bunny avoid the clamped base and stay within the peak of six unit loads."""
    sc = scenes.bunny_scene()
    f, described = cases.fingertip_forces(sc, 8, seed=2, peak_total=6.0)
    for c, d in enumerate(described):
        assert np.all(sc.node_type[d["nodes"]] == 0)
        assert np.linalg.norm(f[c].sum(axis=1), axis=-1).max() <= 6.0 * (1 + 1e-9)


def test_generated_data_carry_train_val_test_splits():
    # The 52 reference cases get the published split; other data a disjoint 80/10/10 split covering all ids.
    from fem.generate import PUBLISHED_TEST, PUBLISHED_VAL, default_splits, held_out_rows

    ref = default_splits(np.arange(1, 53))
    assert ref["test"].tolist() == list(PUBLISHED_TEST) and ref["val"].tolist() == list(PUBLISHED_VAL)
    assert len(ref["train"]) == 41
    other = default_splits(np.arange(1, 101))
    assert [len(other[k]) for k in ("train", "val", "test")] == [80, 10, 10]
    assert sorted(np.concatenate(list(other.values())).tolist()) == list(range(1, 101))
    assert held_out_rows(100).tolist() == list(range(80, 100))   # 0-based rows of val then test
    assert sorted((held_out_rows(52) + 1).tolist()) == sorted(PUBLISHED_VAL + PUBLISHED_TEST)


def test_multi_point_loads_are_apart_and_avoid_held_out_positions():
    """K unit inward normal loads per case, on free surface nodes ≥ min_hops edges apart, none within
    exclude_hops edges of an excluded node; the same seed gives the same cases; impossible requests raise."""
    sc = scenes.bunny_scene()
    held, _ = cases.point_load_forces(sc, 5, seed=2)
    held_nodes = np.where(np.abs(held[:, -1]).sum(axis=(0, 2)) > 0)[0]
    f, picked = cases.multi_point_load_forces(sc, 6, 4, seed=1, exclude_nodes=held_nodes, min_hops=8)
    f2, picked2 = cases.multi_point_load_forces(sc, 6, 4, seed=1, exclude_nodes=held_nodes, min_hops=8)
    np.testing.assert_array_equal(f, f2)
    assert picked.shape == (6, 4)
    hops = fem.meshes.hop_distances(sc.edges, len(sc.points))
    nodes, normals = fem.meshes.surface_nodes_and_normals(sc.points, sc.cells)
    normal_of = dict(zip(nodes.tolist(), normals))
    for c in range(6):
        loaded = np.where(np.linalg.norm(f[c, -1], axis=-1) > 0)[0]
        assert sorted(loaded) == sorted(picked[c])
        assert np.all(sc.node_type[loaded] == 0)
        assert hops[np.ix_(loaded, loaded)][~np.eye(4, dtype=bool)].min() >= 8
        assert hops[np.ix_(loaded, held_nodes)].min() > 2
        for i in loaded:
            np.testing.assert_allclose(f[c, -1, i], -normal_of[int(i)], atol=1e-12)
    with pytest.raises(ValueError, match="cannot place"):
        cases.multi_point_load_forces(sc, 1, 50, seed=0, min_hops=30)


def test_patch_load_spreads_the_unit_force_over_the_surface_near_the_position():
    """radius > 0: the same positions as the point loads, total force = the unit inward normal of the position,
    on free surface nodes within the radius only, weights falling with distance; a bad radius raises."""
    sc = scenes.bunny_scene()
    point, nodes = cases.point_load_forces(sc, 4, seed=3, rise_frames=5)
    patch, nodes2 = cases.point_load_forces(sc, 4, seed=3, rise_frames=5, radius=5.0)
    np.testing.assert_array_equal(nodes, nodes2)
    np.testing.assert_allclose(patch.sum(axis=2), point.sum(axis=2), atol=1e-12)
    surf, _ = fem.meshes.surface_nodes_and_normals(sc.points, sc.cells)
    for c, centre in enumerate(nodes):
        mag = np.linalg.norm(patch[c, -1], axis=-1)
        loaded = np.where(mag > 0)[0]
        d = np.linalg.norm(sc.points[loaded] - sc.points[centre], axis=1)
        assert len(loaded) > 1 and np.all(d < 5.0) and np.all(np.isin(loaded, surf))
        assert np.all(sc.node_type[loaded] == 0)
        assert mag[centre] == mag.max()
        order = np.argsort(d)
        assert np.all(np.diff(mag[loaded][order]) <= 1e-15)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="radius must be a finite number"):
            cases.point_load_forces(sc, 2, radius=bad)
