"""MJCF front end: links, joints, actuators and mass properties against MuJoCo's compiled model; link frame
conventions against mujoco.mj_kinematics (through a numpy reference FK of the spec and through pytorch-kinematics);
refusals."""

import importlib.resources
import math
import os
import warnings

import mujoco
import numpy as np
import pytest
import torch

from cfd_torch.sim.mjcf import MJCFModel, gymnasium_ant_xml, load_mjcf

# Boxes, cylinders, ellipsoids, a capsule, an explicit-mass geom, an unnamed geom, a geom outside
# inertiagrouprange, defaults classes, fromto, euler/axisangle/xyaxes/zaxis in degrees, two hinges (with
# anchors) on one body, a slide joint, an <inertial> with fullinertia (inertiafromgeom auto), a welded body in
# the middle of the tree, a fixed root and a floor plane that must be ignored.
ZOO_XML = """
<mujoco model="zoo">
  <compiler autolimits="true" inertiagrouprange="0 3"/>
  <default>
    <geom density="700"/>
    <joint damping="0.3" armature="0.01"/>
    <default class="heavy"><geom density="2500"/></default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="base" pos="0.1 -0.2 0.5" euler="10 20 30">
      <geom name="base_box" type="box" size="0.2 0.15 0.05" pos="0 0 0.01" quat="0.9 0.1 0.2 0.3"/>
      <body name="column" pos="0 0 0.1" axisangle="0 0 1 25">
        <geom name="column_cyl" class="heavy" type="cylinder" fromto="0 0 0 0 0.05 0.3" size="0.04"/>
        <body name="arm" pos="0 0.05 0.3" xyaxes="0 1 0 -1 0 0">
          <joint name="yaw" axis="0 0 1" pos="0.01 0.02 0" range="-60 60"/>
          <joint name="pitch" axis="1 1 0" pos="0 0 0.03" stiffness="2" springref="0.1"/>
          <geom name="arm_capsule" type="capsule" fromto="0 0 0 0.3 0 0.1" size="0.03"/>
          <geom name="arm_ellipsoid" type="ellipsoid" size="0.05 0.03 0.02" pos="0.3 0 0.1" euler="30 20 10"
                mass="0.25"/>
          <body name="slider" pos="0.3 0 0.1" zaxis="0 1 1">
            <joint name="extend" type="slide" axis="1 0 0.5" range="0 0.2" damping="2"/>
            <geom type="sphere" size="0.04" pos="0.05 0 0"/>
            <geom name="slider_box" type="box" size="0.02 0.03 0.04"/>
            <geom name="decor" type="box" size="0.5 0.5 0.5" group="4"/>
            <body name="tip" pos="0.1 0 0">
              <inertial pos="0.01 0.02 0.03" mass="0.3" fullinertia="0.002 0.003 0.004 0.0001 -0.0002 0.0003"/>
              <joint name="wrist" axis="0 1 0"/>
              <geom name="tip_sphere" type="sphere" size="0.02"/>
            </body>
          </body>
        </body>
      </body>
      <body name="side" pos="0.2 0 0">
        <joint name="side_hinge" axis="0 1 0" range="-30 30" limited="true"/>
        <geom name="side_cyl" class="heavy" type="cylinder" size="0.03 0.1"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m_yaw" joint="yaw" gear="2" ctrlrange="-1 1"/>
    <position name="p_extend" joint="extend" kp="50" kv="3" ctrlrange="0 0.2"/>
    <motor name="m_wrist" joint="wrist" forcerange="-5 5"/>
  </actuator>
</mujoco>
"""

# inertiafromgeom="false": every body's mass comes from its <inertial>, the geoms only shape it; "bare" (welded)
# has none, so it is massless.
INERTIAL_XML = """
<mujoco model="inertial">
  <compiler inertiafromgeom="false"/>
  <worldbody>
    <body name="root" pos="0 0 1">
      <freejoint name="float"/>
      <inertial pos="0 0 0.1" mass="2" diaginertia="0.1 0.2 0.3"/>
      <geom name="root_box" type="box" size="0.1 0.1 0.1"/>
      <body name="welded" pos="0.2 0 0" euler="0 0 90">
        <inertial pos="0.05 0 0" quat="0.8 0.6 0 0" mass="0.5" diaginertia="0.01 0.02 0.025"/>
        <geom name="welded_sphere" type="sphere" size="0.05"/>
      </body>
      <body name="bare" pos="0 0.2 0">
        <geom name="bare_sphere" type="sphere" size="0.05"/>
      </body>
      <body name="leg" pos="0 0 -0.2">
        <joint name="knee" axis="1 0 0"/>
        <inertial pos="0 0 -0.1" mass="1" diaginertia="0.03 0.03 0.001"/>
        <geom name="leg_capsule" type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def ant() -> MJCFModel:
    return load_mjcf(gymnasium_ant_xml())


@pytest.fixture(scope="module")
def zoo() -> MJCFModel:
    return load_mjcf(ZOO_XML)


def _quat_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation of a unit quaternion (w, x, y, z), written out."""
    w, x, y, z = np.asarray(quat) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _reference_fk(model: MJCFModel, q: np.ndarray, base: np.ndarray | None = None) -> list[np.ndarray]:
    """World (4, 4) link frames: T_link = T_parent @ [quat, pos] @ prod_j J_j(q_j), J = translate(pos) @
    rotate(axis, q) @ translate(-pos) for a hinge, translate(axis q) for a slide; base = the free joint's
    (7,) pos + quat for a floating root, replacing the root's [quat, pos]."""
    frames = []
    for k, link in enumerate(model.links):
        if k == 0 and base is not None:
            T = _pose(_quat_matrix(base[3:]), base[:3])
        else:
            T = _pose(_quat_matrix(link.quat), link.pos)
            if link.parent >= 0:
                T = frames[link.parent] @ T
        for j in model.link_joint[k]:
            joint = model.joints[j]
            if joint.kind == "hinge":
                R = _axis_rotation(joint.axis, q[j])
                T = T @ _pose(R, joint.pos - R @ joint.pos)
            else:
                T = T @ _pose(np.eye(3), joint.axis * q[j])
        frames.append(T)
    return frames


def _mujoco_state(model: MJCFModel, q: np.ndarray, base: np.ndarray | None = None):
    m = mujoco.MjModel.from_xml_string(model.xml)
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    for joint, value in zip(model.joints, q, strict=True):
        d.qpos[m.joint(joint.name).qposadr[0]] = value
    if base is not None:
        d.qpos[:7] = base
    mujoco.mj_kinematics(m, d)
    return m, d


def _check_fk(model: MJCFModel, q: np.ndarray, base: np.ndarray | None = None) -> None:
    m, d = _mujoco_state(model, q, base)
    for link, T in zip(model.links, _reference_fk(model, q, base), strict=True):
        b = m.body(link.name).id
        np.testing.assert_allclose(T[:3, 3], d.xpos[b], rtol=0, atol=1e-10, err_msg=link.name)
        np.testing.assert_allclose(T[:3, :3], d.xmat[b].reshape(3, 3), rtol=0, atol=1e-10, err_msg=link.name)


