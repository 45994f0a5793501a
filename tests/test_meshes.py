"""The scene meshes: the reference beam (node order of the Abaqus data set) and the Stanford bunny."""
from pathlib import Path

import numpy as np
import pytest

from fem import meshes

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "abaqus_beam.npz"


@pytest.fixture(scope="module")
def reference():
    if not REFERENCE.exists():
        pytest.skip(f"reference data set not found at {REFERENCE} (it lives outside the repository)")
    with np.load(REFERENCE) as data:
        return {k: data[k] for k in ("q0", "edges", "node_type", "f")}


@pytest.fixture(scope="module")
def beam():
    return meshes.beam_mesh()


@pytest.fixture(scope="module")
def bunny():
    return meshes.bunny_mesh()


def _edge_set(edges):
    return set(map(tuple, np.asarray(edges).T.tolist()))


def _closed_surface_divergence(q0, cells):
    """(sum over boundary triangles of area * n . centroid, 3 * volume): equal for a closed outward surface."""
    tri = meshes.surface_triangles(cells)
    x = q0[tri]
    area_normal = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return np.sum(area_normal * x.mean(1)), 3.0 * meshes.cell_volumes(q0, cells).sum()


def _boundary_edge_use(cells):
    tri = meshes.surface_triangles(cells)
    undirected = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    return counts


# --- the beam ---

def test_beam_nodes_in_reference_order(beam, reference):
    # The learned simulator compares node by node with the Abaqus data, so our nodes must be theirs.
    q0, _, _ = beam
    np.testing.assert_allclose(q0, reference["q0"], atol=1e-6, rtol=0)


def test_beam_edges_equal_reference_edges(beam, reference):
    # Same mesh, same numbering: the graph must be the reference graph, here even in the same array order.
    _, _, edges = beam
    assert _edge_set(edges) == _edge_set(reference["edges"])
    np.testing.assert_array_equal(edges, reference["edges"])


def test_beam_clamped_nodes_are_reference_clamped_nodes(beam, reference):
    # The encastre of the reference is the face x = 0.
    q0, _, _ = beam
    np.testing.assert_array_equal(meshes.beam_node_type(q0), reference["node_type"])


def test_beam_load_lines_are_where_reference_forces_act(beam, reference):
    # Each reference case loads one line of 6 nodes with equal forces along one axis, into the beam.
    q0, _, _ = beam
    for sim_id in range(1, 53):
        nodes, direction = meshes.beam_reference_load(q0, sim_id)
        force = reference["f"][sim_id - 1, 0]
        assert set(np.flatnonzero(np.abs(force).sum(1))) == set(nodes.tolist()), sim_id
        unit = force[nodes] / np.linalg.norm(force[nodes], axis=1, keepdims=True)
        np.testing.assert_allclose(unit, np.broadcast_to(direction, unit.shape), atol=1e-6)


def test_beam_has_1980_edges_of_length_2(beam):
    # A 21x6x6 grid has 20*6*6 + 21*5*6 + 21*6*5 = 1980 edges; the graph holds both directions.
    q0, cells, edges = beam
    assert cells.shape == (500, 8) and cells.dtype == np.int32
    assert edges.shape == (2, 3960) and edges.dtype == np.int32
    assert _edge_set(edges) == {(b, a) for a, b in _edge_set(edges)}
    np.testing.assert_allclose(np.linalg.norm(q0[edges[0]] - q0[edges[1]], axis=1), 2.0)


@pytest.mark.parametrize("order", ["reference", "lexicographic"])
def test_beam_hex_volumes_positive_and_fill_the_block(order):
    # Every hex is a 2x2x2 cube in VTK order (volume +8); together they fill 40x10x10.
    q0, cells, _ = meshes.beam_mesh(order)
    volumes = meshes.cell_volumes(q0, cells)
    np.testing.assert_allclose(volumes, 8.0)
    assert len(np.unique(cells)) == 756


def test_reference_permutation_maps_lexicographic_onto_reference_order(beam):
    # Both orders describe the same mesh: renumbering one gives the other's nodes and cells.
    q0, cells, _ = beam
    q_lex, cells_lex, _ = meshes.beam_mesh("lexicographic")
    perm = meshes.reference_permutation(q0, q_lex)
    np.testing.assert_array_equal(q_lex[perm], q0)
    new_id = np.empty_like(perm)
    new_id[perm] = np.arange(len(perm))
    assert {tuple(c) for c in new_id[cells_lex].tolist()} == {tuple(c) for c in cells.tolist()}


