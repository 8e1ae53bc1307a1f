import numpy as np
import pytest
import torch
import trimesh
from conftest import F64

from cfd_torch import BSH
from cfd_torch.rotation import rotation_derivatives, rotation_matrix, transform_points


def test_rotation_derivatives_match_forward_mode_autodiff():
    g = torch.Generator().manual_seed(3)
    w = torch.cat(
        [torch.zeros(1, 3, dtype=F64), 1e-6 * torch.randn(2, 3, generator=g, dtype=F64),
         0.4 * torch.randn(3, 3, generator=g, dtype=F64), 2.5 * torch.randn(3, 3, generator=g, dtype=F64)]
    )  # fmt: skip
    R, dR, d2R = rotation_derivatives(w)
    jac = torch.func.jacfwd(rotation_matrix)
    torch.testing.assert_close(R, rotation_matrix(w), rtol=0, atol=1e-15)
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=F64).expand(len(w), 3, 3), rtol=0, atol=1e-14
    )
    torch.testing.assert_close(dR, torch.func.vmap(jac)(w), rtol=0, atol=1e-13)
    torch.testing.assert_close(d2R, torch.func.vmap(torch.func.jacfwd(jac))(w), rtol=0, atol=1e-12)
    assert dR.abs().amax() > 0 and d2R.abs().amax() > 0
    # the coefficient switch at theta^2 = 0.25 is continuous to rounding
    t = torch.tensor([[0.5 - 1e-12, 0, 0], [0.5 + 1e-12, 0, 0]], dtype=F64)
    _, dRt, d2Rt = rotation_derivatives(t)
    assert (dRt[0] - dRt[1]).abs().max() < 1e-10 and (d2Rt[0] - d2Rt[1]).abs().max() < 1e-10


def test_transform_points():
    pose = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, np.pi / 2], dtype=F64)
    x = transform_points(pose, torch.tensor([[1.0, 0.0, 0.0]], dtype=F64))
    torch.testing.assert_close(x, torch.tensor([[1.0, 3.0, 3.0]], dtype=F64))


@pytest.mark.parametrize(
    "mesh", [trimesh.creation.icosphere(subdivisions=2), trimesh.creation.torus(1.0, 0.3)]
)
def test_bsh_spheres_contain_their_vertices_and_centres_lie_in_the_hull(mesh):
    b = BSH.from_trimesh(mesh)
    F = len(mesh.faces)
    assert b.num_faces == F and b.num_nodes == 2 * F - 1
    assert int(b.depth.max()) == int(np.ceil(np.log2(F)))  # balanced
    assert ((b.tri >= 0) == (b.child[:, 0] < 0)).all()
    assert sorted(b.tri[b.tri >= 0].tolist()) == list(range(F))
    # collect each node's vertices bottom-up and check the centre/radius rules
    verts = {}
    for node in reversed(range(b.num_nodes)):
        if b.tri[node] >= 0:
            verts[node] = set(b.faces[b.tri[node]].tolist())
            tri = b.triangles[b.tri[node]]
            torch.testing.assert_close(b.centre[node], tri.mean(0))
        else:
            c0, c1 = b.child[node].tolist()
            verts[node] = verts[c0] | verts[c1]
            torch.testing.assert_close(b.centre[node], b.vertices[sorted(verts[node])].mean(0))
        dist = (b.vertices[sorted(verts[node])] - b.centre[node]).norm(dim=-1)
        assert dist.max() <= b.radius[node] * (1 + 1e-12)
        assert dist.max() >= b.radius[node] * (1 - 1e-12) or b.tri[node] >= 0


def test_refinement_keeps_the_surface():
    box = trimesh.creation.box((4.0, 4.0, 0.5))
    b = BSH.from_trimesh(box, max_edge=0.5)
    tris = b.triangles
    edges = torch.stack([tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 1], tris[:, 0] - tris[:, 2]], 1).norm(
        dim=-1
    )
    assert edges.max() <= 0.5 + 1e-12 and b.num_faces > 12
    area = 0.5 * torch.linalg.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]).norm(dim=-1).sum()
    assert abs(float(area) - box.area) < 1e-9