def _check_mass_properties(model: MJCFModel) -> None:
    """Each link against MuJoCo's compiled body_mass, body_ipos, body_inertia, body_iquat.

    A single-body link: mass, COM and principal moments to 1e-10 relative. Every link, welded groups included,
    against the combination of MuJoCo's bodies (world frame at qpos0, mapped into the link frame by MuJoCo's own
    kinematics): 1e-10 relative when each body's principal axes are exact (at most one mass-carrying geom, or an
    <inertial>). MuJoCo finds the principal axes of a summed inertia (body_iquat) with mju_eig3, a Jacobi solver
    that stops at a tolerance, leaving off-diagonal residuals up to ~1e-7 relative where principal moments nearly
    coincide; passing our inertia through mju_eig3 gives its body_inertia and body_iquat to 1e-18, but the
    axes it returns are not a stable function of the input, so those links are compared within 1e-5.
    """
    m, d = _mujoco_state(model, np.zeros(len(model.joints)))
    for link in model.links:
        ids = [m.body(name).id for name in link.bodies]
        if len(ids) == 1:
            b = ids[0]
            assert link.mass == pytest.approx(m.body_mass[b], rel=1e-10), link.name
            np.testing.assert_allclose(link.com, m.body_ipos[b], rtol=0, atol=1e-10 * np.abs(link.com).max())
            inertia = np.trace(link.second_moment) * np.eye(3) - link.second_moment
            np.testing.assert_allclose(
                np.linalg.eigvalsh(inertia), np.sort(m.body_inertia[b]), rtol=1e-10, err_msg=link.name
            )
        mass = sum(m.body_mass[b] for b in ids)
        com = sum(m.body_mass[b] * d.xipos[b] for b in ids) / mass
        S = np.zeros((3, 3))
        for b in ids:
            R = d.ximat[b].reshape(3, 3)
            inertia = R @ np.diag(m.body_inertia[b]) @ R.T
            r = d.xipos[b] - com
            S += 0.5 * np.trace(inertia) * np.eye(3) - inertia + m.body_mass[b] * np.outer(r, r)
        R_link, p_link = d.xmat[ids[0]].reshape(3, 3), d.xpos[ids[0]]
        com_link, S_link = R_link.T @ (com - p_link), R_link.T @ S @ R_link
        scale = max(np.linalg.norm(com_link), math.sqrt(np.trace(S_link) / mass))
        assert link.mass == pytest.approx(mass, rel=1e-10), link.name
        np.testing.assert_allclose(link.com, com_link, rtol=0, atol=1e-10 * scale, err_msg=link.name)
        exact = all(sum(g.mass > 0 for g in link.geoms if g.body == m.body(b).name) <= 1 for b in ids)
        tol = 1e-10 if exact else 1e-5
        np.testing.assert_allclose(
            link.second_moment, S_link, rtol=0, atol=tol * np.abs(S_link).max(), err_msg=link.name
        )


def _check_meshes(model: MJCFModel) -> None:
    for link in model.links:
        assert link.geoms, link.name
        for geom in link.geoms:
            assert geom.mesh.is_watertight and geom.mesh.is_winding_consistent, (link.name, geom.name)
            assert geom.mesh.volume > 0, (link.name, geom.name)  # outward normals
        assert len(link.mesh.faces) == sum(len(g.mesh.faces) for g in link.geoms)


def test_ant_structure(ant: MJCFModel) -> None:
    names = ["torso"] + [n for k in range(1, 5) for n in (f"aux_{k}", f"ankle_{k}_link")]
    assert [link.name for link in ant.links] == names
    assert [link.parent for link in ant.links] == [-1, 0, 1, 0, 3, 0, 5, 0, 7]
    assert ant.links[0].bodies == ("torso", "front_left_leg", "front_right_leg", "back_leg", "right_back_leg")
    assert ant.floating
    assert [j.name for j in ant.joints] == [n for k in range(1, 5) for n in (f"hip_{k}", f"ankle_{k}")]
    assert ant.link_joint == ((),) + tuple((k,) for k in range(8))
    ankle = {1: (30, 70), 2: (-70, -30), 3: (-70, -30), 4: (30, 70)}
    for j in ant.joints:
        lo, hi = (-30, 30) if j.name.startswith("hip") else ankle[int(j.name[-1])]
        assert j.kind == "hinge"
        assert j.range == pytest.approx((math.radians(lo), math.radians(hi)), rel=1e-15)
        assert (j.damping, j.armature, j.stiffness) == (1.0, 1.0, 0.0)
        assert np.linalg.norm(j.axis) == pytest.approx(1.0)
    joint_order = ["hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3"]
    assert [ant.joints[a.joint].name for a in ant.actuators] == joint_order
    for a in ant.actuators:
        assert (a.kind, a.gear, a.ctrlrange, a.kp, a.kv, a.forcerange) == (
            "motor",
            150.0,
            (-1.0, 1.0),
            0,
            0,
            None,
        )
    assert ant.links[0].geoms[0].kind == "sphere" and {g.kind for g in ant.links[1].geoms} == {"capsule"}
    assert all(g.conaffinity == 0 for link in ant.links for g in link.geoms)


def test_ant_mass_properties_and_meshes(ant: MJCFModel) -> None:
    _check_mass_properties(ant)
    _check_meshes(ant)


def test_ant_reference_fk_matches_mujoco(ant: MJCFModel) -> None:
    rng = np.random.default_rng(0)
    for _ in range(5):
        base = np.concatenate([rng.normal(size=3), rng.normal(size=4)])
        base[3:] /= np.linalg.norm(base[3:])
        _check_fk(ant, rng.uniform(-1.5, 1.5, size=8), base)


