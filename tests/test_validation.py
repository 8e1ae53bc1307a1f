"""Bad inputs to the public entry points raise a ValueError (TypeError for a wrong type) whose message names the
argument: meshes (open, self-intersecting, degenerate, NaN), and the step's state, action and params (dtypes,
devices, a kinematic target inside a static body).

Devices: there may be no GPU, so a tensor on the "meta" device stands in for "another device"; the checks compare
devices before reading any value, so they fire before a meta tensor could reach a kernel.
"""

from __future__ import annotations

import math
import pickle
import re

import numpy as np
import pytest
import torch
import trimesh

from cfd_torch import BSH, Action, Scene, State, StepError, pair_forces, rigid_body, rollout, step
from cfd_torch._validate import self_intersection

F64, F32 = torch.float64, torch.float32
META = torch.device("meta")


# ------------------------------------------------------------------------------------------------ meshes
def _overlapping_boxes() -> trimesh.Trimesh:
    """Two unit boxes, the second shifted by less than its size: one closed, watertight mesh that crosses itself."""
    other = trimesh.creation.box((1.0, 1.0, 1.0))
    other.apply_translation([0.5, 0.3, 0.2])
    return trimesh.util.concatenate([trimesh.creation.box((1.0, 1.0, 1.0)), other])


def _with_degenerate_face(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` plus one collinear face (index len(mesh.faces)) over three new vertices on a line."""
    extra = np.array([[5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [7.0, 0.0, 0.0]])
    V = np.vstack([mesh.vertices, extra])
    n = len(mesh.vertices)
    F = np.vstack([mesh.faces, [[n, n + 1, n + 2]]])
    return trimesh.Trimesh(V, F, process=False)


def _with_nan_vertex(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    V = np.array(mesh.vertices)
    V[3, 1] = np.nan
    return trimesh.Trimesh(V, mesh.faces, process=False)


def test_open_dynamic_mesh_names_mesh():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.update_faces(np.arange(len(box.faces)) != 0)  # one triangle missing
    with pytest.raises(ValueError, match="mesh of a dynamic body must be watertight"):
        rigid_body(box)
    # a closed box as a triangle soup (every face its own vertices): the message says how to weld it
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    soup = trimesh.Trimesh(box.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False)
    with pytest.raises(
        ValueError, match=r"closed once its coincident vertices are merged: call mesh.merge_vertices"
    ):
        rigid_body(soup)
    soup.merge_vertices()
    assert rigid_body(soup).mass > 0


def test_self_intersecting_dynamic_mesh_names_mesh_and_faces():
    mesh = _overlapping_boxes()
    assert mesh.is_watertight and mesh.is_winding_consistent  # only the new check can refuse it
    with pytest.raises(ValueError, match=r"mesh of a dynamic body intersects itself: faces \d+ and \d+"):
        rigid_body(mesh)
    rigid_body(mesh, kind="static")  # an obstacle may be any surface


def test_a_shell_nested_in_another_is_refused_and_a_cavity_is_not():
    """Two outward-facing nested shells are watertight, consistently wound and free of self-intersections, but count
    the inner solid twice (a 1 m box around a 0.5 m box weighed 1125 kg at 1000 kg/m^3); an inward-facing inner
    shell is a cavity, and separate pieces are two solids."""
    outer, inner = trimesh.creation.box((1.0, 1.0, 1.0)), trimesh.creation.box((0.5, 0.5, 0.5))
    nested = trimesh.util.concatenate([outer, inner])
    assert nested.is_watertight and nested.is_winding_consistent and float(nested.volume) > 0
    with pytest.raises(
        ValueError, match=r"mesh of a dynamic body has a closed shell inside another, .*\(component 1,"
    ):
        rigid_body(nested)
    inner.invert()
    assert rigid_body(trimesh.util.concatenate([outer, inner]), density=1000.0).mass == pytest.approx(875.0)
    apart = trimesh.creation.box((0.2, 0.2, 0.2))
    apart.apply_translation([1.0, 0.0, 0.0])
    two = trimesh.util.concatenate([trimesh.creation.box((0.2, 0.2, 0.2)), apart])
    assert rigid_body(two, density=1000.0).mass == pytest.approx(16.0)
    # an inward-facing shell inside no outward one is not a cavity: it weighed 992 kg (its 8 kg subtracted)
    stray = trimesh.creation.box((0.2, 0.2, 0.2))
    stray.apply_translation([0.8, 0.0, 0.0])
    stray.invert()
    alone = trimesh.util.concatenate([outer, stray])
    assert alone.is_watertight and alone.is_winding_consistent and float(alone.volume) > 0
    with pytest.raises(
        ValueError, match=r"closed shell facing inward outside every outward one \(component 1,"
    ):
        rigid_body(alone)


def test_vertex_pushed_through_the_mesh_is_a_self_intersection():
    """One vertex of a sphere pulled through to beyond the other side: its fan pierces the far faces."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    V = np.array(mesh.vertices)
    V[0] *= -1.5
    assert self_intersection(V, np.asarray(mesh.faces)) is not None


def test_valid_closed_meshes_are_not_self_intersecting():
    c = trimesh.creation
    far = c.box((1.0, 1.0, 1.0))
    far.apply_translation([1.5, 0.0, 0.0])
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 3.0])
    tilted = c.box((1.0, 2.0, 0.5)).subdivide().subdivide()  # coplanar faces sharing no vertex
    tilted.apply_transform(rot)
    tilted.apply_translation([1e3, -2e3, 5e2])
    meshes = {
        "icosphere": c.icosphere(subdivisions=3),
        "tiny icosphere": c.icosphere(subdivisions=2, radius=1e-4),
        "box": c.box((1.0, 2.0, 3.0)),
        "capsule": c.capsule(height=1.0, radius=0.3, count=[32, 32]),
        "cylinder": c.cylinder(radius=0.3, height=2.0, sections=64),
        "cone": c.cone(radius=0.3, height=2.0, sections=64),
        "torus": c.torus(1.0, 0.2, 32, 16),
        "two separate boxes": trimesh.util.concatenate([c.box((1.0, 1.0, 1.0)), far]),
        "box in a box": trimesh.util.concatenate([c.box((1.0, 1.0, 1.0)), c.box((0.5, 0.5, 0.5))]),
        "tilted subdivided box far away": tilted,
    }
    for name, mesh in meshes.items():
        assert self_intersection(np.asarray(mesh.vertices), np.asarray(mesh.faces)) is None, name


@pytest.mark.parametrize("kind", ["static", "kinematic", "dynamic"])
def test_degenerate_face_names_mesh_and_face(kind):
    mesh = _with_degenerate_face(trimesh.creation.box((1.0, 1.0, 1.0)))
    with pytest.raises(ValueError, match=r"mesh\.faces has degenerate triangles.*first face 12"):
        rigid_body(mesh, kind=kind)


def test_bsh_build_names_the_degenerate_face():
    mesh = _with_degenerate_face(trimesh.creation.box((1.0, 1.0, 1.0)))
    with pytest.raises(ValueError, match=r"faces has degenerate triangles.*first face 12"):
        BSH.build(mesh.vertices, mesh.faces)
    with pytest.raises(ValueError, match=r"faces has degenerate triangles.*first face 12"):
        BSH.from_trimesh(mesh)


@pytest.mark.parametrize("kind", ["static", "dynamic"])
def test_nan_vertex_names_mesh(kind):
    mesh = _with_nan_vertex(trimesh.creation.box((1.0, 1.0, 1.0)))
    with pytest.raises(ValueError, match=r"mesh\.vertices contain NaN or inf \(first at vertex 3"):
        rigid_body(mesh, kind=kind)


def test_bsh_build_names_nan_vertices():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    V = np.array(box.vertices)
    V[5, 0] = np.inf
    with pytest.raises(ValueError, match=r"vertices contain NaN or inf \(first at vertex 5"):
        BSH.build(V, box.faces)


def test_mesh_potential_poses_must_share_a_dtype_and_device():
    from cfd_torch import mesh_potential

    bsh = BSH.from_trimesh(trimesh.creation.box((0.1, 0.1, 0.1)))
    pose = torch.tensor([0.3, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    with _raises("pose_a and pose_b must share a dtype"):
        mesh_potential(bsh, torch.zeros(6, dtype=F32), bsh, pose)
    with _raises("pose_a must be float32 or float64, got torch.int64"):  # (was: "must share a dtype")
        mesh_potential(bsh, torch.zeros(6, dtype=torch.long), bsh, pose)
    with _raises("pose_b must be float32 or float64, got torch.float16"):
        mesh_potential(bsh, pose, bsh, pose.half())
    with _raises("pose_a and pose_b must be on one device"):
        mesh_potential(bsh, torch.zeros(6, dtype=F64, device=META), bsh, pose)


def test_potentials_refuse_meta_tensors_by_name():
    """Tensors without values (the 'meta' device) are refused naming the argument (they failed inside torch with
    "Tensor.item() cannot be called on meta tensors")."""
    from cfd_torch import contact_potential, mesh_potential, pair_potential

    bsh = BSH.from_trimesh(trimesh.creation.box((0.1, 0.1, 0.1)))
    tri = torch.zeros(3, 3, dtype=F64, device=META)
    pose = torch.zeros(6, dtype=F64, device=META)
    with _raises("tri_a is on the 'meta' device"):
        pair_potential(tri, tri)
    with _raises("pose_a is on the 'meta' device"):
        mesh_potential(bsh, pose, bsh, pose)
    with _raises("poses is on the 'meta' device"):
        contact_potential([bsh, bsh], torch.zeros(2, 6, dtype=F64, device=META))


def test_contact_potential_names_the_bad_body_and_refuses_an_empty_scene():
    from cfd_torch import contact_potential

    bsh = BSH.from_trimesh(trimesh.creation.box((0.1, 0.1, 0.1)))
    poses = torch.tensor([[0.0] * 6, [0.3, 0, 0, 0, 0, 0], [0.6, 0, 0, 0, 0, 0]], dtype=F64)
    with _raises(r"bshes\[1\] must be a cfd_torch.BSH, got str", TypeError):  # as mesh_potential's bsh_a
        contact_potential([bsh, "box", bsh], poses)
    with _raises("bshes must be a sequence of N = 3 BSH objects"):
        contact_potential([bsh, bsh], poses)
    with _raises("poses must hold at least one body"):
        contact_potential([], torch.zeros(0, 6, dtype=F64))
    with _raises("mu must be a finite positive number"):
        contact_potential([bsh] * 3, poses, mu=True)
    # NumPy numbers are numbers
    ref = contact_potential([bsh] * 3, poses, mu=1e-3).value
    assert float(contact_potential([bsh] * 3, poses, mu=np.float32(1e-3)).value) == pytest.approx(float(ref))
    # the plane solve's settings are checked here as in pair_potential
    for kw, msg in (
        ({"tol": -1.0}, "tol must be a finite positive number"),
        ({"tol": float("nan")}, "tol must be a finite positive number"),
        ({"max_iter": 0}, "max_iter must be a positive int"),
        ({"max_iter": True}, "max_iter must be a positive int"),
    ):
        with _raises(msg):
            contact_potential([bsh] * 3, poses, **kw)
    # exclude: a tensor of pairs works; pairs of non-integers are refused
    assert float(contact_potential([bsh] * 3, poses, exclude=torch.tensor([[0, 1]])).value) == pytest.approx(
        float(contact_potential([bsh] * 3, poses, exclude=[(0, 1)]).value)
    )
    with _raises("exclude must hold pairs"):
        contact_potential([bsh] * 3, poses, exclude=[(0, 1.5)])
    # an integer array of pairs, as Scene takes them (it was refused as "not int body indices")
    assert float(contact_potential([bsh] * 3, poses, exclude=np.array([[0, 1]])).value) == pytest.approx(
        float(contact_potential([bsh] * 3, poses, exclude=[(0, 1)]).value)
    )
    # translations beyond 1e30 m (pair_potential's limit on coordinates): from about 1e154 m the spheres' squared
    # distances overflowed and the gradient was silently exactly zero
    from cfd_torch import mesh_potential_derivatives

    far = poses.clone()
    far[2, 0] = 1e155
    with _says("poses has a translation beyond 1e+30 m (first at body 2)"):
        contact_potential([bsh] * 3, far)
    with _says("pose_b has a translation beyond 1e+30 m"):
        mesh_potential_derivatives(bsh, poses[0], bsh, far[2])
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    with _says("vertices hold coordinates beyond 1e+30 in magnitude (first in face 0, 12 faces in all)"):
        BSH.build(box.vertices * 1e31, box.faces)  # (it said "degenerate triangles")
    assert float(contact_potential([bsh] * 3, poses, exclude=None).value) == float(
        contact_potential([bsh] * 3, poses).value
    )


def test_mesh_potential_checks_its_solver_settings_and_names_the_bad_hierarchy():
    from cfd_torch import mesh_potential, mesh_potential_derivatives

    bsh = BSH.from_trimesh(trimesh.creation.box((0.1, 0.1, 0.1)))
    pa = torch.zeros(6, dtype=F64)
    pb = torch.tensor([0.3, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    for f in (mesh_potential, mesh_potential_derivatives):
        with _raises("tol must be a finite positive number"):
            f(bsh, pa, bsh, pb, tol=-1.0)
        with _raises("max_iter must be a positive int"):
            f(bsh, pa, bsh, pb, max_iter=0)
    with pytest.raises(TypeError, match="bsh_b must be a cfd_torch.BSH, got str"):
        mesh_potential(bsh, pa, "box", pb)


def test_central_terms_check_their_arguments():
    from cfd_torch.contact.central import blend_weight, central_potential, smoothstep

    with _raises("mu must be a finite positive number"):
        central_potential(torch.tensor([1.0], dtype=F64), mu=-1.0)
    with _raises("d1 must be finite and > 0"):
        blend_weight(torch.tensor([1.0], dtype=F64), 0.0, 0.1)
    with _raises("r contains NaN"):
        blend_weight(torch.tensor([float("nan")], dtype=F64), 1.0, 0.1)
    # infinitely far: the central term alone (phi = 1), as the clamp says
    inf = torch.tensor([float("inf")], dtype=F64)
    assert float(blend_weight(inf, 1.0, 0.1)) == 1.0 and float(smoothstep(inf)) == 1.0
    d1 = torch.tensor(1.0, dtype=F64, requires_grad=True)
    r = torch.tensor([float("inf"), 1.05], dtype=F64, requires_grad=True)
    blend_weight(r, d1, 0.1).sum().backward()
    assert bool(torch.isfinite(d1.grad)) and float(d1.grad) != 0.0 and float(r.grad[0]) == 0.0


def test_a_triangle_soup_has_the_hierarchy_of_the_merged_mesh():
    """An internal node's centre is the mean of the distinct points below it: the same surface with every vertex
    repeated in each face that has it (an STL's triangle soup) gives the same hierarchy and potential."""
    from cfd_torch import mesh_potential

    ico = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    V, Fc = np.asarray(ico.vertices), np.asarray(ico.faces)
    merged = BSH.build(V, Fc)
    soup = BSH.build(V[Fc].reshape(-1, 3), np.arange(3 * len(Fc)).reshape(-1, 3))
    torch.testing.assert_close(soup.centre, merged.centre, rtol=0, atol=1e-15)
    torch.testing.assert_close(soup.radius, merged.radius, rtol=0, atol=1e-15)
    qa = torch.zeros(6, dtype=F64)
    qb = torch.tensor([1.003, 0.02, 0.01, 0, 0, 0], dtype=F64)
    a, b = float(mesh_potential(merged, qa, merged, qb)), float(mesh_potential(soup, qa, soup, qb))
    assert a > 0 and b == pytest.approx(a, rel=1e-12)


def test_bsh_build_warns_that_vertices_get_no_gradient():
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    V = torch.tensor(box.vertices, dtype=F64, requires_grad=True)
    with pytest.warns(UserWarning, match="no gradient flows back to a mesh's vertices"):
        BSH.build(V, box.faces)


def test_non_mesh_is_a_type_error():
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh"):
        rigid_body(np.zeros((4, 3)))
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh"):
        BSH.from_trimesh(np.zeros((4, 3)))


def _says(message: str, err=ValueError):
    """pytest.raises whose message contains ``message`` literally."""
    return pytest.raises(err, match=re.escape(message))


def test_half_precision_poses_and_distances_are_refused():
    """float16 and bfloat16 would silently lose the answer (4-12 % off): every entry point takes float32 or float64."""
    from cfd_torch import contact_potential, mesh_potential
    from cfd_torch.contact.central import blend_weight, central_potential

    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    for dt in (torch.float16, torch.bfloat16):
        qa, qb = torch.zeros(6, dtype=dt), torch.tensor([1.1, 0, 0, 0, 0, 0], dtype=dt)
        with _says("pose_a must be float32 or float64"):
            mesh_potential(ball, qa, ball, qb)
        with _says("poses must be float32 or float64"):
            contact_potential([ball, ball], torch.stack([qa, qb]))
        with _says("r must have a floating dtype (float32 or float64)"):
            central_potential(torch.ones(2, dtype=dt), mu=1e-8)
        with _says("r must have a floating dtype (float32 or float64)"):
            blend_weight(torch.ones(2, dtype=dt), 0.5, 0.1)


def test_tolerances_and_coordinates_beyond_what_the_solve_resolves_are_refused():
    from cfd_torch import ContactConfig, mesh_potential, pair_potential

    A = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64)
    B = A + torch.tensor([0.0, 0, 0.5], dtype=F64)
    for tol in (1.0, 10.0, 1e300):
        with _says("tol must be a finite positive number below 1"):
            pair_potential(A, B, tol=tol)
    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    with _says("tol must be a finite positive number below 1"):
        mesh_potential(ball, torch.zeros(6, dtype=F64), ball, torch.ones(6, dtype=F64), tol=2.0)
    with _says("ContactConfig.pair_tol must be below 1"):
        ContactConfig(pair_tol=1.0)
    # unit triangles 1e32 m apart still resolve (P -> 12 mu); beyond 1e30 m in magnitude the input is refused
    far = pair_potential(A, A + torch.tensor([0.0, 0, 1e29], dtype=F64), mu=1.0)
    assert abs(float(far) - 12.0) < 1e-12
    for gap in (1e40, 1e154, 1e300):
        with pytest.raises(ValueError, match=r"tri_b has coordinates beyond 1e\+30 in magnitude"):
            pair_potential(A, A + torch.tensor([0.0, 0, gap], dtype=F64))


def test_blend_weight_names_a_bad_d1():
    from cfd_torch.contact.central import blend_weight

    r = torch.tensor([0.5, 0.9], dtype=F64)
    with _says("d1 must be a number or a torch.Tensor, got list", TypeError):
        blend_weight(r, [0.4, 0.4], 0.1)
    with _says("d1 of shape (3,) does not broadcast with r of shape (2,)"):
        blend_weight(r, torch.full((3,), 0.4, dtype=F64), 0.1)


def test_scene_and_body_settings_of_the_wrong_kind_are_refused():
    """A misspelt kind used to hang the body in mid-air; non-integer exclude indices were truncated; a non-bool
    static flag was read as True; a wrong config type failed deep inside with an AttributeError."""
    from cfd_torch import RigidBody, contact_potential

    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    ground = rigid_body(trimesh.creation.box((1.0, 1.0, 0.2)), kind="static")
    with _says("RigidBody.kind must be one of"):
        RigidBody(box.bsh, "Dynamic", box.mass, box.second_moment, box.com)
    with _says("RigidBody.mass must be finite, > 0 for a dynamic body"):
        RigidBody(box.bsh, "dynamic", 0.0, box.second_moment, box.com)
    with _says("exclude must hold body pairs (i, j) of integers, got (0, 1.7)"):
        Scene([box, ground], exclude=[(0, 1.7)])
    for rows in (
        np.array([[0, 1]]),
        torch.tensor([[0, 1]]),
        [(np.int64(0), 1)],
    ):  # integer rows are pairs too
        assert Scene([box, ground], exclude=rows).exclude == ((0, 1),)
    with _says("pair_eps must hold body pairs"):
        Scene([box, ground], pair_eps={(0, 1, 2): 0.5})
    with _says("contact must be a ContactConfig or None, got dict", TypeError):
        Scene([box, ground], contact={"margin": 1e-3})
    with _says("solver must be a SolverConfig or None, got int", TypeError):
        Scene([box, ground], solver=3)
    with _says("friction must be a FrictionConfig or a number", TypeError):
        Scene([box, ground], friction=torch.tensor(0.5))
    # a tensor where a number belongs: said so, not "must be a finite number, got tensor(0.0100)"
    with _says("dt must be a real number (a Python or NumPy float), got Tensor"):
        Scene([box, ground], dt=torch.tensor(0.01))
    with _says("ContactConfig.margin must be a finite positive number, got tensor(0.0010) of type Tensor"):
        Scene([box, ground], margin=torch.tensor(1e-3))
    with _says("bodies must be a sequence of RigidBody (see cfd_torch.rigid_body), got str at index 1"):
        Scene([box, "ground"])
    with _says("bodies must be a non-empty sequence of RigidBody"):
        Scene([])
    assert Scene([box, ground], friction=np.float32(0.5)).friction.coefficient == 0.5
    with _says("max_edge must be a finite number > 0"):
        BSH.from_trimesh(trimesh.creation.box((1.0, 1.0, 1.0)), max_edge="0.1")
    # (it ran a 23 GB machine out of memory, splitting 12 triangles towards 2e8)
    with _says(
        "max_edge=0.0001 would split the mesh's 12 triangles into about 2.01e+08 (more than 2,000,000"
    ):
        rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), max_edge=1e-4)
    P = torch.tensor([[0.0] * 6, [1.1, 0, 0, 0, 0, 0]], dtype=F64)
    with _says("static must be N = 2 booleans"):
        contact_potential([box.bsh, box.bsh], P, static=[0.3, 0.0])
    with _says("bshes must be a sequence of BSH objects", TypeError):
        contact_potential((b for b in [box.bsh, box.bsh]), P)
    assert contact_potential([box.bsh, box.bsh], P, static=[1, 0], grad=True).grad[0].abs().max() == 0.0


def test_gravity_pair_eps_contact_model_and_body_inertia_are_checked():
    """gravity is 3 finite numbers (a string, a scalar, a (2, 3) tensor or an entry requiring grad is refused naming
    it); pair_eps is checked whatever the potential; a contact model must be built for the scene's bodies in its
    order (a refined obstacle's hierarchy is the same surface); a RigidBody's second moment must be symmetric (to its
    dtype's rounding) positive semi-definite; NumPy scalars are numbers everywhere."""
    from cfd_torch import FrictionConfig, RigidBody
    from cfd_torch.contact import CfdContact

    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    ground = rigid_body(trimesh.creation.box((1.0, 1.0, 0.2)), kind="static")
    for bad, kind in (
        ("981", TypeError),
        (9.81, TypeError),
        (torch.zeros(2, 3), ValueError),
        ((0, 0), ValueError),
        ((True, 0.0, 0.0), TypeError),
    ):
        with _says("gravity must be", kind):
            Scene([box, ground], gravity=bad)
    with _says("gravity must be numbers, not a tensor that requires grad", TypeError):
        Scene([box, ground], gravity=(torch.tensor(0.1, requires_grad=True), 0.0, -9.81))
    assert Scene([box, ground], gravity=np.array([0.0, 0.0, -9.81])).gravity == (0.0, 0.0, -9.81)
    for potential in ("cfd", "ipc", "sdrs"):
        with _says("pair_eps: the blend width of (0, 1) must be a finite positive number"):
            Scene([box, ground], potential=potential, pair_eps={(0, 1): -1.0})
        with _says("pair_eps: (0, 9) is not a pair of two body indices in [0, 2)"):
            Scene([box, ground], potential=potential, pair_eps={(0, 9): 0.5})
    with _says("pair_eps must be a mapping", TypeError):
        Scene([box, ground], pair_eps=[((0, 1), 0.5)])
    with _says("pair_eps: (1, 0) and (0, 1) are one pair, given 0.2 and 0.5"):
        Scene([box, ground], pair_eps={(0, 1): 0.5, (1, 0): 0.2})
    assert Scene([box, ground], pair_eps={(0, 1): np.float32(0.5)}).pair_eps == {(0, 1): 0.5}
    with _says("contact_model must implement cfd_torch.contact.ContactModel", TypeError):
        Scene([box, ground], contact_model="ipc")
    with _says("contact_model was built for 3 bodies, the scene has 2"):
        Scene([box, ground], contact_model=CfdContact([box.bsh, ground.bsh, box.bsh]))
    with _says("contact_model's hierarchy 0 is not body 0's surface"):
        Scene([box, ground], contact_model=CfdContact([ground.bsh, box.bsh]))
    Scene(
        [box, ground],
        contact_model=CfdContact([BSH.from_trimesh(trimesh.creation.box((0.2, 0.2, 0.2))), ground.bsh]),
    )
    refined = Scene([box, ground])  # the ground refined to the box's scale: the same surface, accepted
    assert refined.bodies[1].bsh.num_faces > ground.bsh.num_faces
    Scene([box, ground], contact_model=refined.contact_model)
    assert Scene([box, ground], gravity=(g for g in (0.0, 0.0, -9.81))).gravity == (0.0, 0.0, -9.81)
    assert Scene([box, ground], pair_eps={(0, 1): np.float32(0.3), (1, 0): 0.3}).pair_eps[(1, 0)] == 0.3
    c, s_ = math.cos(0.7), math.sin(0.7)
    R = torch.tensor([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    S = R @ torch.diag(torch.tensor([1.0, 1.0, 2.0], dtype=F64)) * 1e-3 @ R.T  # symmetric to rounding
    for dt in (F64, F32):
        RigidBody(box.bsh, "dynamic", box.mass, S.to(dt), box.com.to(dt))
    with _says("RigidBody.second_moment must be symmetric positive semi-definite"):
        RigidBody(box.bsh, "dynamic", box.mass, -box.second_moment, box.com)
    with _says("RigidBody.second_moment must be a finite tensor of shape (3, 3)"):
        RigidBody(box.bsh, "dynamic", box.mass, box.second_moment[0], box.com)
    with _says("RigidBody.com must be a float tensor", TypeError):
        RigidBody(box.bsh, "dynamic", box.mass, box.second_moment, np.zeros(3))
    assert FrictionConfig(coefficient=np.float32(0.5), active=np.float64(1e-6)).coefficient == 0.5
    scene = Scene([box, ground])
    q = torch.zeros(2, 6, dtype=F64)
    q[0, 2], q[1, 2] = 0.2, -0.1
    assert len(rollout(scene, State(q, q.clone()), np.int64(1))) == 2


def test_recentre_rotation_checks_its_poses():
    from cfd_torch import recentre_rotation

    out = recentre_rotation(torch.tensor([1.0, 2.0, 3.0, 4.0, 0.0, 0.0], dtype=F64))
    torch.testing.assert_close(out, torch.tensor([1.0, 2.0, 3.0, 4.0 - 2 * math.pi, 0.0, 0.0], dtype=F64))
    bad_ones = (torch.tensor([0, 0, 0, 4.0]), torch.zeros(2, 7), torch.zeros(3, 6, dtype=torch.long))
    for bad in (*bad_ones, torch.zeros(6, dtype=torch.float16)):
        with _says("q must be a float32 or float64 tensor of poses (..., 6)"):
            recentre_rotation(bad)
    with _says("q contains NaN or inf"):
        recentre_rotation(torch.full((6,), float("nan")))
    # 1e300 rad came back NaN, 1e20 rad as 0: beyond 1e6 rad refused, as by every function taking poses
    big = torch.zeros(2, 6, dtype=F64)
    big[1, 3:5] = 1e300
    with _says("q has a rotation vector longer than 1e+06 rad (first at index (1,))"):
        recentre_rotation(big)
    big[1, 3:5] = 7e5  # (|omega| 9.9e5 rad: wrapped)
    assert float(recentre_rotation(big)[1, 3:].norm()) <= math.pi


# ------------------------------------------------------------------------------------------------ the step
@pytest.fixture(scope="module")
def scene():
    """A 0.2 m cube (dynamic), a ground slab with its top at z = 0 (static) and a paddle (kinematic)."""
    ground = trimesh.creation.box((1.0, 1.0, 0.05))
    ground.apply_translation([0.0, 0.0, -0.025])
    bodies = [
        rigid_body(trimesh.creation.box((0.2, 0.2, 0.2))),
        rigid_body(ground, kind="static"),
        rigid_body(trimesh.creation.box((0.05, 0.2, 0.1)), kind="kinematic"),
    ]
    return Scene(bodies, refine_obstacles=None)


@pytest.fixture(scope="module")
def state(scene):
    q = torch.tensor([[0.0, 0.0, 0.105, 0, 0, 0], [0.0] * 6, [-0.3, 0.0, 0.06, 0, 0, 0]], dtype=F64)
    return scene.initial_state(q)


def _raises(name: str, err=ValueError):
    return pytest.raises(err, match=name.replace(".", r"\."))


def test_unbatched_state_takes_unbatched_actions_and_empty_batches_are_refused(scene, state):
    """With an unbatched state an action field has no batch dimension (the message offers only that shape); a batch
    of no scenes is refused by name."""
    msg = "action.force must have shape (3, 3) (state.q has no batch dimension), got (1, 3, 3)"
    with pytest.raises(ValueError, match=re.escape(msg)):
        step(scene, state, Action(force=torch.zeros(1, 3, 3, dtype=F64)))
    empty = torch.zeros(0, 3, 6, dtype=F64)
    with _raises("state.q: a batch of no scenes"):
        step(scene, State(empty, empty))


def test_a_failed_step_in_a_batch_names_its_scene():
    """Three scenes; only scene 1 (a box thrown spinning at the floor) fails within 4 Newton iterations, also in
    2 and 4 sub-steps: the StepError says it is scene 1."""
    from cfd_torch import StepError

    floor = rigid_body(trimesh.creation.box((4, 4, 0.2)), kind="static", max_edge=0.1)
    sc = Scene(
        [rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=500.0), floor], dt=0.01, friction=0.5,
        max_newton_iter=4, substeps=4,
    )  # fmt: skip
    q = torch.tensor([[[0, 0, 0.1015, 0, 0, 0], [0, 0, -0.1, 0, 0, 0]]] * 3, dtype=F64)
    q_prev = q.clone()
    q[1, 0, 2] = 0.115
    q_prev[1, 0] = q[1, 0] - 0.01 * torch.tensor([1.0, 0, -1.5, 2, 3, 0], dtype=F64)
    with pytest.raises(
        StepError, match="^scene 1 of the batch: the step did not converge in 4 Newton iterations"
    ):
        step(sc, State(q, q_prev))


def test_a_body_turning_too_fast_names_its_body_and_scene():
    """Three scenes of two free boxes; in scene 2 box 1 spins at 200 rad/s (2 rad per step): the free rotation's
    StepError names the body and the scene (it named neither)."""
    from cfd_torch import StepError

    box = rigid_body(trimesh.creation.box((0.4, 0.2, 0.1)), density=500.0)
    sc = Scene([box, box], dt=0.01, gravity=(0, 0, 0))
    q = torch.zeros(3, 2, 6, dtype=F64)
    q[:, 1, 0] = 1.0
    v = torch.zeros(3, 2, 6, dtype=F64)
    v[2, 1, 3:] = 200.0 * torch.tensor([0.3, 1.0, 0.5], dtype=F64) / math.sqrt(1.34)
    with pytest.raises(StepError, match=r"the free rotation of a body \(body 1, scene 2\) over the step"):
        step(sc, State(q, q - 0.01 * v))
    with pytest.raises(StepError, match=r"the free rotation of a body \(body 1\) over the step"):
        step(sc, State(q[2], q[2] - 0.01 * v[2]))
    # the callers that add context (the env shells name the environment, a batch solved in groups its scenes)
    # raise type(err)(message) again: the error was rebuilt with that message as its row, and its own text without
    # the body or scene; it pickles with its row (a process pool sends it back to the parent)
    with pytest.raises(StepError) as err:
        step(sc, State(q, q - 0.01 * v))
    assert type(err.value).__name__ == "FreeRotationError" and err.value.row == 5
    again = type(err.value)(f"environment 2: {err.value}")
    assert str(again).startswith("environment 2: the free rotation of a body (body 1, scene 2) over the step")
    back = pickle.loads(pickle.dumps(err.value))
    assert str(back) == str(err.value) and back.row == 5


def test_state_dtypes_must_match(scene, state):
    with _raises("state.q_prev is torch.float32 but state.q is torch.float64"):
        step(scene, State(state.q, state.q_prev.to(F32)))


def test_state_devices_must_match(scene, state):
    with _raises("state.q_prev is on meta but state.q is on cpu"):
        step(scene, State(state.q, state.q_prev.to(META)))


@pytest.mark.parametrize("dtype", [torch.float16, torch.int64, torch.complex128])
def test_state_dtype_must_be_float32_or_float64(scene, state, dtype):
    with _raises("state.q must be float32 or float64"):
        step(scene, State(state.q.to(dtype), state.q_prev.to(dtype)))


@pytest.mark.parametrize("field, cols", [("force", 3), ("torque", 3), ("target", 6)])
def test_action_on_another_device(scene, state, field, cols):
    n = 1 if field == "target" else 3
    with _raises(f"action.{field} is on meta but state.q is on cpu"):
        step(scene, state, Action(**{field: torch.zeros(n, cols, dtype=F64, device=META)}))


@pytest.mark.parametrize("field, cols", [("force", 3), ("torque", 3), ("target", 6)])
def test_action_dtype_must_match_the_state(scene, state, field, cols):
    n = 1 if field == "target" else 3
    with _raises(f"action.{field} is torch.float32 but state.q is torch.float64"):
        step(scene, state, Action(**{field: torch.zeros(n, cols, dtype=F32)}))


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.float16, torch.complex128])
@pytest.mark.parametrize("field", ["force", "torque"])
def test_non_float_action_names_the_field(scene, state, field, dtype):
    """Non-float actions (integers, booleans; float16 and complex, which could carry requires_grad) are refused."""
    x = torch.zeros(3, 3, dtype=dtype)
    if dtype.is_floating_point or dtype.is_complex:
        x.requires_grad_()
    with _raises(f"action.{field} must be float32 or float64"):
        step(scene, state, Action(**{field: x}))


def test_a_non_finite_target_names_the_kinematic_body(scene, state):
    """action.target's rows are the kinematic bodies: a NaN in row 0 names body 2 (the paddle), batched with its
    scene (the message named "body (0,)")."""
    target = torch.tensor([[-0.3, 0.0, float("nan"), 0.0, 0.0, 0.0]], dtype=F64)
    with _says("action.target contains NaN or inf (first at body 2)"):
        step(scene, state, Action(target=target))
    batch = State(state.q.expand(2, -1, -1), state.q_prev.expand(2, -1, -1))
    with _says("action.target contains NaN or inf (first at scene 1, body 2)"):
        step(scene, batch, Action(target=torch.stack([state.q[2:3], target])))


def test_targets_and_poses_out_of_range_are_refused_by_name(scene, state):
    """A kinematic target's rotation vector beyond 1e6 rad (it was stepped as some arbitrary rotation) and
    translations beyond 1e30 m in the state, a target or pair_forces' poses (pair_forces returned zero forces at
    1e160 m) get the contact functions' errors, naming the argument and the body."""
    turned = state.q[2:3].clone()
    turned[0, 5] = 2e6
    with _says("action.target has a rotation vector longer than 1e+06 rad (first at body 2)"):
        step(scene, state, Action(target=turned))
    far = state.q[2:3].clone()
    far[0, 0] = 1e31
    batch = State(state.q.expand(2, -1, -1), state.q_prev.expand(2, -1, -1))
    with _says("action.target has a translation beyond 1e+30 m (first at scene 1, body 2)"):
        step(scene, batch, Action(target=torch.stack([state.q[2:3], far])))
    q = state.q.clone()
    q[0, 1] = -1e160
    with _says("state.q has a translation beyond 1e+30 m (first at body 0)"):
        step(scene, State(q, state.q_prev))
    with _says("q has a translation beyond 1e+30 m (first at body 0)"):
        pair_forces(scene, q)
    with _says("poses has a translation beyond 1e+30 m (first at body 0)"):
        scene.initial_state(q)


@pytest.mark.parametrize("far", [1e5, 1e17, 1e25])
def test_a_move_too_long_for_the_path_check_is_a_step_error_before_any_sampling(scene, state, far):
    """A target 1e5 m away took 1.3 GB and 21 s of path samples; at 1e17 m their count wrapped around int64 and the
    paddle passed through the box unchecked. Now a path of more than MAX_PATH_SAMPLES pieces is refused at once;
    a target 10 m away carries the box along."""
    from cfd_torch.sim.feasibility import MAX_PATH_SAMPLES

    target = state.q[2:3].clone()
    target[0, 0] = far
    with _says(f"a body would move {far - 0.3:.3g} m in one step", StepError):
        step(scene, state, Action(target=target))
    assert far / scene.path_spacing > MAX_PATH_SAMPLES
    target[0, 0] = 10.0
    assert float(step(scene, state, Action(target=target)).q[0, 0]) > 9.5
    fast = scene.initial_state(state.q, torch.tensor([[0.0, 0.0, 1e8, 0, 0, 0]] + [[0.0] * 6] * 2, dtype=F64))
    with _says("a body would move 1e+06 m in one step", StepError):
        step(scene, fast)


def test_action_must_be_an_action(scene, state):
    with _raises("action must be a cfd_torch.Action", err=TypeError):
        step(scene, state, {"force": torch.zeros(3, 3, dtype=F64)})


def test_params_on_a_device_torch_cannot_use_is_named(scene):
    with _says("device 'foo' is not usable with this torch build"):
        scene.params(device="foo")


def test_params_on_another_device(scene, state):
    p = scene.params()
    with _raises("params.mass is on meta"):
        step(scene, state, params=p._replace(mass=p.mass.to(META)))
    with _raises("params.friction is on meta"):
        step(scene, state, params=p._replace(friction=p.friction.to(META)))


def test_params_dtype_and_type(scene, state):
    p = scene.params()
    with _raises("params.second_moment must be float32 or float64"):
        step(scene, state, params=p._replace(second_moment=p.second_moment.half()))
    with _raises("params.mass must be a torch.Tensor", err=TypeError):
        step(scene, state, params=p._replace(mass=[8.0]))
    with _raises("params must be a cfd_torch.Params", err=TypeError):
        step(scene, state, params=tuple(p))


def test_params_values_name_the_scene_and_body(scene, state):
    """A bad value of a per-scene parameter names the first scene and body (or actuator) where it is bad; a shared
    one names the body alone."""
    p = scene.params()

    def refused(message):
        return pytest.raises(ValueError, match=re.escape(message))

    with refused("params.mass must be positive (first at body 0)"):
        step(scene, state, params=p._replace(mass=-p.mass))
    batch = State(state.q.expand(3, -1, -1), state.q_prev.expand(3, -1, -1))
    mass = p.mass.expand(3, -1).clone()
    mass[2, 0] = float("nan")
    with refused("params.mass contains NaN or inf (first at scene 2, body 0)"):
        step(scene, batch, params=p._replace(mass=mass))
    moment = p.second_moment.expand(3, -1, -1, -1).clone()
    moment[1, 0] = -moment[1, 0]
    with refused(
        "params.second_moment must be positive semi-definite with a positive definite inertia (first "
        "at scene 1, body 0)"
    ):
        step(scene, batch, params=p._replace(second_moment=moment))
    with refused("params.mass must be positive (first at body 0)"):  # shared by the batch: no scene named
        step(scene, batch, params=p._replace(mass=-p.mass))
    nan_moment = p.second_moment.clone()
    nan_moment[0, 1, 2] = float("nan")
    with refused("params.second_moment contains NaN or inf (first at body 0)"):
        step(scene, state, params=p._replace(second_moment=nan_moment))
    with refused("params.friction must be >= 0 (first at scene 1)"):
        step(scene, batch, params=p._replace(friction=torch.tensor([0.5, -0.1, -0.2], dtype=F64)))
    q = step(scene, batch, params=p._replace(mass=p.mass.expand(3, -1).clone())).q
    assert q.shape == (3, 3, 6) and bool(torch.isfinite(q).all())


def test_kinematic_target_wholly_inside_a_static_body():
    """A target sunk wholly into a thick static slab (surfaces clear) is refused like one that pierces its top: it
    was accepted, only the surface test ran."""
    slab = trimesh.creation.box((4.0, 4.0, 0.4))
    slab.apply_translation([0.0, 0.0, -0.2])
    bodies = [
        rigid_body(trimesh.creation.box((0.1, 0.1, 0.1))),
        rigid_body(slab, kind="static"),
        rigid_body(trimesh.creation.box((0.04, 0.04, 0.1)), kind="kinematic"),
    ]
    scene = Scene(bodies, refine_obstacles=None)
    q = torch.tensor([[0.0, 0.0, 0.052, 0, 0, 0], [0.0] * 6, [-0.3, 0.0, 0.06, 0, 0, 0]], dtype=F64)
    state = scene.initial_state(q)
    with _raises("action.target: kinematic body 2 at its target lies inside static body 1"):
        step(scene, state, Action(target=torch.tensor([[-0.3, 0.0, -0.2, 0.0, 0.0, 0.0]], dtype=F64)))
    step(
        scene, state, Action(target=torch.tensor([[-0.3, 0.0, 0.07, 0.0, 0.0, 0.0]], dtype=F64))
    )  # clear: steps


@pytest.mark.parametrize("z", [0.04, 0.0505])  # the paddle's bottom 1 cm inside the ground, 0.5 mm above it
def test_kinematic_target_into_a_static_body(scene, state, z):
    target = torch.tensor([[-0.3, 0.0, z, 0.0, 0.0, 0.0]], dtype=F64)
    with _raises("action.target: kinematic body 2 at its target penetrates static body 1"):
        step(scene, state, Action(target=target))
    batch = State(state.q.expand(2, -1, -1), state.q_prev.expand(2, -1, -1))
    targets = torch.stack([state.q[2:3], target])
    with pytest.raises(ValueError, match=r"action\.target: .* in scene 1"):
        step(scene, batch, Action(target=targets))


def test_a_kinematic_body_penetrating_at_the_start_is_refused_though_its_target_is_clear(scene, state):
    """The paddle 0.5 mm into the cube at the start, its target 10 cm back: the start is refused, as when the target
    stays (it stepped, friction taken at the +inf start kicking the cube); in a batch the message names the scene."""
    q = state.q.clone()
    q[2, 0] = -0.1 - 0.025 + 5e-4
    target = q[2:3].clone()
    target[0, 0] -= 0.1
    message = r"state\.q: bodies penetrate \(within the contact margin 0\.001\): pairs \(0, 2\)"
    for to in (q[2:3], target):
        with pytest.raises(ValueError, match=message + "$"):
            step(scene, State(q, q.clone()), Action(target=to))
    batch = State(torch.stack([state.q, q]), torch.stack([state.q, q]))
    with pytest.raises(ValueError, match=message + r" \(scene 1\)"):
        step(scene, batch, Action(target=torch.stack([state.q[2:3], target])))


def test_kinematic_target_clear_of_static_bodies_steps(scene, state):
    target = torch.tensor([[-0.3, 0.0, 0.06 - 1e-3, 0.0, 0.0, 0.0]], dtype=F64)  # 9 mm above the ground
    nxt = step(scene, state, Action(target=target))
    torch.testing.assert_close(nxt.q[2], target[0])


def test_a_body_wholly_inside_another_is_refused():
    """Surfaces clear of each other but one body inside the other: the potential is finite and nothing pushes it
    out (a 0.1 m box at the centre of a 1 m block fell through it for 20 steps); a pusher placed inside a box is
    refused at its target. Bodies beside and on top of each other step as before."""
    block = rigid_body(trimesh.creation.box((1.0, 1.0, 1.0)), kind="static")
    small = rigid_body(trimesh.creation.box((0.1, 0.1, 0.1)))
    scene = Scene([small, block])
    inside = torch.tensor([[0.0, 0.0, 0.1, 0.3, 0.2, 0.0], [0.0] * 6], dtype=F64)
    with _says("state.q: body 0 lies inside body 1"):
        step(scene, scene.initial_state(inside))
    batch = torch.stack([inside.clone(), inside.clone()])
    batch[0, 0, 2] = 0.6  # on top of the block: fine
    with _says(
        "state.q: body 0 lies inside body 1 (their surfaces do not touch, so the contact potential cannot "
    ):
        step(scene, scene.initial_state(batch))
    with pytest.raises(ValueError, match=r"lies inside body 1 .*\(scene 1\)"):
        step(scene, scene.initial_state(batch))
    on_top = batch[0]
    assert float(step(scene, scene.initial_state(on_top)).q[0, 2]) > 0.5
    # inside a room (a closed surface facing inward) is free space: the box falls to its floor
    room = trimesh.creation.box((1.0, 1.0, 1.0))
    room.invert()
    scene = Scene([small, rigid_body(room, kind="static")])
    state = scene.initial_state(inside)
    for _ in range(3):
        state = step(scene, state)
    assert float(state.q[0, 2]) < 0.1
    # one static mesh of an outward slab and an inward room (a positive volume overall): the room is free space
    slab = trimesh.creation.box((4.0, 4.0, 0.5))
    slab.apply_translation([0.0, 0.0, -0.25])
    room.apply_translation([0.0, 0.0, 0.51])
    scene = Scene([small, rigid_body(trimesh.util.concatenate([slab, room]), kind="static")])
    in_room = torch.tensor([[0.0, 0.0, 0.062, 0.0, 0.0, 0.0], [0.0] * 6], dtype=F64)
    assert abs(float(step(scene, scene.initial_state(in_room)).q[0, 2]) - 0.062) < 1e-3
    # the probe is a vertex of a face: a ring whose unused vertex 0 sits at its centre, round a rod, is not inside it
    ring = trimesh.creation.torus(0.3, 0.05, major_sections=24, minor_sections=8)
    ring = trimesh.Trimesh(np.vstack([[0.0, 0.0, 0.0], ring.vertices]), ring.faces + 1, process=False)
    rod = rigid_body(trimesh.creation.box((0.1, 0.1, 2.0)))
    scene = Scene([rod, rigid_body(ring, kind="kinematic")], gravity=(0.0, 0.0, 0.0))
    step(scene, scene.initial_state(torch.zeros(2, 6, dtype=F64)))
    # a kinematic paddle (5 mm) whose target lies inside a dynamic box, 9 mm from its start: the path samples are
    # at most half its thickness plus the margin apart (3.5 mm), so one lands on the crossing and the paddle
    # pushes the box; were the move
    # shorter than the samples' spacing (no sample of its path on the box's surface, as with the samples 1 cm
    # apart before session 53), the target inside would be refused
    box = rigid_body(trimesh.creation.box((0.4, 0.4, 0.4)))
    paddle = rigid_body(trimesh.creation.box((0.005, 0.005, 0.005)), kind="kinematic")
    scene = Scene([box, paddle], gravity=(0.0, 0.0, 0.0))
    q = torch.tensor([[0.0] * 6, [0.2045, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=F64)
    target = torch.tensor(
        [[0.1955, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=F64
    )  # 2 mm inside the box's face (1 mm: within the margin, pushed)
    assert float(step(scene, scene.initial_state(q), Action(target=target)).q[0, 0]) < -0.0065
    object.__setattr__(scene, "path_spacing", 0.01)  # a sparser sweep: the crossing between two samples
    with _says("action.target: body 1 lies inside body 0"):
        step(scene, scene.initial_state(q), Action(target=target))
    big = rigid_body(trimesh.creation.box((0.05, 0.05, 0.05)), kind="kinematic")
    scene = Scene([box, big], gravity=(0.0, 0.0, 0.0))
    q = torch.tensor([[0.0] * 6, [0.23, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=F64)
    far = torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=F64)
    pushed = step(scene, scene.initial_state(q), Action(target=far))
    assert float(pushed.q[0, 0]) < 0.05 - 0.025 - 0.2  # the box was pushed ahead of the paddle


def test_step_refuses_torch_func_transforms(scene, state):
    """The step's autograd Function cannot pass torch.func's transforms: grad and vmap are refused, saying what
    to use instead."""
    msg = "do not pass through a simulation step; differentiate with torch.autograd"

    def f(q):
        return step(scene, State(q, state.q_prev)).q.sum()

    with _raises(msg, err=NotImplementedError):
        torch.func.grad(f)(state.q)
    with _raises(msg, err=NotImplementedError):
        torch.func.vmap(f)(state.q[None].expand(2, -1, -1))


def test_rollout_actions(scene, state):
    with _says("actions must be a number of steps in [0, 1e+09], got -1"):
        rollout(scene, state, -1)
    with _says("actions must be a number of steps in [0, 1e+09]"):  # (OverflowError: cannot fit 'int')
        rollout(scene, state, 10**30)
    with _says("progress must be a bool, got 'yes'", TypeError):
        rollout(scene, state, 1, progress="yes")
    # Trajectory's own constructor took lists and mismatched shapes (indexing failed later, or paired wrong rows)
    from cfd_torch import Trajectory

    traj = rollout(scene, state, 1)
    assert len(traj[0:1]) == 1 and torch.equal(traj[1].q_prev, traj.q_prev[1])
    with _says("Trajectory.q must be a torch.Tensor, got list", TypeError):
        Trajectory([[0.0] * 6], traj.q_prev)
    with _says("Trajectory.q and q_prev must be (T + 1, [B,] N, 6) tensors of one shape"):
        Trajectory(traj.q, traj.q_prev[:1])
    with _raises("actions must be a sequence", err=TypeError):
        rollout(scene, state, 2.5)


def test_initial_state_velocities_must_match_poses(scene, state):
    with _raises("velocities is torch.float32 but poses is torch.float64"):
        scene.initial_state(state.q, torch.zeros(3, 6, dtype=F32))
    with _raises("velocities is on meta but poses is on cpu"):
        scene.initial_state(state.q, torch.zeros(3, 6, dtype=F64, device=META))


def test_a_tensor_in_place_of_an_action_or_params_and_a_lone_action_are_refused_by_name():
    """(A tensor passed as the action or the parameters reached a truth test of the tensor first; a single Action
    passed to rollout was iterated as a sequence of its fields, stepping once per field.)"""
    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    scene = Scene((box,))
    state = scene.initial_state(torch.zeros(1, 6, dtype=torch.float64))
    force = torch.zeros(1, 3, dtype=torch.float64)
    with pytest.raises(TypeError, match="action must be a cfd_torch.Action or None, got Tensor"):
        step(scene, state, force)
    with pytest.raises(TypeError, match="params must be a cfd_torch.Params or None, got Tensor"):
        step(scene, state, None, scene.params().mass)
    with pytest.raises(TypeError, match="got a single Action"):
        rollout(scene, state, Action(force=force))
    with pytest.raises(TypeError, match="action must be a cfd_torch.Action or None, got Tensor"):
        rollout(scene, state, [force] * 3)


def test_a_rollout_of_no_steps_checks_its_inputs():
    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    scene = Scene((box,))
    state = scene.initial_state(torch.zeros(1, 6, dtype=torch.float64))
    assert rollout(scene, state, 0).q.shape == (1, 1, 6)
    with pytest.raises(TypeError, match="scene must be a cfd_torch.Scene"):
        rollout("not a scene", state, [])
    with pytest.raises(ValueError, match="state.q"):
        rollout(scene, State(torch.full((1, 6), float("nan"), dtype=torch.float64), state.q_prev), 0)
    bad = scene.params()._replace(mass=-scene.params().mass)
    with pytest.raises(ValueError, match="mass"):
        rollout(scene, state, 0, bad)


def test_static_and_kinematic_rows_come_back_exactly():
    """Rows the step does not solve are the inputs, bit for bit, whatever their digits (the step solves in a frame
    near the moving bodies, and the shift's round trip is exact only near them)."""
    cube = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    small = trimesh.creation.box((0.1, 0.1, 0.1))
    scene = Scene(
        (cube, rigid_body(small, kind="static"), rigid_body(small, kind="kinematic")), gravity=(0, 0, 0)
    )
    q0 = torch.tensor(
        [
            [20.3, 0.1, 0.7, 0.0, 0.0, 0.0],  # the moving cube, 20 m from the origin
            [0.123456789012345, -0.98765432101234, 0.3333333333333333, 0.1, 0.2, 0.3],
            [-3.3, 0.7, 0.1, 0.0, 0.0, 0.0],
        ],
        dtype=torch.float64,
    )
    v = torch.zeros(3, 6, dtype=torch.float64)
    v[0, 0] = 1.0
    target = torch.tensor([[-3.2999999999, 0.70000001, 0.1, 0.01, 0.0, 0.0]], dtype=torch.float64)
    nxt = step(scene, scene.initial_state(q0, v), Action(target=target))
    assert torch.equal(nxt.q[1], q0[1]) and torch.equal(nxt.q[2], target[0])
    assert not torch.equal(nxt.q[0], q0[0])  # the cube did move


def test_float32_results_that_overflow_are_refused_and_thin_triangles_accepted():
    """A float64 result too large for float32 (a Hessian at the margin, a huge stiffness) is refused naming the
    inputs, not returned as inf (which reads as infeasible); a thin float32 triangle that float64 accepts is solved
    in float64 like it; float32 coordinates stop at 1e12 m, where their derivatives still resolve."""
    from cfd_torch import pair_potential, pair_potential_derivatives

    A = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64)
    B = A + torch.tensor([0.0, 0, 0.5], dtype=F64)
    assert math.isfinite(float(pair_potential_derivatives(A, B, mu=1e37).value))  # float64 holds it
    with _says("pair_potential_derivatives' value overflows torch.float32"):
        pair_potential_derivatives(A.float(), B.float(), mu=1e37)
    with _says(
        "pair_potential's value overflows torch.float32 (7.01e+38 > 3.4e+38; the solve runs in float64): "
        "pass tri_a and tri_b as float64"
    ):
        pair_potential(A.float(), B.float(), mu=1e37)
    needle = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, 1e-6, 0]])
    P32 = pair_potential(needle, needle + torch.tensor([0.0, 0, 0.5]))
    P64 = pair_potential(needle.double(), needle.double() + torch.tensor([0.0, 0, 0.5], dtype=F64))
    assert P32.dtype == F32 and float(P32) == pytest.approx(float(P64), rel=1e-6)
    far = torch.tensor([0.0, 0, 1e13])
    with _says(
        "tri_b has coordinates beyond 1e+12 in magnitude, where the pair solve cannot resolve the potential "
        "in float32"
    ):
        pair_potential(A.float(), A.float() + far)
    assert float(pair_potential(A, A + far.double(), mu=1.0)) > 0  # float64 takes it


def test_float32_gradients_that_overflow_are_refused():
    """A float32 value that fits with a gradient that does not: autograd (and torch.func.grad) raise naming the
    function and its inputs instead of returning inf, for each differentiable potential; float64 gives the finite
    gradient, and a float32 gradient that fits comes back in float32."""
    from cfd_torch import contact_potential, mesh_potential, pair_potential

    A = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F32)
    B = A + torch.tensor([0.0, 0, 0.00101])
    a64 = A.double().requires_grad_()
    (g64,) = torch.autograd.grad(pair_potential(a64, B.double(), mu=1e30), a64)
    assert float(g64.abs().max()) > 3.5e38 and bool(torch.isfinite(g64).all())  # float64 holds it
    a = A.clone().requires_grad_()
    value = pair_potential(a, B, mu=1e30)
    assert value.dtype == F32 and math.isfinite(float(value.detach()))
    with _says("pair_potential's gradient overflows torch.float32"):
        torch.autograd.grad(value, a)
    with _says("pair_potential's gradient overflows torch.float32"):
        torch.func.grad(lambda x: pair_potential(x, B, mu=1e30))(A)
    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    qa = torch.zeros(6, dtype=F32, requires_grad=True)
    qb = torch.tensor([1.003, 0, 0, 0, 0, 0], dtype=F32)
    value = mesh_potential(ball, qa, ball, qb, mu=1e33)
    assert math.isfinite(float(value.detach()))
    with _says("mesh_potential's gradient overflows torch.float32"):
        torch.autograd.grad(value, qa)
    P = torch.stack([qa.detach(), qb]).requires_grad_()
    value = contact_potential([ball, ball], P, mu=1e33, grad=False).value
    with _says(
        "contact_potential's gradient overflows torch.float32 (5.02e+40 > 3.4e+38; the solve runs in "
        "float64): pass poses as float64"
    ):
        torch.autograd.grad(value, P)
    (g,) = torch.autograd.grad(contact_potential([ball, ball], P).value, P)  # the default stiffness: it fits
    assert g.dtype == F32 and float(g.abs().max()) > 0 and bool(torch.isfinite(g).all())
    P64 = P.detach().double().requires_grad_()
    (g64,) = torch.autograd.grad(contact_potential([ball, ball], P64).value, P64)
    torch.testing.assert_close(g, g64.float(), rtol=1e-5, atol=0)  # the float64 gradient, rounded
    # a gradient that fits with a Hessian that does not: the Hessian-vector products come back through the same cast
    a = A.clone().requires_grad_()
    (g,) = torch.autograd.grad(pair_potential(a, B, mu=1e24), a, create_graph=True)
    assert bool(torch.isfinite(g).all()) and float(g.abs().max()) > 1e33
    with _says("pair_potential's gradient overflows torch.float32"):
        torch.autograd.grad(g.sum(), a)

    ground = trimesh.creation.box((1.0, 1.0, 0.05))
    ground.apply_translation([0.0, 0.0, -0.025])
    bodies = [rigid_body(trimesh.creation.box((0.2, 0.2, 0.2))), rigid_body(ground, kind="static")]
    q = torch.tensor([[0.0, 0.0, 0.1015, 0, 0, 0], [0.0] * 6], dtype=F64)
    assert bool(torch.isfinite(pair_forces(Scene(bodies, mu=1e33, refine_obstacles=None), q)).all())
    with _says("pair_forces' F overflows torch.float32"):
        pair_forces(Scene(bodies, mu=1e33, refine_obstacles=None), q.float())


def test_a_stiffness_that_could_overflow_float64_is_refused_by_name():
    """mu beyond 1e250, where the potential's terms can overflow float64 (+inf would read as 'within the margin':
    no force, an infeasible step; mu = 1e308 did so for triangles 0.5 m apart, and for balls 1.5 m apart through the
    central terms), is refused naming it wherever a stiffness is taken; 1e250 is solved."""
    from cfd_torch import ContactConfig, contact_potential, mesh_potential, pair_potential
    from cfd_torch.contact.central import central_potential

    A = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64)
    B = A + torch.tensor([0.0, 0, 0.5], dtype=F64)  # 0.5 m apart: far outside the margin
    for backend in ("numba", "torch"):
        assert math.isfinite(float(pair_potential(A, B, mu=1e250, backend=backend)))
        with _says("mu must be at most 1e+250"):
            pair_potential(A, B, mu=1e308, backend=backend)
    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    poses = torch.tensor([[0.0] * 6, [1.5, 0, 0, 0, 0, 0]], dtype=F64)
    assert math.isfinite(float(contact_potential([ball, ball], poses, mu=1e250).value))
    with _says("mu must be at most 1e+250"):
        contact_potential([ball, ball], poses, mu=1e308)
    with _says("mu must be at most 1e+250"):
        mesh_potential(ball, poses[0], ball, poses[1], mu=1e251)
    with _says("mu must be at most 1e+250"):
        central_potential(torch.ones(1, dtype=F64), mu=1e308)
    with _says("ContactConfig.stiffness must be at most 1e+250"):
        ContactConfig(stiffness=1e300)


def test_bsh_vertices_and_small_arguments_are_checked_by_name():
    """Complex, boolean, ragged or meta vertices; a non-tensor pose array, an exclude generator, a scene that is
    not one, a density of a static body, a non-bool hessian flag and a zero dt are named, not silently used."""
    from cfd_torch import contact_potential, pair_potential_derivatives

    box = trimesh.creation.box((1.0, 1.0, 1.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    with _says("vertices must be an array of real numbers, got dtype complex128", TypeError):
        BSH.build(V + 5j, F)
    with _says("vertices must be an array of real numbers, got dtype bool", TypeError):
        BSH.build(V > 0, F)
    with _says("vertices must be a (V, 3) array of real numbers"):
        BSH.build([[0.0, 0.0, 0.0], [1.0, 0.0], [0.0, 1.0, 0.0]], [[0, 1, 2]])
    with _says("vertices is on the 'meta' device"):
        BSH.build(torch.zeros(8, 3, device=META), F)
    bsh = BSH.build(V, F)
    with _says("poses must be a (N, 6) torch.Tensor, got ndarray", TypeError):
        contact_potential([bsh, bsh], np.zeros((2, 6)))
    poses = torch.tensor([[0.0] * 6, [3.0, 0, 0, 0, 0, 0]], dtype=F64)
    assert float(contact_potential([bsh, bsh], poses).value) > 0
    skipped = contact_potential(
        [bsh, bsh], poses, exclude=((0, 1) for _ in range(1))
    )  # any iterable of pairs
    assert float(skipped.value) == 0.0 and skipped.stats["body_pairs"] == 0
    ground = rigid_body(box, kind="static")
    with _says("density must be a finite positive number, got -1.0"):
        rigid_body(box, kind="static", density=-1.0)
    with _says(
        "density must be a Python number, got a tensor", TypeError
    ):  # it read: a finite positive number
        rigid_body(box, density=torch.tensor(1000.0, dtype=F64, requires_grad=True))
    with _says("scene must be a cfd_torch.Scene, got NoneType", TypeError):
        pair_forces(None, poses)
    with _says("bodies must be a sequence of RigidBody, got int", TypeError):
        Scene(5)
    with _says("bodies must be a sequence of RigidBody, got RigidBody", TypeError):
        Scene(ground)
    with _says("hessian must be a bool, got 'no'", TypeError):
        pair_potential_derivatives(torch.eye(3, dtype=F64), torch.eye(3, dtype=F64) + 2, hessian="no")
    # the other functions' flags ("no" read as True; a tensor failed inside torch as ambiguous)
    from cfd_torch import mesh_potential_derivatives

    with _says("hessian must be a bool, got 'no'", TypeError):
        mesh_potential_derivatives(bsh, poses[0], bsh, poses[1], hessian="no")
    with _says("hessian must be a bool, got 'False'", TypeError):
        contact_potential([bsh, bsh], poses, hessian="False")
    with _says("grad must be a bool or None, got tensor([False,  True])", TypeError):
        contact_potential([bsh, bsh], poses, grad=torch.tensor([False, True]))
    with _says("dt must be a finite positive number"):
        State(poses, poses.clone()).velocity(0.0)
    # the velocity of a NaN state was NaN, a tiny dt's -inf; other shapes failed inside torch, dtypes were promoted
    with _says("State.q or State.q_prev contains NaN or inf"):
        State(poses, poses * float("nan")).velocity(0.01)
    with _says("the velocity (q - q_prev) / dt overflows torch.float64"):
        State(poses, poses + 1.0).velocity(1e-320)
    with _says(
        "State.q (torch.float64 (2, 6) on cpu) and State.q_prev (torch.float32 (2, 6) on cpu) must match"
    ):
        State(poses, poses.float()).velocity(0.01)
    with _says("must match in shape, dtype and device"):
        State(poses, poses[:1]).velocity(0.01)


def test_sparse_tensors_are_refused_by_name():
    """Sparse tensors failed inside torch ("Could not run 'aten::ne.Scalar' with arguments from the 'SparseCPU'
    backend", "reshape is not implemented for sparse tensors"), naming none of the caller's arguments."""
    from cfd_torch import contact_potential, mesh_potential, pair_potential

    box = trimesh.creation.box((0.2, 0.2, 0.2))
    body = rigid_body(box)
    scene = Scene([body, body], dt=0.01, gravity=(0, 0, 0))
    q = torch.tensor([[0.0] * 6, [1.0, 0, 0, 0, 0, 0]], dtype=F64)
    tri = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64)
    p = scene.params()
    for call, name in (
        (lambda: pair_potential(tri, (tri + 1).to_sparse()), "tri_b"),
        (lambda: mesh_potential(body.bsh, q[0].to_sparse(), body.bsh, q[1]), "pose_a"),
        (lambda: contact_potential([body.bsh, body.bsh], q.to_sparse()), "poses"),
        (lambda: scene.initial_state(q.to_sparse()), "poses"),
        (lambda: step(scene, State(q, q.to_sparse())), "state.q_prev"),
        (
            lambda: step(scene, State(q, q), Action(torque=torch.zeros(2, 3, dtype=F64).to_sparse())),
            "action.torque",
        ),
        (lambda: step(scene, State(q, q), params=p._replace(mass=p.mass.to_sparse())), "params.mass"),
        (lambda: pair_forces(scene, q.to_sparse()), "q"),
        (lambda: BSH.build(torch.tensor(box.vertices).to_sparse(), box.faces), "vertices"),
    ):
        with _says(f"{name} must be a dense (strided) tensor, got layout torch.sparse_coo", TypeError):
            call()


def test_rotation_vectors_beyond_a_million_radians_are_refused():
    """A rotation vector whose float64 spacing is coarser than a step's resolution is refused by name (it failed as
    'did not converge ... try a smaller dt'); one of 1e4 rad is wrapped and stepped."""
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1), density=500.0)
    scene = Scene([ball], dt=0.01, gravity=(0, 0, 0))
    q = torch.tensor([[0.0, 0, 0, 1e4, 0, 0]], dtype=F64)
    assert float(step(scene, State(q, q.clone())).q[0, 3:].norm()) <= math.pi
    far = torch.tensor([[0.0, 0, 0, 0, 0, 1e30]], dtype=F64)
    with _says("state.q has a rotation vector longer than 1e+06 rad (first at body 0)"):
        step(scene, State(far, far.clone()))
    with _says("state.q_prev has a rotation vector longer than 1e+06 rad (first at scene 1, body 0)"):
        step(scene, State(q.expand(2, -1, -1), torch.stack([q, far])))


def test_every_entry_taking_poses_refuses_rotation_vectors_beyond_a_million_radians():
    """As the step does (the contact functions took |omega| = 1e15 rad silently, where float64 cannot say which
    rotation it is); 1e4 rad is a rotation like any other."""
    from cfd_torch import contact_potential, mesh_potential, mesh_potential_derivatives

    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1), density=500.0)
    scene = Scene([ball, ball], dt=0.01, gravity=(0, 0, 0))
    near = torch.tensor([[0.0, 0, 0, 1e4, 0, 0], [0.5, 0, 0, 0, 0, 0]], dtype=F64)
    far = near.clone()
    far[1, 5] = 1e15
    bsh = ball.bsh
    assert torch.isfinite(mesh_potential(bsh, near[0], bsh, near[1]))
    why = "rad (first at {}): beyond 1e6 rad the float64 spacing of a rotation vector exceeds 1.2e-10 rad"
    with _says(f"pose_b has a rotation vector longer than 1e+06 {why.format('batch index ()')}"):
        mesh_potential(bsh, near[0], bsh, far[1])
    with _says(f"pose_a has a rotation vector longer than 1e+06 {why.format('batch index (1,)')}"):
        mesh_potential_derivatives(bsh, far, bsh, near[1])
    with _says(f"poses has a rotation vector longer than 1e+06 {why.format('body 1')}"):
        contact_potential([bsh, bsh], far)
    with _says(f"q has a rotation vector longer than 1e+06 {why.format('scene 1, body 1')}"):
        pair_forces(scene, torch.stack([near, far]))
    with _says(f"poses has a rotation vector longer than 1e+06 {why.format('body 1')}"):
        scene.initial_state(far)


def test_a_tumbling_body_whose_rotation_vector_is_on_a_far_branch_steps_as_re_centred():
    """A rotation vector |omega| = 2 pi k + a (the rotation of |omega| = a) is a valid state: a tumbling box steps
    from it as from the re-centred state, in as many Newton iterations, to the same rotation and the same gradient
    (on the far branch a turn is a coordinate change |omega| / a times larger: 200 iterations did not converge)."""
    from cfd_torch import recentre_rotation
    from cfd_torch.rotation import rotation_matrix

    scene = Scene([rigid_body(trimesh.creation.box((0.1, 0.2, 0.3)))], gravity=(0.0, 0.0, 0.0))
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    w = 1e-3 * axis / axis.norm()
    w_prev = w - scene.dt * torch.tensor([2.0, -1.0, 3.0], dtype=F64)

    def far(v, k):
        return torch.cat([torch.zeros(3, dtype=F64), v * (1 + 2 * math.pi * k / v.norm())])[None]

    q, q_prev = far(w, 100), far(w_prev, 100)
    assert float(q[0, 3:].norm()) > 600
    force = torch.zeros(1, 3, dtype=F64, requires_grad=True)
    ends, grads, iters = [], [], []
    for state in (State(q, q_prev), State(recentre_rotation(q), recentre_rotation(q_prev))):
        nxt, info = step(scene, state, Action(force=force, torque=force * 0.1), return_info=True)
        (g,) = torch.autograd.grad(rotation_matrix(nxt.q[:, 3:]).sum(), force)
        ends.append(rotation_matrix(nxt.q[:, 3:].detach()))
        grads.append(g)
        iters.append(int(info.newton_iters))
    assert float(grads[1].abs().max()) > 0
    assert iters[0] == iters[1] <= 3
    torch.testing.assert_close(ends[0], ends[1], rtol=0, atol=1e-12)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-9, atol=0)


def test_float32_step_that_rounds_into_the_margin_raises():
    """A heavy box resting on a floor 2 km up: the float32 spacing there (2.4e-4 m) exceeds the solution's gap
    beyond the margin, so rounding the float64 solution to the float32 state puts the box within the margin. The
    step that does so raises StepError saying why (the next step named state.q); float64 steps on."""
    from cfd_torch import StepError

    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=1e5, max_edge=0.1)
    ground = rigid_body(trimesh.creation.box((4, 4, 0.2)), kind="static", max_edge=0.1)
    scene = Scene([box, ground], dt=0.01, friction=0.5)
    zmin = float(scene.bodies[0].bsh.vertices[:, 2].min())
    H = 2048.00034
    z = torch.tensor(H - zmin + 1e-3 - 2.16e-5, dtype=F32)
    z = z + 2 * (torch.nextafter(z, torch.tensor(1e9)) - z)  # two float32 values clear of the margin
    q = torch.tensor([[0.0, 0, 0, 0, 0, 0], [0, 0, H - 0.1, 0, 0, 0]], dtype=F32)
    q[0, 2] = z
    state, state64 = State(q, q.clone()), State(q.double(), q.double())
    with _says(
        "the step's solution rounded to the state's torch.float32 puts bodies 0 and 1 within the contact "
        "margin",
        err=StepError,
    ):
        for _ in range(3):
            state = step(scene, state)
    for _ in range(3):
        state64 = step(scene, state64)
    assert bool(torch.isfinite(state64.q).all())


def test_a_scene_is_read_only_once_built_and_its_settings_are_checked_up_front():
    """Assigning a scene's setting (which left the contact model, pairs and tables built from the old one, or shadowed
    a shorthand name) raises, pointing to replace(); contact settings beside a contact_model (which has its own) are
    refused; an iteration cap beyond 1e6, exclude=None and bool gravity are refused at construction."""
    from cfd_torch import ContactConfig
    from cfd_torch.contact import CfdContact

    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)))
    ground = rigid_body(trimesh.creation.box((1.0, 1.0, 0.2)), kind="static")
    scene = Scene([box, ground])
    for name, value in (("margin", 0.01), ("dt", -0.01), ("exclude", ((0, 1),)), ("friction", 0.5)):
        before = getattr(scene, name)
        with _says("a Scene is read-only once built", AttributeError):
            setattr(scene, name, value)
        assert getattr(scene, name) is before
    with _says("so 'dt' cannot be deleted", AttributeError):
        del scene.dt
    with _says("so 'pairs' cannot be set: scene.replace(...) builds one", AttributeError):
        scene.pairs = scene.pairs[:0]
    assert scene.replace(margin=0.01).margin == 0.01 and scene.margin == 1e-3
    model = CfdContact([box.bsh, ground.bsh])
    with _says(
        "beside a contact_model must be the model's own (its config, or the defaults for a model without "
        "one): leave them out (these differ: stiffness, margin)"
    ):
        Scene([box, ground], contact_model=model, margin=0.01, mu=1e-6)
    with _says("(these differ: margin)"):
        Scene([box, ground], contact_model=model).replace(margin=0.01)
    assert Scene([box, ground], contact_model=model, contact=ContactConfig()).replace(dt=0.02).dt == 0.02
    wide = ContactConfig(margin=0.01)  # a model with its own margin: the scene's settings are its
    own = CfdContact([box.bsh, ground.bsh], wide)
    assert Scene([box, ground], contact_model=own).margin == 0.01
    assert Scene([box, ground], contact_model=own, contact=wide).replace(dt=0.02).contact == wide
    with _says(
        "ContactConfig.pair_max_iter must be a positive int of at most 1,000,000, got 9223372036854775808"
    ):
        Scene([box, ground], pair_max_iter=2**63)
    with _says("SolverConfig.substeps must be a positive int of at most 65,536"):
        Scene([box, ground], substeps=2**20)
    with _says("exclude must be a sequence of body pairs (i, j), got None", TypeError):
        Scene([box, ground], exclude=None)


def test_bsh_build_takes_bfloat16_vertices_and_names_bfloat16_faces():
    """bfloat16, which NumPy lacks, failed inside .numpy() with a TypeError naming no argument: its vertices are
    widened exactly (the hierarchy equals that of the same values in float64), its faces refused by name."""
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    V = torch.tensor(box.vertices, dtype=torch.bfloat16)
    F = torch.tensor(box.faces)
    b16, b64 = BSH.build(V, F), BSH.build(V.double(), F)
    assert torch.equal(b16.vertices, b64.vertices) and torch.equal(b16.faces, b64.faces)
    with _says("faces must hold integer vertex indices, got dtype torch.bfloat16"):
        BSH.build(V.double(), F.to(torch.bfloat16))


def test_contact_potential_stats_hold_every_key_when_no_pair_is_traversed():
    """A single body or static bodies only: the counts are zeros (stats held only "body_pairs")."""
    from cfd_torch import contact_potential

    bsh = BSH.from_trimesh(trimesh.creation.box((1.0, 1.0, 1.0)))
    poses = torch.tensor([[0.0] * 6, [3.0, 0, 0, 0, 0, 0]], dtype=F64)
    keys = {"body_pairs", "node_pairs", "leaf_pairs", "levels"}
    for res in (
        contact_potential([bsh], poses[:1]),
        contact_potential([bsh, bsh], poses, static=[True, True]),
    ):
        assert set(res.stats) == keys and all(res.stats[k] == 0 for k in keys) and float(res.value) == 0.0
    moving = contact_potential([bsh, bsh], poses)
    assert set(moving.stats) == keys and moving.stats["body_pairs"] == 1 and moving.stats["node_pairs"] > 0


def test_a_thin_plate_turned_off_the_axes_is_a_body_and_a_needle_too_thin_for_its_inertia_is_named():
    """The volume integrals' rounding made a rotated 1 um plate's smallest second moment negative (-4e-16 against
    8e-17 kg m^2) and RigidBody refused it as not positive semi-definite, naming a field the user never passed; it
    is clipped to zero within 1e-9 of the largest. A needle whose axial inertia is below that rounding is refused
    by name."""
    R = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])
    plate = trimesh.creation.box((1.0, 1.0, 1e-6))
    plate.apply_transform(R)
    body = rigid_body(plate, density=1000.0)
    exact = torch.tensor(R[:3, :3] @ np.diag([1e-3 / 12, 1e-3 / 12, 1e-3 * 1e-12 / 12]) @ R[:3, :3].T)
    assert float(torch.linalg.eigvalsh(body.second_moment)[0]) >= -1e-15 * float(exact.abs().max())
    assert float((body.second_moment - exact).abs().max()) < 1e-10 * float(exact.abs().max())
    needle = trimesh.creation.box((1.0, 1e-6, 1e-6))
    needle.apply_transform(R)
    with _says("mesh of a dynamic body is too thin for its mass properties: its smallest moment of inertia"):
        rigid_body(needle, density=1000.0)
    assert rigid_body(needle, kind="static").kind == "static"


@pytest.mark.parametrize("kind", ["dynamic", "static"])
def test_vertices_no_face_uses_are_left_out_of_a_body(kind):
    """A stray vertex 100 m away (a mesh loaded with process=False) set the scene's extent to 100 m and the mass
    properties' bounding box (a dropped box took 309 Newton iterations instead of 179); it is dropped."""
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    stray = trimesh.Trimesh(np.vstack([box.vertices, [[100.0, 0.0, 0.0]]]), box.faces, process=False)
    a, b = rigid_body(box, kind=kind, density=500.0), rigid_body(stray, kind=kind, density=500.0)
    assert len(b.bsh.vertices) == 8 and torch.equal(a.bsh.vertices, b.bsh.vertices)
    assert a.mass == b.mass and torch.equal(a.second_moment, b.second_moment) and torch.equal(a.com, b.com)
    other = rigid_body(
        trimesh.creation.box((2.0, 2.0, 0.2)), kind="static" if kind == "dynamic" else "dynamic"
    )
    assert torch.equal(Scene([a, other]).extent, Scene([b, other]).extent)


def test_an_inside_out_mesh_is_refused_with_the_fix():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.invert()
    with _says("must enclose a positive volume (outward normals), got -1.0; its faces are wound inward: "):
        rigid_body(box)
    box.invert()
    assert rigid_body(box).mass == 1000.0


def test_a_friction_slip_scale_that_underflows_is_refused_by_name():
    """friction_eps_v = 1e-160 (or 1e-300) failed in the step as a non-finite energy naming neither it nor
    friction: (eps_v dt)^2 underflows; 1e-30 steps."""
    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=500.0)
    floor = rigid_body(trimesh.creation.box((2.0, 2.0, 0.2)), kind="static")
    for tiny in (1e-160, 1e-300):
        with _says(f"FrictionConfig.eps_v must be at least 1e-30 m/s, got {tiny!r}: the friction law works"):
            Scene([box, floor], friction=0.5, friction_eps_v=tiny)
    scene = Scene([box, floor], friction=0.5, friction_eps_v=1e-30)
    q = torch.tensor([[0, 0, 0.1015, 0, 0, 0], [0, 0, -0.1, 0, 0, 0]], dtype=F64)
    v = torch.tensor([[1.0, 0, 0, 0, 0, 0], [0.0] * 6], dtype=F64)
    assert float(step(scene, scene.initial_state(q, v)).q[0, 0]) > 0.0


def test_pair_mu_is_checked_like_pair_eps():
    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=500.0)
    floor = rigid_body(trimesh.creation.box((2.0, 2.0, 0.2)), kind="static")
    pusher = rigid_body(trimesh.creation.box((0.05, 0.05, 0.3)), kind="kinematic")
    assert Scene([box, floor, pusher], pair_mu={(1, 0): 2e-8}).pair_mu == {(1, 0): 2e-8}
    why = "is a pair without contact (neither body is dynamic, or the pair is excluded or two links of one robot)"
    with _says(f"pair_mu: (1, 2) {why}: its stiffness would never be used"):
        Scene([box, floor, pusher], pair_mu={(1, 2): 1e-8})
    with _says("pair_mu: the stiffness of (0, 1) must be a finite positive number"):
        Scene([box, floor, pusher], pair_mu={(0, 1): -1e-8})
    with _says("pair_mu: the stiffness of (0, 1) must be at most 1e+250"):
        Scene([box, floor, pusher], pair_mu={(0, 1): 1e300})
    with _says("pair_mu: (0, 5) is not a pair of two body indices in [0, 3)"):
        Scene([box, floor, pusher], pair_mu={(0, 5): 1e-8})
    with _says("pair_mu: (1, 0) and (0, 1) are one pair, given 2e-08 and 1e-08"):
        Scene([box, floor, pusher], pair_mu={(0, 1): 1e-8, (1, 0): 2e-8})
    with pytest.raises(TypeError, match=r"pair_mu must be a mapping \{\(i, j\): mu\}"):
        Scene([box, floor, pusher], pair_mu=[(0, 1, 1e-8)])
    with _says(
        "pair_mu sets stiffnesses of this library's potential; the contact model potential='ipc' has its own"
    ):
        Scene([box, floor, pusher], pair_mu={(0, 1): 1e-8}, potential="ipc")
    scene = Scene([box, floor, pusher], pair_mu={(0, 1): 2e-8})
    assert scene.replace(dt=0.02).pair_mu == {(0, 1): 2e-8}  # carried over


def test_pair_eps_of_a_pair_without_contact_is_refused():
    """A blend width for a pair the scene never evaluates (static-kinematic, excluded) was accepted silently and
    never used (a user audit)."""
    box = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=500.0)
    floor = rigid_body(trimesh.creation.box((2.0, 2.0, 0.2)), kind="static")
    pusher = rigid_body(trimesh.creation.box((0.05, 0.05, 0.3)), kind="kinematic")
    assert Scene([box, floor, pusher], pair_eps={(2, 0): 1.0}).pair_eps == {(2, 0): 1.0}
    why = "is a pair without contact (neither body is dynamic, or the pair is excluded or two links of one robot)"
    with _says(f"pair_eps: (1, 2) {why}"):
        Scene([box, floor, pusher], pair_eps={(1, 2): 1.0})
    with _says(f"pair_eps: (2, 0) {why}"):
        Scene([box, floor, pusher], pair_eps={(2, 0): 1.0}, exclude=[(0, 2)])
