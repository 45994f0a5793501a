"""Your own mesh, end to end with the CLI alone: generate → train → evaluate, demo, rollout to ParaView; and every
bad input refused in one line (exit code 2)."""
import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from fem import user_mesh as um
from fem.mesh import box_hex_mesh, hex_to_tet
from tignn_jax.cli import main

ROOT = Path(__file__).resolve().parents[1]
MATERIAL = ["--c10", "1e3", "--d1", "1e-4", "--density", "1e-2", "--damping", "10"]


def _write(path, points, cells, kind="hexahedron", **kw):
    meshio.write(path, meshio.Mesh(points, [(kind, cells)]), **kw)
    return str(path)


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """A 24 x 6 x 6 hex8 box of 12 x 3 x 3 cells (208 nodes) in a .vtu file."""
    p, c = box_hex_mesh((24.0, 6.0, 6.0), (12, 3, 3))
    return _write(tmp_path_factory.mktemp("mesh") / "box.vtu", p, c)


def _error(capsys, argv):
    """(exit code, the one line written to stderr) of a CLI call."""
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return code, err[0]


def test_whole_path_on_a_small_mesh(tmp_path, box, capsys):
    """generate (6 cases) → train linear → card; the model beats doing nothing on the held-out case against the
    FEM, and evaluate, demo and rollout --paraview run on it; the embedded recipe carries the mesh on a cage."""
    data, run = str(tmp_path / "box.npz"), str(tmp_path / "run")
    assert main(["generate", "mesh", "--mesh", box, *MATERIAL, "--clamp", "x=min", "--load", "fingertip,point",
                 "--force", "20", "--cases", "6", "--frames", "10", "--rise-frames", "5", "--out", data,
                 "--no-progress"]) == 0
    with np.load(data) as d:
        meta = json.loads(str(d["metadata"]))
        assert d["z"].shape == (6, 11, 208, 12) and d["cells"].shape == (108, 8)
        assert d["split_test"].tolist() == [6] and meta["clamped_nodes"] == 16
        assert [c["kind"] for c in meta["cases"]] == ["fingertip", "point"] * 3
        z_test, q0 = d["z"][5], d["q0"]
    assert main(["train", "--config", "linear", "--data", data, "--run-dir", run, "--set", "steps=2",
                 "--set", "val_every=1", "--no-progress"]) == 0
    card = json.loads((tmp_path / "run" / "model" / "card.json").read_text())
    assert card["evaluated_split"] == "test" and card["step_ms_median"] > 0
    assert "Test errors" in (tmp_path / "run" / "model" / "MODEL_CARD.md").read_text()
    import tignn_jax

    params, graph = tignn_jax.load_pretrained(run)            # a run folder loads as a model
    with np.load(data) as d:
        forces = d["f"][5]
    pred = np.asarray(tignn_jax.rollout(params, graph, forces))
    u_fem, u_model = z_test[-1, :, :3] - q0, pred[-1, :, :3] - q0
    err = np.linalg.norm(u_model - u_fem) / np.linalg.norm(u_fem)
    assert err < 0.2, err          # held-out case, last frame, against the FEM
    assert card["errors_of_peak"]["u"] < 0.2
    capsys.readouterr()
    assert main(["evaluate", "--model", run, "--data", data, "--splits", "test", "--no-structure"]) == 0
    assert main(["rollout", "--model", run, "--data", data, "--sims", "test", "--out",
                 str(tmp_path / "roll" / "r.npz"), "--paraview"]) == 0
    frame = meshio.read(tmp_path / "roll" / "r_case006_frames" / "frame_0010.vtu")
    assert {"u", "u_fem", "u_error", "von_mises"} <= set(frame.point_data)
    assert main(["demo", "--model", run, "--frames", "3", "--size", "160x120", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "scene own" in out and (tmp_path / "demo" / "own.gif").exists()
    # the same mesh carried by a cage of 4 × 1 × 1 cells of 6 (nothing fitted): it follows the FEM on the held-out
    # case, coarsely (a fingertip dents finer than one cell across), and keeps its clamped nodes where they are
    cage = str(tmp_path / "cage")
    assert main(["train", "--config", str(ROOT / "configs" / "embedded.py"), "--data", data, "--run-dir", cage,
                 "--set", "cell=6", "--no-progress", "--no-card"]) == 0
    params, graph = tignn_jax.load_pretrained(cage)
    assert params["model"].name == "embedded" and params["arrays"]["cage"]["q0"].shape == (20, 3)
    states = np.asarray(tignn_jax.rollout(params, graph, forces))
    clamped = params["mesh"]["node_type"] != 0
    assert np.abs(states[:, clamped, :3] - q0[clamped]).max() == 0.0
    err = np.linalg.norm(states[-1, :, :3] - q0 - u_fem) / np.linalg.norm(u_fem)
    assert err < 0.2, err          # measured 0.10
    capsys.readouterr()
    code, line = _error(capsys, ["train", "--config", "embedded", "--data", data, "--run-dir", str(tmp_path / "x"),
                                 "--set", "cell=-1"])
    assert code == 2 and "cell=-1" in line, line


def test_tet_mesh_from_gmsh_with_a_clamp_file(tmp_path):
    p, c = box_hex_mesh((8.0, 2.0, 2.0), (4, 1, 1))
    path = _write(tmp_path / "bar.msh", p, hex_to_tet(c), "tetra", file_format="gmsh22", binary=False)
    mesh = um.read_volume_mesh(path)
    assert mesh.cell_type == "tetra" and mesh.cells.shape == (24, 4)
    ids = tmp_path / "clamp.txt"
    ids.write_text("0, 5\n10 15")
    clamped = um.clamp_nodes(mesh.points, [str(ids)], mesh.file_ids)
    assert clamped.tolist() == [0, 5, 10, 15]
    np.testing.assert_array_equal(clamped, um.clamp_nodes(mesh.points, "x=min"))


def test_clamp_expressions():
    p, _ = box_hex_mesh((4.0, 2.0, 2.0), (2, 1, 1))
    assert len(um.clamp_nodes(p, "x=0")) == 4 and len(um.clamp_nodes(p, "x=max")) == 4
    assert len(um.clamp_nodes(p, "z<=0")) == 6 and len(um.clamp_nodes(p, "x>1")) == 8
    assert um.clamp_nodes(p, ["x=0", "x=4"]).tolist() == sorted(um.clamp_nodes(p, "x=min").tolist()
                                                                + um.clamp_nodes(p, "x=max").tolist())
    assert len(um.clamp_nodes(p, "box:1.5,0,0,2.5,2,2")) == 4
    for bad, said in (("x=7", "selects no node"), ("x>=0", "every node"), ("w=0", "not a plane"),
                      ("box:1,2", "six numbers"), ("z<min", "min and max go with '='")):
        with pytest.raises(ValueError, match=said):
            um.clamp_nodes(p, bad)


def test_pressure_loads_sum_to_pressure_times_area():
    """A pressure patch's nodal forces add up to −p Σ A n over the faces it loads, less the clamped nodes' shares (a
    face's force is spread equally over its four nodes), with the box's boundary faces enumerated here from its
    geometry: unit squares on top (four free nodes), on the clamped bottom (none) and on the sides (two of four)."""
    from fem.material import mooney_rivlin

    p, c = box_hex_mesh((4.0, 4.0, 1.0), (4, 4, 1))
    mesh = um.VolumeMesh(p, c, "hexahedron", np.arange(len(p)))
    scene = um.mesh_scene(mesh, mooney_rivlin(1.0, 0.0, 0.1), um.clamp_nodes(p, "z=min"), n_frames=4)
    faces = []                                                     # (centroid, outward normal, free share)
    for i in range(4):
        for j in range(4):
            faces += [((i + 0.5, j + 0.5, 1.0), (0, 0, 1), 1.0), ((i + 0.5, j + 0.5, 0.0), (0, 0, -1), 0.0)]
        for side, n in ((0.0, -1), (4.0, 1)):
            faces += [((side, i + 0.5, 0.5), (n, 0, 0), 0.5), ((i + 0.5, side, 0.5), (0, n, 0), 0.5)]
    f, info = um.mesh_forces(scene, ["pressure"], 3, 0, pressure=2.0, radius=0.8, rise_frames=2)
    for c_, case in enumerate(info):
        assert case["kind"] == "pressure" and 0.2 <= case["peak_pressure"] <= 2.0
        loaded = [(n, w) for x, n, w in faces if np.linalg.norm(np.subtract(x, p[case["centre"]])) <= case["radius"]]
        assert len(loaded) == case["faces"] >= 2
        expected = -case["peak_pressure"] * sum(w * np.asarray(n, float) for n, w in loaded)
        np.testing.assert_allclose(f[c_, -1].sum(axis=0), expected, atol=1e-9)
        np.testing.assert_allclose(f[c_, 1], f[c_, -1], rtol=1e-6)     # risen by frame 2, then held
    top = um.mesh_forces(scene, ["pressure"], 1, 3, pressure=1.0, radius=10.0, rise_frames=0)[0][0, -1]
    # radius 10 loads every boundary face: the closed surface's Σ A n = 0, less the clamped bottom's share
    assert abs(top.sum(axis=0)[0]) < 1e-5 and top.sum(axis=0)[2] < 0


def test_fingertip_and_point_levels(box):
    from fem.material import mooney_rivlin

    mesh = um.read_volume_mesh(box)
    scene = um.mesh_scene(mesh, mooney_rivlin(1e3, 0.0, 1e-4), um.clamp_nodes(mesh.points, "x=min"))
    f, info = um.mesh_forces(scene, ["fingertip", "point"], 8, 1, force=50.0)
    for c_, case in enumerate(info):
        peak = np.abs(np.linalg.norm(f[c_].sum(axis=1), axis=-1)).max()
        assert peak <= 50.0 * (1 + 1e-5) and peak >= 5.0 * (1 - 1e-5) - 1e-3
        assert np.all(f[c_][:, scene.node_type == 1] == 0)            # clamped nodes take no load
    with pytest.raises(ValueError, match="positive force"):
        um.mesh_forces(scene, ["point"], 2, 0)


@pytest.mark.parametrize("case", ["unreadable", "mixed", "unsupported", "inverted", "degenerate", "non-manifold",
                                  "empty-clamp", "all-clamped", "material", "no-force", "bad-load"])
def test_bad_input_is_one_line(tmp_path, box, capsys, case):
    p, c = box_hex_mesh((4.0, 2.0, 2.0), (2, 1, 1))
    path, extra = box, []
    if case == "unreadable":
        path = tmp_path / "bad.vtu"
        path.write_text("not a mesh")
        said = "meshio cannot read it"
    elif case == "mixed":
        tets = hex_to_tet(c[:1])
        path = str(tmp_path / "mixed.vtu")
        meshio.write(path, meshio.Mesh(p, [("hexahedron", c[1:]), ("tetra", tets)]))
        said = "mixed volume cells"
    elif case == "unsupported":
        path = _write(tmp_path / "wedge.vtu", p, c[:, :6], "wedge")
        said = "unsupported cells 'wedge'"
    elif case == "inverted":
        bad = c.copy()
        bad[0] = bad[0][[4, 5, 6, 7, 0, 1, 2, 3]]
        path, said = _write(tmp_path / "inv.vtu", p, bad), "1 inverted elements"
    elif case == "degenerate":
        q = p.copy()
        q[c[0]] = q[c[0][0]]      # every node of cell 0 at one point (also squashes cell 1's shared face)
        path, said = _write(tmp_path / "deg.vtu", q, c), "degenerate elements"
    elif case == "non-manifold":
        q, cc = box_hex_mesh((4.0, 4.0, 2.0), (2, 2, 1))
        path, said = _write(tmp_path / "nm.vtu", q, cc[[0, 3]]), "not manifold"   # two cubes touching at an edge
        extra = ["--clamp", "x=max"]
    elif case == "empty-clamp":
        extra, said = ["--clamp", "x=-3"], "selects no node"
    elif case == "all-clamped":
        extra, said = ["--clamp", "x>=0"], "every node"
    elif case == "material":
        said = "d1 must be positive"
    elif case == "no-force":
        said = "--force is required"
    else:
        extra, said = ["--load", "finger"], "--load 'finger'"
    argv = ["generate", "mesh", "--mesh", str(path), "--out", str(tmp_path / "x.npz"), "--no-progress",
            "--c10", "1e3", "--d1", "-1" if case == "material" else "1e-4", "--density", "1"]
    argv += extra or ["--clamp", "x=min"]
    if case != "no-force":
        argv += ["--force", "1"]
    code, line = _error(capsys, argv)
    assert code == 2 and said in line and line.startswith("tignn generate: error:"), line


def test_model_on_another_mesh_is_refused(tmp_path, capsys):
    """A shipped beam model against a data file of another mesh: one line, exit 2."""
    p, c = box_hex_mesh((4.0, 2.0, 2.0), (2, 1, 1))
    path = tmp_path / "d.npz"
    from fem.meshes import mesh_edges

    np.savez(path, q0=p.astype(np.float32), edges=mesh_edges(c), node_type=np.zeros(len(p), np.int8),
             z=np.zeros((1, 2, len(p), 12), np.float32), f=np.zeros((1, 1, len(p), 3), np.float32), dt=0.05,
             sim_id=np.array([1], np.int32), split_test=np.array([1], np.int32))
    code, line = _error(capsys, ["evaluate", "--model", "beam-linear", "--data", str(path), "--splits", "test"])
    assert code == 2 and "another mesh" in line