def test_ant_pytorch_kinematics_matches_mujoco(ant: MJCFModel) -> None:
    chain = ant.chain
    assert chain.dtype == torch.float64
    rng = np.random.default_rng(1)
    q = rng.uniform(-1.5, 1.5, size=8)
    by_name = dict(zip([j.name for j in ant.joints], q, strict=True))
    th = torch.tensor([[by_name[n] for n in chain.get_joint_parameter_names()]], dtype=torch.float64)
    frames = chain.forward_kinematics(th)
    m, d = _mujoco_state(ant, q)  # free joint at qpos0: the torso at its MJCF pose, as pk's root frame
    assert len(frames) == m.nbody - 1
    for name, transform in frames.items():
        b = m.body(name).id
        T = transform.get_matrix()[0].numpy()
        np.testing.assert_allclose(T[:3, 3], d.xpos[b], rtol=0, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(T[:3, :3], d.xmat[b].reshape(3, 3), rtol=0, atol=1e-10, err_msg=name)


def test_zoo_structure(zoo: MJCFModel) -> None:
    assert [link.name for link in zoo.links] == ["base", "arm", "slider", "tip", "side"]
    assert [link.parent for link in zoo.links] == [-1, 0, 1, 2, 0]
    assert zoo.links[0].bodies == ("base", "column")
    assert not zoo.floating
    assert zoo.chain is None  # two joints on "arm": pytorch-kinematics cannot build it
    assert [j.name for j in zoo.joints] == ["yaw", "pitch", "extend", "wrist", "side_hinge"]
    assert zoo.link_joint == ((), (0, 1), (2,), (3,), (4,))
    yaw, pitch, extend, wrist, side = zoo.joints
    assert yaw.range == pytest.approx((-math.pi / 3, math.pi / 3), rel=1e-15)
    assert pitch.range is None and wrist.range is None
    assert extend.kind == "slide" and extend.range == (0.0, 0.2) and extend.damping == 2.0
    np.testing.assert_allclose(extend.axis, np.array([1, 0, 0.5]) / math.sqrt(1.25), rtol=1e-15)
    np.testing.assert_allclose(pitch.axis, np.array([1, 1, 0]) / math.sqrt(2), rtol=1e-15)
    np.testing.assert_array_equal(yaw.pos, [0.01, 0.02, 0])
    assert (pitch.stiffness, pitch.damping, pitch.armature) == (2.0, 0.3, 0.01)
    assert pitch.springref == pytest.approx(math.radians(0.1), rel=1e-15)  # angle="degree" converts springref
    assert side.range == pytest.approx((-math.pi / 6, math.pi / 6), rel=1e-15)
    m_yaw, p_extend, m_wrist = zoo.actuators
    assert (m_yaw.kind, m_yaw.joint, m_yaw.gear, m_yaw.ctrlrange) == ("motor", 0, 2.0, (-1.0, 1.0))
    assert (p_extend.kind, p_extend.joint, p_extend.kp, p_extend.kv) == ("position", 2, 50.0, 3.0)
    assert (m_wrist.ctrlrange, m_wrist.forcerange) == (None, (-5.0, 5.0))
    base_geoms = [g.name for g in zoo.links[0].geoms]
    assert base_geoms == ["base_box", "column_cyl"]  # the floor is not part of the model
    slider = zoo.links[2].geoms
    assert [g.name for g in slider] == ["", "slider_box", "decor"] and slider[2].mass == 0.0
    assert zoo.links[1].geoms[1].mass == 0.25 and zoo.links[3].geoms[0].mass == 0.0


def test_zoo_mass_properties_and_meshes(zoo: MJCFModel) -> None:
    _check_mass_properties(zoo)
    _check_meshes(zoo)
    kinds = {g.kind for link in zoo.links for g in link.geoms}
    assert kinds == {"sphere", "capsule", "box", "cylinder", "ellipsoid"}


def test_zoo_reference_fk_matches_mujoco(zoo: MJCFModel) -> None:
    rng = np.random.default_rng(2)
    for _ in range(5):
        _check_fk(zoo, rng.uniform(-1.5, 1.5, size=5))


def test_inertial_elements_with_inertiafromgeom_false() -> None:
    model = load_mjcf(INERTIAL_XML)
    assert [link.name for link in model.links] == ["root", "leg"] and model.floating
    assert model.links[0].mass == pytest.approx(2.5, rel=1e-15)
    assert all(g.mass == 0.0 for link in model.links for g in link.geoms)
    _check_mass_properties(model)
    _check_meshes(model)
    _check_fk(model, np.array([0.7]), np.array([0.1, 0.2, 0.3, 0.5, 0.5, -0.5, 0.5]))


def _one_body(inner: str, name: str = 'name="b"') -> str:
    return f"""<mujoco><worldbody><body name="a"><geom size="0.1"/>
      <body {name} pos="1 0 0"><geom size="0.1"/>{inner}</body></body></worldbody></mujoco>"""


@pytest.mark.parametrize("asset", ["ant.xml", "half_cheetah.xml"])
def test_unnamed_bodies_and_settotalmass(asset: str) -> None:
    """Gymnasium's Ant as shipped (unnamed shins) and half_cheetah (settotalmass 14): unnamed bodies get names from
    their parents, masses are scaled as MuJoCo scales them (mass properties against the compiled model)."""
    model = load_mjcf(str(importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / asset))
    if asset == "ant.xml":
        assert [link.name for link in model.links][1:3] == ["aux_1", "aux_1/0"]
    else:
        assert sum(link.mass for link in model.links) == pytest.approx(14.0, rel=1e-12)
    _check_mass_properties(model)
    _check_meshes(model)
    assert load_mjcf(_one_body('<joint name="h"/>', name="")).links[1].name == "a/0"


def test_unnamed_bodies_and_includes_keep_the_text_as_written(tmp_path) -> None:
    """A model with an unnamed body or an <include> loads from its own text (bodies named, includes inlined), not
    from MuJoCo's rewrite of it, which drops settotalmass and inertiagrouprange and rounds numbers to 6 digits:
    masses, inertias, ranges and refs against MuJoCo compiled from the user's file (the rewrite gave 219.67 kg for a
    3.67 kg link, ranges off by 1e-7); the refusals read the same text."""
    inner = """<body NAME pos="0.5 0 0" euler="17 23 41"><joint name="j1" range="-33 47" ref="11"/>
      <geom type="capsule" size="0.05 0.2" group="1"/><geom type="box" size="0.3 0.3 0.3" contype="0"
      conaffinity="0"/><inertial pos="0.1 -0.2 0.3" mass="1.5" fullinertia="0.1 0.2 0.25 0.01 -0.02 0.03"/></body>"""
    head = '<mujoco><compiler settotalmass="10" inertiagrouprange="1 3" inertiafromgeom="auto"/><worldbody>'
    xml = f'{head}<body name="r"><geom size="0.1" group="1"/>{inner}</body></worldbody></mujoco>'
    named = inner.replace("NAME", 'name="a"')
    (tmp_path / "parts.xml").write_text(f"<mujocoinclude>{named}</mujocoinclude>")
    (tmp_path / "model.xml").write_text(xml.replace(inner, '<include file="parts.xml"/>'))
    for source, name in ((xml.replace("NAME", ""), "r/0"), (str(tmp_path / "model.xml"), "a")):
        model = load_mjcf(source)
        m = mujoco.MjModel.from_xml_path(source) if name == "a" else mujoco.MjModel.from_xml_string(source)
        assert [link.name for link in model.links] == ["r", name]
        assert sum(link.mass for link in model.links) == pytest.approx(10.0, rel=1e-12)
        for b, link in enumerate(model.links, start=1):  # (MuJoCo's body ids: world 0, r 1, its child 2)
            assert link.mass == pytest.approx(float(m.body_mass[b]), rel=1e-12)
            S = link.second_moment
            moments = np.linalg.eigvalsh(np.trace(S) * np.eye(3) - S)
            np.testing.assert_allclose(moments, np.sort(m.body_inertia[b]), rtol=1e-10)
        assert model.joints[0].range == tuple(float(x) for x in m.jnt_range[0])
        assert model.joints[0].ref == float(m.qpos0[0])
        assert "<include" not in model.xml and 'settotalmass="10"' in model.xml
    with pytest.raises(ValueError, match='compiler fusestatic="true" is not supported'):
        load_mjcf(xml.replace("NAME", "").replace("<compiler ", '<compiler fusestatic="true" '))
    (tmp_path / "loop.xml").write_text('<mujoco><include file="loop.xml"/></mujoco>')
    with pytest.raises(ValueError, match="loop.xml is already included"):
        load_mjcf(str(tmp_path / "loop.xml"))
    with pytest.raises(ValueError, match="<include file='missing.xml'>: cannot read"):
        load_mjcf(xml.replace(inner, '<include file="missing.xml"/>'))


def test_include_and_naming_rules_follow_mujoco(tmp_path) -> None:
    """MuJoCo's rules, against its compiled masses: two <worldbody> sections (a scene including its robot, each with
    unnamed bodies) are one world, numbered together (both were named "world/0"); a nested include is looked for
    beside the including file when the main folder lacks it; unnamed bodies inside <replicate> are named (they were
    refused); a generated name never takes a user's ("a/0"); a file included twice is refused, as MuJoCo does."""

    def write(name: str, text: str) -> str:
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        return str(path)

    def masses(path: str, **kw) -> None:
        m = mujoco.MjModel.from_xml_path(path)
        model = load_mjcf(path, **kw)
        for b, link in enumerate(model.links, start=1):  # (each link one body, MuJoCo's in the same order)
            assert link.mass == pytest.approx(float(m.body_mass[b]), rel=1e-12), link.name
        return model

    box = '<geom type="box" size=".1 .1 .1" mass="2"/>'
    ball = '<geom type="sphere" size=".05" mass=".5"/>'
    write("robot.xml", f'<mujoco><worldbody><body pos="0 0 1"><freejoint/>{box}<body pos=".2 0 0"><joint name="j1"/>'
          f"{ball}</body></body></worldbody></mujoco>")  # fmt: skip
    scene = write("scene.xml", '<mujoco><include file="robot.xml"/><worldbody><body pos="3 0 .5">'
                  '<geom type="box" size=".3 .3 .5" mass="7"/></body></worldbody></mujoco>')  # fmt: skip
    assert [link.name for link in masses(scene, root="world/0").links] == ["world/0", "world/0/0"]
    assert "world/1" in load_mjcf(scene, root="world/1").xml
    write(
        "sub/deeper/foot.xml",
        f'<mujoco><body name="foot" pos=".2 0 0"><joint name="ankle"/>{ball}</body></mujoco>',
    )
    write("sub/leg.xml", f'<mujoco><body name="leg" pos=".2 0 0"><joint name="hip"/>{ball}'
          '<include file="deeper/foot.xml"/></body></mujoco>')  # fmt: skip
    nested = write("nested.xml", f'<mujoco><worldbody><body name="root">{box}<include file="sub/leg.xml"/></body>'
                   "</worldbody></mujoco>")  # fmt: skip
    assert [link.name for link in masses(nested).links] == ["root", "leg", "foot"]
    rep = write("rep.xml", f'<mujoco><worldbody><body name="a">{box}<replicate count="3" offset=".3 0 0">'
                f'<body name="r" pos=".2 0 0"><joint name="jr"/>{ball}<body pos=".1 0 0">{ball}</body></body>'
                "</replicate></body></worldbody></mujoco>")  # fmt: skip
    assert [link.mass for link in load_mjcf(rep).links] == pytest.approx([2.0, 1.0, 1.0, 1.0], rel=1e-12)
    clash = write("clash.xml", f'<mujoco><worldbody><body name="a">{box}<body pos=".2 0 0"><joint name="j1"/>'
                  f'{ball}</body><body name="a/0" pos="-.2 0 0"><joint name="j2"/>{box}</body></body></worldbody>'
                  "</mujoco>")  # fmt: skip
    assert [link.name for link in masses(clash).links] == ["a", "a/0_", "a/0"]
    write("part.xml", f"<mujoco>{ball}</mujoco>")
    twice = write("twice.xml", '<mujoco><worldbody><body name="a"><include file="part.xml"/><body name="b">'
                  '<joint name="j"/><include file="part.xml"/></body></body></worldbody></mujoco>')  # fmt: skip
    with pytest.raises(ValueError, match="part.xml is already included"):
        load_mjcf(twice)


def test_hinge_ranges_that_look_like_radians_are_warned_of() -> None:
    """MJCF angles are degrees unless <compiler angle="radian"/> says otherwise: a model that leaves the compiler's
    angle unset and whose every limited hinge lies within +-2 pi "degrees" is warned of (a user's range="-2.8 2.8"
    loaded silently as +-0.049 rad); radians declared, or ranges in plain degrees, load quietly."""
    arm = _one_body('<joint name="h" range="-2.8 2.8"/>')
    with pytest.warns(UserWarning, match="joint 'h': -2.8 .. 2.8 degrees.*angle=\"radian\""):
        assert load_mjcf(arm).joints[0].range == pytest.approx((-2.8 * math.pi / 180, 2.8 * math.pi / 180))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mjcf(arm.replace("<mujoco>", '<mujoco><compiler angle="radian"/>')).joints[0].range == (
            -2.8,
            2.8,
        )
        load_mjcf(_one_body('<joint name="h" range="-120 120"/>'))


def test_refusals() -> None:
    with pytest.raises(ValueError, match="free joint 'fj' in body 'b'"):
        load_mjcf(_one_body('<freejoint name="fj"/>'))
    with pytest.raises(ValueError, match="joint 'bj' of body 'b': ball joints"):
        load_mjcf(_one_body('<joint name="bj" type="ball"/>'))
    with pytest.raises(ValueError, match="geom 'ground' of body 'b' has unsupported type plane"):
        load_mjcf(_one_body('<geom name="ground" type="plane" size="1 1 0.1"/>'))
    with pytest.raises(ValueError, match="geom 'hull' of body 'b': shell inertia"):
        load_mjcf(_one_body('<joint name="h"/><geom name="hull" size="0.1" shellinertia="true"/>'))
    two_roots = '<mujoco><worldbody><body name="a"/><body name="c"/></worldbody></mujoco>'
    with pytest.raises(ValueError, match="2 top-level bodies"):
        load_mjcf(two_roots)


def test_visual_only_mesh_geoms_are_left_out_with_a_warning() -> None:
    """The common robot-file pattern: mesh geoms that never collide (contype = conaffinity = 0) in bodies whose
    mass comes from <inertial>; MuJoCo's masses are the same with or without them, and so are ours."""
    xml = """<mujoco><asset><mesh name="shell" vertex="0 0 0 .1 0 0 0 .1 0 0 0 .1"/></asset>
     <default><default class="visual"><geom type="mesh" contype="0" conaffinity="0" group="2"/></default></default>
     <worldbody><body name="base"><inertial pos="0 0 0" mass="2" diaginertia=".01 .01 .01"/>
      <geom type="box" size=".1 .1 .1"/>{v}
      <body name="arm" pos="0 0 .1"><joint name="j" axis="0 1 0"/>
       <inertial pos="0 0 .1" mass="1" diaginertia=".002 .002 .001"/>
       <geom type="capsule" fromto="0 0 0 0 0 .2" size=".02"/>{v}</body></body></worldbody></mujoco>"""
    plain = load_mjcf(xml.format(v=""))
    with pytest.warns(UserWarning, match=r"geoms \['base/#1', 'arm/#1'\] are left out"):
        model = load_mjcf(xml.format(v='<geom class="visual" mesh="shell"/>'))
    for a, b in zip(model.links, plain.links, strict=True):
        assert a.mass == b.mass and len(a.geoms) == len(b.geoms) == 1
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    # in a body without <inertial> (its geoms' masses count), a visual mesh of no mass is left out too
    bare = xml.replace('<inertial pos="0 0 0" mass="2" diaginertia=".01 .01 .01"/>', "")
    for zero in ('mass="0"', 'density="0"'):
        with pytest.warns(UserWarning, match=r"geoms \['base/#1', 'arm/#1'\] are left out"):
            load_mjcf(bare.format(v=f'<geom class="visual" mesh="shell" {zero}/>'))
    # a mesh geom MuJoCo collides, or whose mass counts, is a geom of its link (section "mesh geoms" below)
    collides = load_mjcf(xml.format(v='<geom type="mesh" mesh="shell"/>'))
    for a, b in zip(collides.links, plain.links, strict=True):
        assert a.mass == b.mass and len(a.geoms) == 2 and a.geoms[1].kind == "mesh"
        assert len(a.mesh.faces) == len(b.mesh.faces) + 4  # the tetrahedron MuJoCo makes of the four vertices
    with pytest.warns(
        UserWarning, match=r"geoms \['arm/#1'\] are left out"
    ):  # (the arm's mass: its <inertial>)
        counted = load_mjcf(bare.format(v='<geom class="visual" mesh="shell"/>'))
    assert counted.links[0].mass == pytest.approx(1000 * (0.2**3 + 0.1**3 / 6), rel=1e-6)  # box + tetrahedron


def test_source_must_be_text_or_a_path() -> None:
    one = _one_body('<geom size="0.1"/>')
    for bad in (0, one.encode()):  # an int would be read as a file descriptor (0: stdin)
        with pytest.raises(TypeError, match="source must be MJCF text or a path"):
            load_mjcf(bad)
    assert [link.name for link in load_mjcf("\ufeff" + one).links] == [
        "a"
    ]  # a byte-order mark before the text


def test_chain_of_a_nested_root_and_its_joint_limits() -> None:
    """The pytorch-kinematics chain of a root hung in a joint-less parent: its frames are MuJoCo's world frames
    (the parent's transform composed), and unlimited joints have infinite limits (pk copies the unused range)."""
    xml = """<mujoco><worldbody><body name="table" pos="0 0 0.8" euler="0 0 90">
      <body name="root" pos="0.1 0.2 0.05"><geom type="box" size=".1 .1 .05"/>
        <body name="link" pos="0 0 0.1"><joint name="h" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 .3 0 0" size=".02"/>
          <body name="slider" pos=".3 0 0"><joint name="s" type="slide" axis="1 0 0" range="-0.1 0.2"/>
            <geom type="sphere" size=".03"/></body></body></body></body></worldbody></mujoco>"""
    model = load_mjcf(xml, root="root")
    m = mujoco.MjModel.from_xml_string(model.xml)
    d = mujoco.MjData(m)
    d.qpos[:] = [0.4, 0.05]
    mujoco.mj_kinematics(m, d)
    frames = model.chain.forward_kinematics(torch.tensor([0.4, 0.05], dtype=torch.float64))
    for name in ("root", "link", "slider"):
        T = frames[name].get_matrix()[0].numpy()
        np.testing.assert_allclose(T[:3, 3], d.xpos[m.body(name).id], rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(T[:3, :3], d.xmat[m.body(name).id].reshape(3, 3), rtol=0, atol=1e-12)
    assert model.chain.get_joint_limits() == ([-math.inf, -0.1], [math.inf, 0.2])


def test_options_and_attributes_the_step_does_not_model_are_refused_or_warned() -> None:
    """What the file would change but the step ignores: flags that switch modelled physics off are refused, the
    file's gravity and per-geom friction are warned of (the Scene's apply), damping or armature on the free base
    joint and tendon friction loss are refused; the mesh resolutions are checked."""
    body = _one_body('<joint name="h"/>')
    with pytest.raises(ValueError, match='MJCF <flag gravity="disable" limit="disable">'):
        load_mjcf(
            body.replace("<mujoco>", '<mujoco><option><flag gravity="disable" limit="disable"/></option>')
        )
    with pytest.raises(ValueError, match='MJCF <flag contact="disable" constraint="disable">'):
        load_mjcf(
            body.replace(
                "<mujoco>", '<mujoco><option><flag contact="disable" constraint="disable"/></option>'
            )
        )
    with pytest.warns(UserWarning, match="joint margin of 'h' \\(0.2\\): ignored"):
        load_mjcf(_one_body('<joint name="h" range="-1 1" margin="0.2"/>'))
    with pytest.raises(TypeError, match="root must be the name of a body"):
        load_mjcf(body, root=3)
    with pytest.raises(ValueError, match="not 'world' itself"):
        load_mjcf(body, root="world")
    with pytest.warns(UserWarning, match="gravity=\\(0.0, 0.0, -1.62\\)>: ignored"):
        load_mjcf(body.replace("<mujoco>", '<mujoco><option gravity="0 0 -1.62"/>'))
    contact = '<contact><pair geom1="g1" geom2="g2" friction="0.1 0.1 0.005 0.0001 0.0001"/></contact>'
    named = body.replace('<geom size="0.1"/>', '<geom name="g1" size="0.1"/>', 1).replace(
        '<geom size="0.1"/>', '<geom name="g2" size="0.1"/>', 1
    )
    with pytest.warns(UserWarning, match="1 <pair> and 0 <exclude> elements ignored"):
        load_mjcf(named.replace("</worldbody>", "</worldbody>" + contact))
    with pytest.warns(UserWarning, match="geom friction differs"):
        load_mjcf(body.replace('<joint name="h"/>', '<joint name="h"/><geom size="0.05" friction="0.1"/>'))
    free = """<mujoco><worldbody><body name="a"><freejoint name="root"/><geom size="0.1"/>
      <body name="b" pos="1 0 0"><joint name="h"/><geom size="0.1"/></body></body></worldbody></mujoco>"""
    load_mjcf(free)
    for attribute in (
        'damping="5"',
        'stiffness="200"',
    ):  # (stiffness loaded silently, with no effect, before)
        with pytest.raises(ValueError, match="free joint 'root': damping, armature and stiffness"):
            load_mjcf(
                free.replace('<freejoint name="root"/>', f'<joint name="root" type="free" {attribute}/>')
            )
    for option in (
        "discardvisual",
        "fusestatic",
    ):  # (the link masses lost the dropped geoms' or merged bodies')
        with pytest.raises(ValueError, match=f'compiler {option}="true" is not supported'):
            load_mjcf(free.replace("<mujoco>", f'<mujoco><compiler {option}="true"/>'))
    disabled = body.replace("<mujoco>", '<mujoco><option actuatorgroupdisable="2"/>').replace(
        "</worldbody>", '</worldbody><actuator><motor name="m" joint="h" group="2"/></actuator>'
    )
    with pytest.raises(
        ValueError, match="actuator 'm': its group 2 is disabled by <option actuatorgroupdisable>"
    ):
        load_mjcf(disabled)  # (its torque was applied: MuJoCo applies none)
    pid = body.replace(
        "<mujoco>",
        '<mujoco><extension><plugin plugin="mujoco.pid"><instance name="p"><config key="kp" value="40"/>'
        "</instance></plugin></extension>",
    ).replace(
        "</worldbody>",
        '</worldbody><actuator><plugin joint="h" plugin="mujoco.pid" instance="p"/></actuator>',
    )
    with pytest.raises(ValueError, match="actuator plugins \\(such as mujoco.pid\\) are not supported"):
        load_mjcf(pid)  # (it loaded as a motor, torque = ctrl)
    tendon = '<tendon><fixed name="t" frictionloss="5"><joint joint="h" coef="1"/></fixed></tendon>'
    with pytest.raises(ValueError, match="tendon 't': .*frictionloss are not supported"):
        load_mjcf(body.replace("</worldbody>", "</worldbody>" + tendon))
    for kwargs, match in (
        ({"capsule_count": (0, 0)}, "capsule_count must be two ints"),
        ({"sphere_subdivisions": 2.5}, "sphere_subdivisions must be an int"),
        ({"cylinder_sections": 2}, "cylinder_sections must be an int >= 3"),
    ):
        with pytest.raises(ValueError, match=match):
            load_mjcf(body, **kwargs)


def test_keyframes_other_bodies_actuators_and_the_model_friction() -> None:
    """A floating model with a <keyframe> loads (its pytorch-kinematics chain is compiled without the free joint,
    which the keyframe's qpos counted: refused before); actuators of another top-level body are left out with it
    (one of them failed the load, blaming its joint); ``friction`` is the geoms' shared coefficient (MuJoCo's
    default 1 where unset), None where they differ."""
    xml = """<mujoco><worldbody>
      <body name="a"><freejoint name="root"/><geom size="0.1"/>
        <body name="b" pos="0.3 0 0"><joint name="h" axis="0 1 0"/><geom size="0.1"/></body></body>
      <body name="other" pos="2 0 0"><joint name="o"/><geom size="0.1" friction="0.3"/></body>
    </worldbody>
    <actuator><motor name="m_o" joint="o"/><motor name="m_h" joint="h" gear="2"/></actuator>
    <keyframe><key name="home" qpos="0 0 1 1 0 0 0 0.5 0.1"/></keyframe></mujoco>"""
    model = load_mjcf(xml, root="a")
    assert model.floating and model.chain is not None and [j.name for j in model.joints] == ["h"]
    assert [a.name for a in model.actuators] == ["m_h"] and model.actuators[0].gear == 2.0
    assert model.friction == 1.0
    assert load_mjcf(xml, root="other").friction == 0.3
    assert [a.name for a in load_mjcf(xml, root="other").actuators] == ["m_o"]
    mixed = xml.replace('<geom size="0.1"/></body></body>', '<geom size="0.1" friction="0.5"/></body></body>')
    with pytest.warns(UserWarning, match="geom friction differs"):
        assert load_mjcf(mixed, root="a").friction is None
    # geoms MuJoCo never collides do not count, unless they are all their link has (then they collide here)
    visual = mixed.replace('friction="0.5"', 'friction="0.5" contype="0" conaffinity="0"')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert (
            load_mjcf(
                visual.replace("</body></body>", '<geom size="0.02"/></body></body>'), root="a"
            ).friction
            == 1
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert load_mjcf(visual, root="a").friction is None
    messages = " | ".join(str(w.message) for w in caught)
    assert "contype = conaffinity = 0" in messages and "colliding geoms (0.5, 1.0)" in messages, messages


def test_gymnasium_ant_with_servos() -> None:
    """gymnasium_ant_xml(servos=(kp, kv)): the eight motors become position servos on the same joints."""
    plain, servo = load_mjcf(gymnasium_ant_xml()), load_mjcf(gymnasium_ant_xml(servos=(100.0, 5.0)))
    assert [a.joint for a in servo.actuators] == [a.joint for a in plain.actuators]
    for a in servo.actuators:
        assert (a.kind, a.gear, a.kp, a.kv, a.ctrlrange, a.forcerange) == (
            "position",
            1.0,
            100.0,
            5.0,
            None,
            None,
        )
    for bad in ((0.0, 1.0), (1.0, 5.0, 3.0), "ab", 5.0):  # (unpacking and conversion errors named nothing)
        with pytest.raises(ValueError, match="servos must be"):
            gymnasium_ant_xml(servos=bad)


# ------------------------------------------------------------------------------------------------ mesh geoms
def _ring_model(folder, inertia: str, ring: str = 'density="500"') -> str:
    """An arm on a fixed base whose link carries a capsule and a torus mesh (an STL file beside the model, read
    through meshdir), tilted on its geom frame; the model file's path."""
    import trimesh

    os.makedirs(folder / "meshes", exist_ok=True)
    trimesh.creation.torus(0.3, 0.1).export(folder / "meshes" / "torus.stl")
    xml = f"""<mujoco><compiler meshdir="meshes" angle="radian"/>
      <asset><mesh name="T" file="torus.stl" inertia="{inertia}"/></asset>
      <worldbody><body name="base"><geom type="box" size=".05 .05 .05"/>
        <body name="arm"><joint name="j" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 .5 0 0" size=".02"/>
          <geom name="ring" type="mesh" mesh="T" {ring} pos=".5 0 .1" euler="1.2 .3 .1"/></body></body>
      </worldbody></mujoco>"""
    path = folder / "robot.xml"
    path.write_text(xml)
    return str(path)


def _against_mujoco(model: MJCFModel, path: str, link: str, rel: float) -> None:
    """The link's mass, COM and inertia against MuJoCo's compiled body, to ``rel`` (MuJoCo keeps mesh vertices in
    float32, so a mesh's mass properties agree to about 1e-8, not to rounding)."""
    m = mujoco.MjModel.from_xml_path(path)
    spec = next(x for x in model.links if x.name == link)
    b = m.body(link).id
    assert spec.mass == pytest.approx(m.body_mass[b], rel=rel)
    size = max(np.abs(spec.com).max(), math.sqrt(np.trace(spec.second_moment) / spec.mass))
    np.testing.assert_allclose(spec.com, m.body_ipos[b], rtol=0, atol=rel * size)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.body_iquat[b])
    R = R.reshape(3, 3)
    inertia = R @ np.diag(m.body_inertia[b]) @ R.T
    ours = np.trace(spec.second_moment) * np.eye(3) - spec.second_moment
    np.testing.assert_allclose(ours, inertia, rtol=0, atol=rel * np.abs(inertia).max())


def test_mesh_geoms_collide_and_count_their_mass_as_mujoco_does(tmp_path) -> None:
    """A mesh geom (a torus, an STL file read through meshdir) is part of its link: its triangles are MuJoCo's
    compiled mesh placed by the geom frame, and its mass properties MuJoCo's under <mesh inertia="exact"> (the
    closed mesh) and "convex" (its hull), to 1e-7; under the default "legacy", the closed mesh's, with a warning
    that quotes what MuJoCo's legacy rule counts for a mesh not star-shaped about its centre (the torus: 0.0870
    against 0.0585 m^3) and names the fix; a mesh MuJoCo's legacy rule gets right (a convex one, an icosphere with
    a dent) loads quietly, as MuJoCo has it."""
    exact = load_mjcf(_ring_model(tmp_path / "exact", "exact"))
    _against_mujoco(exact, str(tmp_path / "exact" / "robot.xml"), "arm", 1e-7)
    convex = load_mjcf(_ring_model(tmp_path / "convex", "convex"))
    _against_mujoco(convex, str(tmp_path / "convex" / "robot.xml"), "arm", 1e-7)
    arm = exact.links[1]
    ring = arm.geoms[1]
    assert (
        ring.kind == "mesh" and ring.name == "ring" and ring.mass == pytest.approx(500 * 0.0584605, rel=1e-5)
    )
    assert convex.links[1].mass > arm.mass * 1.4  # the hull holds the hole
    # the collision mesh: the capsule's triangles and the ring's, placed by the geom frame (its centre 0.1 above
    # the arm's axis, tilted): the ring's vertices lie 0.2-0.4 m from its centre, in its tilted plane
    assert len(arm.mesh.faces) == len(arm.geoms[0].mesh.faces) + len(ring.mesh.faces)
    V = np.asarray(ring.mesh.vertices)
    centre = V.mean(0)
    np.testing.assert_allclose(centre, [0.5, 0.0, 0.1], atol=1e-6)
    d = np.linalg.norm(V - centre, axis=1)
    assert 0.2 - 1e-6 < d.min() and d.max() < 0.4 + 1e-6
    with pytest.warns(
        UserWarning,
        match=r"mesh 'T' of geom 'ring' of body 'arm': .*legacy rule counts 0.0870292 .*inertia=\"exact\"",
    ):
        legacy = load_mjcf(_ring_model(tmp_path / "legacy", "legacy"))
    # (MuJoCo centres the mesh at its own legacy centre there: other float32 vertices, so not to the last bit)
    assert legacy.links[1].mass == pytest.approx(exact.links[1].mass, rel=1e-7)
    assert mujoco.MjModel.from_xml_path(str(tmp_path / "legacy" / "robot.xml")).body_mass[2] > 1.4 * arm.mass
    # a convex mesh under the default legacy rule: as MuJoCo, quietly
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cube = _one_body('<joint name="j"/><geom name="c" type="mesh" mesh="cube" density="300"/>').replace(
            "<worldbody>",
            '<asset><mesh name="cube" vertex="0 0 0 .2 0 0 0 .3 0 .2 .3 0 0 0 .1 .2 0 .1 0 .3 .1 .2 .3 .1"/></asset>'
            "<worldbody>",
        )
        model = load_mjcf(cube)
    assert model.links[1].mass == pytest.approx(1000 * 4 / 3 * math.pi * 0.1**3 + 300 * 0.006, rel=1e-7)
    (tmp_path / "cube.xml").write_text(cube)
    _against_mujoco(model, str(tmp_path / "cube.xml"), "b", 1e-7)
    import trimesh

    dent = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    dent.vertices[0] *= 0.5  # not convex, yet star-shaped about its centre: MuJoCo's legacy volume is exact
    dent.export(tmp_path / "dent.stl")
    xml = (
        f'<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh name="d" file="dent.stl"/></asset><worldbody>'
        '<body name="root"><joint name="j"/><geom type="mesh" mesh="d"/></body></worldbody></mujoco>'
    )
    (tmp_path / "dent.xml").write_text(xml)
    assert dent.convex_hull.volume > dent.volume * (1 + 1e-4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dented = load_mjcf(str(tmp_path / "dent.xml"))
    _against_mujoco(dented, str(tmp_path / "dent.xml"), "root", 1e-7)
    # an L-shaped block with a bar: star-shaped about the faces' centre, not about MuJoCo's legacy centre, where its
    # legacy rule counts 7.4 % more; the warning quotes MuJoCo's figure
    poly = (
        np.array([(0, 0), (0.8, 0), (0.8, -5), (1, -5), (1, 6), (0.8, 6), (0.8, 1), (0, 1)], dtype=float) / 10
    )
    n = len(poly)
    V = np.vstack(
        [np.c_[poly, np.zeros(n)], np.c_[poly, np.full(n, 0.5)], [0.09, 0.05, 0], [0.09, 0.05, 0.5]]
    )
    F = []
    for i in range(n):
        j = (i + 1) % n
        F += [[2 * n, j, i], [2 * n + 1, n + i, n + j], [i, j, n + j], [i, n + j, n + i]]
    block = trimesh.Trimesh(V, F)
    if block.volume < 0:
        block.invert()
    assert block.is_watertight and block.volume > 0
    block.export(tmp_path / "block.stl")
    xml = (
        f'<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh name="k" file="block.stl"/></asset><worldbody>'
        '<body name="root"><joint name="j"/><geom type="mesh" mesh="k" density="1"/></body></worldbody></mujoco>'
    )
    mujoco_legacy = float(mujoco.MjModel.from_xml_string(xml).body_mass[1])
    assert mujoco_legacy > 1.05 * block.volume
    with pytest.warns(UserWarning, match=f"legacy rule counts {mujoco_legacy:.6g} for it"):
        assert load_mjcf(xml).links[0].mass == pytest.approx(block.volume, rel=1e-6)


def test_mesh_geoms_with_degenerate_triangles_or_no_hull_are_refused_by_name(tmp_path) -> None:
    """A zero-area triangle of a mesh file comes back from MuJoCo (float32 vertices moved into the mesh's inertial
    frame) as a sliver of about 1e-8 relative area, which the float64 test let through where MuJoCo turned the
    mesh: refused by name at float32's resolution. A mesh with inertia="convex" that no geom collides with would
    crash MuJoCo 3.2.7's compiler (a segmentation fault): refused by name before it is compiled."""
    import trimesh

    box = trimesh.creation.box((0.1, 0.2, 0.3))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, [1, 2, 3]))
    V = np.vstack([box.vertices, (box.vertices[0] + box.vertices[1]) / 2])  # a point on an edge
    F = np.vstack([box.faces, [[0, len(V) - 1, 1]]])  # a zero-area triangle along that edge
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "sliver.stl")
    xml = (
        f'<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh name="s" file="sliver.stl"/></asset><worldbody>'
        '<body name="root"><inertial pos="0 0 0" mass="1" diaginertia=".01 .01 .01"/><joint name="j"/>'
        '<geom name="g" type="mesh" mesh="s"/></body></worldbody></mujoco>'
    )
    with pytest.raises(
        ValueError, match=r"mesh 's' of geom 'g' of body 'root': faces has degenerate triangles"
    ):
        load_mjcf(xml)
    # a real sliver stays: a 3 m rod of 1 mm radius in 256 sections (triangles 2.5e-5 m wide), as MuJoCo has it
    rod = trimesh.creation.cylinder(radius=1.0, height=3000.0, sections=256)
    rod.apply_scale(1e-3)
    rod.export(tmp_path / "rod.stl")
    xml = (
        f'<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh name="r" file="rod.stl" inertia="exact"/></asset>'
        '<worldbody><body name="root"><joint name="j"/><geom type="mesh" mesh="r"/></body></worldbody></mujoco>'
    )
    (tmp_path / "rod.xml").write_text(xml)
    _against_mujoco(load_mjcf(str(tmp_path / "rod.xml")), str(tmp_path / "rod.xml"), "root", 1e-6)
    box.export(tmp_path / "box.stl")
    for geom in (
        '<geom type="box" size=".1 .1 .1"/>',
        '<geom type="mesh" mesh="b" contype="0" conaffinity="0"/>',
    ):
        xml = (
            f'<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh name="b" file="box.stl" inertia="convex"/>'
            f'</asset><worldbody><body name="root"><joint name="j"/><geom size=".1"/>{geom}</body></worldbody>'
            "</mujoco>"
        )
        with pytest.raises(ValueError, match=r"mesh 'b': inertia=\"convex\" on a mesh that no geom collides"):
            load_mjcf(xml)