def test_hierarchy_does_not_share_memory_with_the_callers_arrays():
    """Writing into the arrays a hierarchy was built from (NumPy or torch, float64: no conversion copies them)
    leaves the hierarchy as it was."""
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    for V, F in ((np.array(m.vertices, dtype=np.float64), np.array(m.faces)),
                 (torch.tensor(m.vertices, dtype=torch.float64), torch.tensor(m.faces))):  # fmt: skip
        bsh = BSH.build(V, F)
        before = bsh.vertices.clone(), bsh.faces.clone()
        V *= 0.5
        F[0] = F[1]
        assert torch.equal(bsh.vertices, before[0]) and torch.equal(bsh.faces, before[1])


def test_bad_meshes_are_rejected():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0.0]])
    with pytest.raises(ValueError, match="faces has degenerate"):
        BSH.build(v, np.array([[0, 1, 2], [0, 1, 3]]))
    with pytest.raises(ValueError, match="NaN or inf"):
        BSH.build(np.where(np.arange(12).reshape(4, 3) == 4, np.nan, v), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="out of range"):
        BSH.build(v, np.array([[0, 1, 7]]))
    with pytest.raises(ValueError, match=r"shape \(F, 3\)"):
        BSH.build(v, np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="max_edge"):
        BSH.build(v, np.array([[0, 1, 2]]), max_edge=-1.0)


def _fields(b: BSH) -> dict:
    return {
        f: getattr(b, f).clone() for f in ("vertices", "faces", "centre", "radius", "child", "tri", "depth")
    }


def test_bsh_from_saved_fields_is_the_same_hierarchy_and_bad_fields_are_refused():
    import io

    from cfd_torch import mesh_potential

    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=2, radius=0.5))
    small = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    qa = torch.zeros(6, dtype=F64)
    qb = torch.tensor([1.002, 0, 0, 0.1, 0, 0], dtype=F64)
    ref = mesh_potential(ball, qa, ball, qb)
    assert float(ref) > 0
    again = BSH(**_fields(ball))
    assert torch.equal(mesh_potential(again, qa, again, qb), ref)
    # torch.load's default (weights_only=True) rebuilds it
    buf = io.BytesIO()
    torch.save(ball, buf)
    buf.seek(0)
    loaded = torch.load(buf)
    assert torch.equal(mesh_potential(loaded, qa, loaded, qb), ref)

    def refused(match, err=ValueError, **change):
        with pytest.raises(err, match=match):
            BSH(**{**_fields(ball), **change})

    f = _fields(ball)
    refused(r"BSH\.centre must be a torch\.Tensor", TypeError, centre=f["centre"].numpy())
    refused(
        r"BSH\.vertices must be a torch\.float64 tensor on the CPU, got torch\.float32",
        vertices=f["vertices"].float(),
    )
    refused(r"BSH\.faces must be a torch\.int64", faces=f["faces"].int())
    refused(r"BSH\.radius must have shape \(639,\)", radius=f["radius"][:, None])
    refused(
        r"BSH\.centre must have shape \(159, 3\)", vertices=small.vertices, faces=small.faces
    )  # another mesh
    refused(r"BSH\.faces index vertices out of range", vertices=small.vertices)
    refused(r"BSH\.radius does not contain the vertices below node 0", radius=torch.zeros_like(f["radius"]))
    shrunk = f["radius"].clone()
    leaf = int(torch.nonzero(f["tri"] >= 0)[5])
    shrunk[leaf] *= 0.9
    refused(rf"below node {leaf} \(1 nodes in all\)", radius=shrunk)
    refused(r"BSH\.radius must be finite", radius=torch.full_like(f["radius"], float("nan")))
    cyc = f["child"].clone()
    cyc[1] = cyc[0]  # node 1 points back at its siblings: not a tree
    refused(r"BSH\.child must make a binary tree", child=cyc)
    refused(r"BSH\.child must make a binary tree", child=f["child"].flip(1).roll(1, 0))
    tri = f["tri"].clone()
    leaves = torch.nonzero(tri >= 0).flatten()
    tri[leaves[0]] = tri[leaves[1]]  # a triangle twice, another never
    refused(r"BSH\.tri must give each leaf a distinct triangle", tri=tri)
    refused(r"BSH\.depth must count from 0", depth=f["depth"] + 1)