def test_reference_permutation_rejects_other_coordinates(beam):
    q0, _, _ = beam
    with pytest.raises(ValueError, match="tol"):
        meshes.reference_permutation(q0 + np.array([0.5, 0.0, 0.0]), q0)


def test_beam_surface_is_closed_with_outward_normals(beam):
    # Divergence theorem: the closed outward surface integral of x . n equals 3 V = 3 * 4000.
    q0, cells, _ = beam
    assert np.all(_boundary_edge_use(cells) == 2)
    flux, three_volume = _closed_surface_divergence(q0, cells)
    np.testing.assert_allclose(flux, 12000.0, rtol=1e-12)
    np.testing.assert_allclose(three_volume, 12000.0, rtol=1e-12)


def test_beam_face_node_normal_is_the_face_normal(beam):
    # A node inside the face y = 10 (not on an edge of the block) has the face's outward normal +y.
    q0, cells, _ = beam
    nodes, normals = meshes.surface_nodes_and_normals(q0, cells)
    assert len(nodes) == 756 - 19 * 4 * 4
    on_top = np.isclose(q0[nodes, 1], 10.0) & np.isclose(q0[nodes, 0], 20.0) & np.isclose(q0[nodes, 2], 4.0)
    np.testing.assert_allclose(normals[on_top], [[0.0, 1.0, 0.0]], atol=1e-12)


def test_mesh_edges_rejects_unknown_cell_shape():
    with pytest.raises(ValueError, match="cells"):
        meshes.mesh_edges(np.zeros((3, 5), np.int32))


# --- the bunny ---

def test_bunny_counts_close_to_paper(bunny):
    # The paper's bunny has 1352 nodes and 4941 linear tets; ours is within 15 %.
    q0, cells, edges = bunny
    assert abs(len(q0) / 1352 - 1) <= 0.15
    assert abs(len(cells) / 4941 - 1) <= 0.15
    assert q0.dtype == np.float64 and cells.dtype == np.int32 and cells.shape[1] == 4
    assert edges.shape[0] == 2 and _edge_set(edges) == {(b, a) for a, b in _edge_set(edges)}


def test_bunny_tets_have_positive_volume_and_use_every_node(bunny):
    # Inverted or orphan elements would make the explicit FEM meaningless.
    q0, cells, _ = bunny
    assert np.all(meshes.cell_volumes(q0, cells) > 0)
    assert np.array_equal(np.unique(cells), np.arange(len(q0)))


def test_bunny_tets_have_no_slivers(bunny):
    # A sliver would set a tiny stable time step for the whole explicit run.
    q0, cells, _ = bunny
    x = q0[cells]
    volume = meshes.cell_volumes(q0, cells)
    face_areas = np.stack([0.5 * np.linalg.norm(np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a]), axis=1)
                           for a, b, c in meshes.TET_FACES], axis=1)
    height = 3.0 * volume / face_areas.max(1)
    assert height.min() > 0.15 * np.median(height)


def test_bunny_surface_is_closed(bunny):
    # Every edge of a watertight surface is shared by exactly two boundary triangles.
    _, cells, _ = bunny
    assert np.all(_boundary_edge_use(cells) == 2)


def test_bunny_normals_point_outward(bunny):
    # Divergence theorem: the outward surface integral of x . n equals 3 V.
    q0, cells, _ = bunny
    flux, three_volume = _closed_surface_divergence(q0, cells)
    np.testing.assert_allclose(flux, three_volume, rtol=1e-10)
    nodes, normals = meshes.surface_nodes_and_normals(q0, cells)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-12)
    top = nodes[np.argmax(q0[nodes, 2])]
    assert normals[nodes == top][0, 2] > 0.5


def test_bunny_stands_on_a_flat_base_of_bottom_nodes(bunny):
    # The clamped set is the flat base z = 0: several surface nodes whose normals point down.
    q0, cells, _ = bunny
    bottom = meshes.bunny_bottom_nodes(q0)
    assert len(bottom) >= 10
    np.testing.assert_array_equal(q0[bottom, 2], 0.0)
    assert q0[:, 2].min() == 0.0
    nodes, normals = meshes.surface_nodes_and_normals(q0, cells)
    assert set(bottom.tolist()) <= set(nodes.tolist())
    assert np.all(normals[np.isin(nodes, bottom), 2] < 0.0)


def test_bunny_file_is_small_and_credited():
    # The mesh ships in the package; the scan's source must be credited.
    assert meshes.BUNNY_FILE.stat().st_size < 200 * 1024
    with np.load(meshes.BUNNY_FILE) as data:
        assert "Stanford 3D Scanning Repository" in str(data["credit"])
        assert "Stanford University Computer Graphics Laboratory" in str(data["credit"])