def test_mesh_geoms_that_need_mass_properties_must_be_closed(tmp_path) -> None:
    """An open mesh (a tetrahedron missing a face) has no volume: refused by name where its mass counts, loaded
    where it does not (an <inertial> in its body, mass="0")."""
    asset = '<asset><mesh name="open" vertex="0 0 0 .1 0 0 0 .1 0 0 0 .1" face="0 2 1 0 1 3 0 3 2"/></asset>'

    def body(geom: str, inertial: str = "") -> str:
        return _one_body(f'{inertial}<joint name="j"/>{geom}').replace("<worldbody>", asset + "<worldbody>")

    with pytest.raises(
        ValueError, match="mesh 'open' of geom 'lid' of body 'b' is not a closed, outward-wound"
    ):
        load_mjcf(body('<geom name="lid" type="mesh" mesh="open"/>'))
    ball = 1000 * 4 / 3 * math.pi * 0.1**3
    held = load_mjcf(body('<geom name="lid" type="mesh" mesh="open"/>', '<inertial pos="0 0 0" mass="2" '
                          'diaginertia=".01 .01 .01"/>'))  # fmt: skip
    assert held.links[1].mass == 2.0 and held.links[1].geoms[1].kind == "mesh"
    light = load_mjcf(body('<geom name="lid" type="mesh" mesh="open" mass="0"/>'))
    assert light.links[1].mass == pytest.approx(ball, rel=1e-12)
    assert len(light.links[1].mesh.faces) == len(light.links[1].geoms[0].mesh.faces) + 3
    # a kinematic robot's masses play no part: its mesh geoms' are not read, and the open mesh loads
    from cfd_torch import articulation

    xml = body('<geom name="lid" type="mesh" mesh="open"/>')
    with pytest.raises(ValueError, match="mesh 'open' of geom 'lid' of body 'b' is not a closed"):
        articulation(xml)
    pusher = articulation(xml, kinematic=True)
    assert pusher.num_links == 2 and len(pusher.bodies[1].bsh.faces) == len(light.links[1].mesh.faces)
    assert load_mjcf(xml, mesh_masses=False).links[1].mass == pytest.approx(ball, rel=1e-12)
    with pytest.raises(TypeError, match="mesh_masses must be a bool"):
        load_mjcf(xml, mesh_masses=0)


# ------------------------------------------------------------------------------------------------ URDF
_URDF = """<robot name="ringarm">
  <mujoco><compiler meshdir="meshes"/></mujoco>
  <link name="base">
    <inertial><origin xyz="0 0 0.05"/><mass value="2.0"/>
      <inertia ixx="0.01" iyy="0.02" izz="0.03" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.05"/><geometry><box size="0.2 0.2 0.1"/></geometry></collision>
    <visual><geometry><box size="0.2 0.2 0.1"/></geometry></visual>
  </link>
  <link name="upper">
    <inertial><origin xyz="0 0 0.2"/><mass value="1.25"/>
      <inertia ixx="0.011" iyy="0.012" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.04" length="0.4"/></geometry></collision>
  </link>
  <link name="ring">
    <inertial><origin xyz="0.3 0 0"/><mass value="3.0"/>
      <inertia ixx="0.1" iyy="0.1" izz="0.2" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0.3 0 0" rpy="1.2 0.3 0.1"/>
      <geometry><mesh filename="package://ringarm/meshes/ring.stl"/></geometry></collision>
  </link>
  <link name="tool"/>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 1 0"/><limit lower="-1.5" upper="1.5" effort="50" velocity="2"/></joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="ring"/><origin xyz="0 0 0.4" rpy="0 0.2 0"/>
    <axis xyz="1 0 0"/><dynamics damping="0.1" friction="{friction}"/></joint>
  <joint name="tool_fixed" type="fixed"><parent link="ring"/><child link="tool"/><origin xyz="0.9 0 0"/></joint>
</robot>"""


def _urdf_file(folder, friction: float = 0.0) -> str:
    import trimesh

    os.makedirs(folder / "meshes", exist_ok=True)
    trimesh.creation.torus(0.3, 0.1).export(folder / "meshes" / "ring.stl")
    path = folder / "ringarm.urdf"
    path.write_text(_URDF.format(friction=friction))
    return str(path)


def test_urdf_is_read_with_mujocos_importer(tmp_path, capfd) -> None:
    """A URDF (primitives, a package:// mesh found in its meshdir, a revolute joint with an effort limit, a
    continuous one with damping, a fixed joint) loads as MuJoCo imports it: the links and joints it names, its
    <inertial>s as the links' masses, link frames equal to MuJoCo's kinematics of the URDF itself at random joint
    values (to 1e-6: MuJoCo writes its MJCF with 6 digits), the fixed joint's child welded into its parent, and
    the mesh a collision geom of its link. Joint friction (MuJoCo's frictionloss) is refused by name, as in
    MJCF; a URDF MuJoCo cannot read is a ValueError saying so."""
    path = _urdf_file(tmp_path)
    model = load_mjcf(path)
    assert [link.name for link in model.links] == ["base", "upper", "ring"]
    assert [link.bodies for link in model.links][2] == ("ring", "tool")
    assert [(j.name, j.kind) for j in model.joints] == [("shoulder", "hinge"), ("elbow", "hinge")]
    assert model.joints[0].range == (-1.5, 1.5) and model.joints[1].range is None
    assert model.joints[1].damping == pytest.approx(0.1) and model.actuators == ()
    assert [link.mass for link in model.links] == [2.0, 1.25, 3.0]
    inertia = np.trace(model.links[1].second_moment) * np.eye(3) - model.links[1].second_moment
    np.testing.assert_allclose(np.diag(inertia), [0.011, 0.012, 0.002], rtol=1e-12)
    assert [g.kind for g in model.links[2].geoms] == ["mesh"] and len(model.links[2].mesh.faces) > 1000
    # unnamed collision elements are named after their link (MuJoCo printed a warning for each)
    assert [g.name for link in model.links for g in link.geoms] == [
        "base/collision0",
        "upper/collision0",
        "ring/collision0",
    ]
    assert "duplicate name" not in capfd.readouterr().out
    spec = mujoco.MjSpec.from_file(
        path
    )  # MuJoCo's own reading of the URDF, the root body not fused into the world
    spec.compiler.fusestatic = False
    m = spec.compile()
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for _ in range(4):
        q = rng.uniform(-1.4, 1.4, 2)
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        for link, T in zip(model.links, _reference_fk(model, q), strict=True):
            b = m.body(link.name).id
            np.testing.assert_allclose(T[:3, 3], d.xpos[b], rtol=0, atol=1e-6, err_msg=link.name)
            np.testing.assert_allclose(
                T[:3, :3], d.xmat[b].reshape(3, 3), rtol=0, atol=1e-6, err_msg=link.name
            )
    # and it simulates: hung from its fixed base, the arm held out sideways swings down under gravity
    from cfd_torch import Action, Scene, State, articulation, rollout

    arm = articulation(path)
    scene = Scene([], articulations=[arm], dt=0.01)
    q0 = torch.tensor([1.2, 0.0], dtype=torch.float64)
    rows = arm.poses(q0)
    traj = rollout(scene, State(rows, rows), [Action(ctrl=torch.zeros(0, dtype=torch.float64))] * 20)
    z = traj.q[:, 2, 2]  # the ring link's centre of mass falls
    assert float(z[-1]) < float(z[0]) - 0.01
    with pytest.raises(ValueError, match="frictionloss"):
        load_mjcf(_urdf_file(tmp_path / "rough", friction=0.3))
    # a <mimic> MuJoCo's importer drops is warned of; a mesh path MuJoCo does not follow gets the meshdir hint
    mimic = _URDF.format(friction=0).replace(
        '<dynamics damping="0.1"', '<mimic joint="shoulder"/><dynamics damping="0.1"'
    )
    (tmp_path / "mimic.urdf").write_text(mimic)
    with pytest.warns(
        UserWarning, match=r"URDF joints \['elbow'\] have a <mimic>, which MuJoCo's importer drops"
    ):
        load_mjcf(str(tmp_path / "mimic.urdf"))
    (tmp_path / "nodir.urdf").write_text(_URDF.format(friction=0).replace('<compiler meshdir="meshes"/>', ""))
    with pytest.raises(
        ValueError, match=r"Error opening file.*by their names alone, from its meshdir .*: pass meshdir="
    ):
        load_mjcf(str(tmp_path / "nodir.urdf"))
    # a ROS package's layout, robot/urdf/robot.urdf beside robot/meshes/: meshdir= finds them, the URDF untouched
    os.makedirs(tmp_path / "robot" / "urdf")
    os.rename(tmp_path / "nodir.urdf", tmp_path / "robot" / "urdf" / "robot.urdf")
    os.rename(tmp_path / "meshes", tmp_path / "robot" / "meshes")
    ros = load_mjcf(tmp_path / "robot" / "urdf" / "robot.urdf", meshdir="../meshes")
    assert ros.links[2].mesh.vertices.shape == model.links[2].mesh.vertices.shape
    with pytest.raises(TypeError, match="meshdir must be a folder path"):
        load_mjcf(path, meshdir=3)
    with pytest.raises(ValueError, match="the URDF could not be read by MuJoCo's importer"):
        load_mjcf(_URDF.format(friction=0).replace('<child link="ring"/>', '<child link="nowhere"/>'))


def test_mesh_mass_rules_read_the_mesh_as_mujoco_compiles_it(tmp_path) -> None:
    """Three ways the mass properties left MuJoCo's (a review of the mesh-geom change): an unnamed <mesh> (named
    after its file) lost its inertia rule (convex read as legacy: 37 % light, and warned of); inertia="convex"
    took the full hull where MuJoCo's honours maxhullvert (33.2 kg against 8.7); an OBJ, whose vertices MuJoCo
    keeps per face, was refused as not closed. Each against MuJoCo's compiled body, to 1e-7."""
    import trimesh

    torus = trimesh.creation.torus(0.3, 0.1)
    torus.export(tmp_path / "ring.stl")
    trimesh.creation.icosphere(subdivisions=3, radius=0.2).export(tmp_path / "ball.stl")
    soup = trimesh.Trimesh(torus.vertices[torus.faces].reshape(-1, 3), np.arange(3 * len(torus.faces)).reshape(-1, 3),
                           process=False)  # fmt: skip
    soup.export(tmp_path / "soup.obj")
    cases = {
        "unnamed": ('<mesh file="ring.stl" inertia="convex"/>', "ring"),
        "maxhullvert": ('<mesh name="b" file="ball.stl" inertia="convex" maxhullvert="8"/>', "b"),
        "obj": ('<mesh name="s" file="soup.obj" inertia="exact"/>', "s"),
    }
    for label, (asset, mesh) in cases.items():
        xml = (
            f'<mujoco><compiler meshdir="{tmp_path}"/><asset>{asset}</asset><worldbody><body name="root">'
            f'<joint name="j"/><geom type="mesh" mesh="{mesh}"/></body></worldbody></mujoco>'
        )
        path = tmp_path / f"{label}.xml"
        path.write_text(xml)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # (the unnamed convex mesh was warned of as legacy)
            model = load_mjcf(str(path))
        _against_mujoco(model, str(path), "root", 1e-7)
    assert len(trimesh.load(tmp_path / "soup.obj", process=False).vertices) == 3 * len(torus.faces)
    # meshdir= replaces an MJCF's own (a model whose meshdir is wrong loads with the right one)
    wrong = (tmp_path / "obj.xml").read_text().replace(f'meshdir="{tmp_path}"', 'meshdir="elsewhere"')
    (tmp_path / "wrong.xml").write_text(wrong)
    with pytest.raises(ValueError, match="elsewhere"):
        load_mjcf(str(tmp_path / "wrong.xml"))
    assert load_mjcf(str(tmp_path / "wrong.xml"), meshdir=str(tmp_path)).links[0].mass == pytest.approx(
        load_mjcf(str(tmp_path / "obj.xml")).links[0].mass, rel=1e-15
    )
