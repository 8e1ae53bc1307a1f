"""Articulated bodies in the step: a hinged physical pendulum built from link data (no MJCF), against implicit
Euler's closed form, with joint terms, a motor, limits and the rollout gradient."""

from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
import scipy.linalg
import torch
import trimesh

from cfd_torch import Action, Scene, State, rigid_body
from cfd_torch.sim.articulation import Articulation, articulation
from cfd_torch.sim.mjcf import load_mjcf
from cfd_torch.sim.stepper import rollout, step

F64 = torch.float64
L, W, RHO = 0.5, 0.05, 1000.0


def _pendulum(
    *, damping=0.0, armature=0.0, limits=None, gear=None, floating=False, actuator=None
) -> Articulation:
    """A 0.05 x 0.05 x 0.5 m bar hanging from a hinge about y at the root's origin."""
    bar = trimesh.creation.box((W, W, L))
    bar.apply_translation((0.0, 0.0, -L / 2))
    m = RHO * W * W * L
    Ic = m / 12.0 * np.diag([W * W + L * L, W * W + L * L, 2 * W * W])
    S = 0.5 * np.trace(Ic) * np.eye(3) - Ic
    root = trimesh.creation.box((0.04, 0.04, 0.04))
    root.apply_translation((0.0, 0.0, 0.1))
    joint = NS(
        name="hinge", kind="hinge", axis=np.array([0.0, 1.0, 0.0]), pos=np.zeros(3), range=limits,
        damping=damping, armature=armature, stiffness=0.0, springref=0.0,
    )  # fmt: skip
    m_root = RHO * 0.04**3
    links = (
        NS(name="root", parent=-1, pos=np.zeros(3), quat=np.array([1.0, 0, 0, 0]), joints=(), mesh=root,
           mass=m_root, com=np.array([0.0, 0.0, 0.1]), second_moment=m_root * 0.04**2 / 12 * np.eye(3)),
        NS(name="bar", parent=0, pos=np.zeros(3), quat=np.array([1.0, 0, 0, 0]), joints=(joint,), mesh=bar,
           mass=m, com=np.array([0.0, 0.0, -L / 2]), second_moment=S),
    )  # fmt: skip
    acts = (
        () if gear is None else (NS(name="motor", joint=0, kind="motor", gear=gear, ctrlrange=(-1.0, 1.0),
                                    kp=0.0, kv=0.0, forcerange=None),)
    )  # fmt: skip
    if actuator is not None:
        acts = (NS(**{"name": "act", "joint": 0, "gear": 1.0, "ctrlrange": None, "kp": 0.0, "kv": 0.0,
                      "forcerange": None} | actuator),)  # fmt: skip
    return Articulation(
        NS(name="pendulum", links=links, joints=(joint,), actuators=acts, floating=floating, friction=None)
    )


def _omega(art: Articulation) -> tuple[float, float]:
    b = art.bodies[1]
    m = b.mass
    I_c = float(b.inertia[1, 1])
    I_p = I_c + m * (L / 2) ** 2
    return math.sqrt(m * 9.81 * (L / 2) / I_p), I_p


def _lowest(bodies, rows: torch.Tensor) -> torch.Tensor:
    """(T,) the lowest vertex height of ``bodies`` at their state rows (T, L, 6)."""
    from cfd_torch.rotation import rotation_matrix

    rows = rows.detach()
    out = [
        (b.bsh.vertices.double() @ rotation_matrix(rows[:, k, 3:]).transpose(-1, -2) + rows[:, k, None, :3])[
            ..., 2
        ].amin(1)
        for k, b in enumerate(bodies)
    ]
    return torch.stack(out, 1).amin(1)


def _angles(scene: Scene, traj) -> np.ndarray:
    return scene.kinematics.coords(traj.q.reshape(-1, *traj.q.shape[-2:]))[:, 0].detach().numpy()


def test_pendulum_period_and_decay_match_implicit_euler():
    art = _pendulum()
    dt = 0.02
    scene = Scene([], articulations=[art], dt=dt)
    q0 = art.poses(torch.tensor([0.01], dtype=F64), torch.zeros(6, dtype=F64))
    th = _angles(scene, rollout(scene, State(q0, q0.clone()), 80))
    om, _ = _omega(art)
    z = [i + th[i] / (th[i] - th[i + 1]) for i in range(len(th) - 1) if th[i] > 0 >= th[i + 1]]
    assert len(z) == 2
    # implicit Euler on theta'' = -om^2 theta: roots (1 +- i om dt) / (1 + om^2 dt^2), argument atan(om dt),
    # modulus (1 + om^2 dt^2)^-1/2
    assert z[1] - z[0] == pytest.approx(2 * math.pi / math.atan(om * dt), rel=1e-4)
    env = lambda k: math.hypot(th[k], (th[k] - th[k - 1]) / math.tan(math.atan(om * dt)))  # noqa: E731
    n = int(z[1] - z[0])
    assert env(1 + n) / env(1) == pytest.approx((1.0 + (om * dt) ** 2) ** (-n / 2), rel=2e-2)


DOUBLE_PENDULUM = """<mujoco><worldbody><body name="base" pos="0 0 2"><geom type="sphere" size="0.05"/>
  <body name="upper"><joint name="j1" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/>
    <body name="lower" pos="0 0 -0.5"><joint name="j2" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03"/></body></body></body></worldbody></mujoco>"""


@pytest.mark.parametrize("mode", [0, 1])
def test_double_pendulum_normal_modes_and_energy_match_implicit_euler(mode):
    """A double pendulum (two capsules on hinges, MJCF) released from rest in one of its normal modes at 1e-3 rad:
    the joint angles follow the mode shape times implicit Euler's scalar recursion x_{n+1} = (2 x_n - x_{n-1}) /
    (1 + w^2 dt^2) for that mode's w (from M and K of the linearised chain, built from the links' own mass
    properties), and its energy 1/2 v^T M v + 1/2 x^T K x (finite-difference velocities) follows that of the
    recursion's trajectory: implicit Euler loses energy at (1 + w^2 dt^2)^-1 per step."""
    from cfd_torch.sim.articulation import articulation

    art = articulation(DOUBLE_PENDULUM)
    g, dt, steps = 9.81, 0.01, 120
    (m1, m2) = (art.bodies[k].mass for k in (1, 2))
    c1, c2 = -art.com[1, 2], -art.com[2, 2]  # centres of mass below each hinge
    I1, I2 = (float(art.bodies[k].inertia[1, 1]) for k in (1, 2))  # about y through the centre of mass
    l1 = 0.5
    M = np.array(
        [[I1 + m1 * c1**2 + I2 + m2 * (l1**2 + c2**2 + 2 * l1 * c2), I2 + m2 * (c2**2 + l1 * c2)],
         [I2 + m2 * (c2**2 + l1 * c2), I2 + m2 * c2**2]]
    )  # fmt: skip
    K = g * np.array([[m1 * c1 + m2 * (l1 + c2), m2 * c2], [m2 * c2, m2 * c2]])
    w2, V = scipy.linalg.eigh(K, M)
    v = V[:, mode] / np.abs(V[:, mode]).max()
    x = [1.0, 1.0]
    for _ in range(steps):
        x.append((2 * x[-1] - x[-2]) / (1 + w2[mode] * dt**2))
    x = np.array(x[1:])
    scene = Scene([], articulations=[art], dt=dt)
    q0 = art.poses(torch.as_tensor(1e-3 * v), torch.tensor([0.0, 0.0, 2.0, 0.0, 0.0, 0.0], dtype=F64))
    traj = rollout(scene, State(q0, q0.clone()), steps)
    th = scene.kinematics.coords(traj.q).detach().numpy()  # (steps + 1, 2)
    assert np.abs(th - 1e-3 * x[:, None] * v).max() < 1e-3 * 1e-3  # 0.1 % of the amplitude

    def energy(th: np.ndarray) -> np.ndarray:
        vel = np.diff(th, axis=0) / dt
        return 0.5 * np.einsum("ni,ij,nj->n", vel, M, vel) + 0.5 * np.einsum("ni,ij,nj->n", th[1:], K, th[1:])

    e_sim, e_ref = energy(th), energy(1e-3 * x[:, None] * v)
    assert np.abs(e_sim - e_ref).max() < 2e-3 * e_ref[0]
    assert (
        e_sim[-1] < (1 - 0.5 * steps * w2[mode] * dt**2) * e_sim[0]
    )  # implicit Euler's loss, to first order


def test_damping_and_armature_match_the_linear_recursion():
    """Small swings with joint damping d and armature a follow implicit Euler's scalar recursion
    (I_p + a)(th' - 2 th + th_) / dt^2 + d (th' - th) / dt + m g l_c th' = 0 (sin th ~ th)."""
    d, a, dt = 0.05, 0.01, 0.01
    art = _pendulum(damping=d, armature=a)
    scene = Scene([], articulations=[art], dt=dt)
    q0 = art.poses(torch.tensor([0.01], dtype=F64), torch.zeros(6, dtype=F64))
    th = _angles(scene, rollout(scene, State(q0, q0.clone()), 60))
    om, I_p = _omega(art)
    k = om * om * I_p
    ref = [0.01, 0.01]
    for _ in range(60):
        t, tp = ref[-1], ref[-2]
        ref.append(((I_p + a) / dt**2 * (2 * t - tp) + d / dt * t) / ((I_p + a) / dt**2 + d / dt + k))
    ref = np.array(ref[1:])
    assert np.abs(th - ref).max() < 1e-3 * 0.01
    assert np.abs(th[-20:]).max() < 0.9 * np.abs(ref[:20]).max()  # it did decay


SLIDE_MOTOR = """<mujoco><worldbody><body name="base"><geom type="sphere" size="0.05"/>
<body name="s"><joint name="s" type="slide" axis="1 0 0" range="-0.1 0.3"/>
<geom type="box" size="0.05 0.05 0.05" pos="0.2 0 0"/></body></body></worldbody>
<actuator><motor name="m" joint="s" gear="1000" ctrlrange="-10 10"/></actuator></mujoco>"""


@pytest.mark.parametrize("ctrl", [3.0, 3.0 * (1 - 1e-9), 1.5])
def test_a_step_whose_free_solution_lies_on_a_limit_stops_short_of_it(ctrl):
    """A 1 kg slide from rest under gear 1000: the free step moves it 0.1 ctrl, exactly onto its upper limit at
    ctrl 3 (and within 1e-9 of it just below; at 1.5 the start's constant-velocity prediction lands there). Newton's
    step next to the limit's barrier is a fixed fraction of the gap, within newton_tol: the solve used to stop
    there, 1e-16 from the limit, and the next step refused that state. Now it goes on to the balance, 8.6e-3 m
    inside at ctrl 3, and the next step runs."""
    art = articulation(SLIDE_MOTOR)
    scene = Scene([], articulations=[art], dt=0.01, gravity=(0, 0, 0))
    q = art.poses(torch.zeros(1, dtype=torch.float64), torch.zeros(6, dtype=torch.float64))
    s = State(q, q.clone())
    for _ in range(2):
        s = step(scene, s, Action(ctrl=torch.tensor([ctrl], dtype=torch.float64)))
        gap = 0.3 - scene.kinematics.coords(s.q[None]).item()
        assert gap > 1e-4


def test_limits_are_never_crossed_under_a_large_torque():
    art = _pendulum(limits=(-0.2, 0.2), gear=200.0)
    scene = Scene([], articulations=[art], dt=0.01)
    q0 = art.poses(torch.tensor([0.0], dtype=F64), torch.zeros(6, dtype=F64))
    traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=torch.tensor([1.0], dtype=F64))] * 25)
    th = _angles(scene, traj)
    assert th.max() > 0.19  # pushed against the limit
    assert th.max() < 0.2  # and never through it


def test_rollout_gradient_matches_finite_differences():
    art = _pendulum(damping=0.1, armature=0.01, gear=1.0)
    scene = Scene([], articulations=[art], dt=0.01)

    def final(th0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        q0 = art.poses(th0[None], torch.zeros(6, dtype=F64))
        traj = rollout(scene, State(q0, q0), [Action(ctrl=u[None])] * 8)
        return scene.kinematics.coords(traj.q[-1][None])[0, 0]

    th0 = torch.tensor(0.2, dtype=F64, requires_grad=True)
    u = torch.tensor(0.3, dtype=F64, requires_grad=True)
    g_th, g_u = torch.autograd.grad(final(th0, u), (th0, u))
    assert abs(float(g_th)) > 1e-3 and abs(float(g_u)) > 1e-4
    h = 1e-6
    with torch.no_grad():
        fd_th = (final(th0 + h, u) - final(th0 - h, u)) / (2 * h)
        fd_u = (final(th0, u + h) - final(th0, u - h)) / (2 * h)
    assert float(g_th) == pytest.approx(float(fd_th), rel=1e-5)
    assert float(g_u) == pytest.approx(float(fd_u), rel=1e-5)


def test_rollout_gradient_through_contact_of_a_planar_robot():
    """Gymnasium's hopper (a planar root of two slides and a hinge with nonzero ref, three motors) dropped 2 mm onto
    a floor: the gradient of its final coordinates through 10 steps of contact, in the initial joint velocities and
    the controls, against central differences."""
    import importlib.resources

    from cfd_torch import rigid_body
    from cfd_torch.sim.articulation import articulation

    hop = articulation(
        str(importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / "hopper.xml")
    )
    floor = trimesh.creation.box((3.0, 3.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    scene = Scene([rigid_body(floor, kind="static")], articulations=[hop], dt=0.01)
    th = torch.tensor(np.clip(hop.ref, hop.lower + 0.1, hop.upper - 0.1), dtype=F64)

    def lowest(rows: torch.Tensor) -> float:
        return float(_lowest(hop.bodies, rows[None])[0])

    th[hop.joint_names.index("rootz")] -= lowest(hop.poses(th)) - 0.002
    zero = torch.zeros(1, 6, dtype=F64)
    low = []

    def final(v0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        q0, qp = torch.cat([zero, hop.poses(th)]), torch.cat([zero, hop.poses(th - 0.01 * v0)])
        traj = rollout(scene, State(q0, qp), [Action(ctrl=u)] * 10)
        low.append(lowest(traj.q[-1, 1:]))
        return scene.kinematics.coords(traj.q[-1][None])[0]

    w = torch.tensor([1.0, 0.5, 0.3, 0.2, -0.2, 0.1], dtype=F64)
    v0 = torch.tensor([0.2, -0.1, 0.3, 0.5, -0.4, 0.2], dtype=F64, requires_grad=True)
    u = torch.tensor([0.3, -0.2, 0.4], dtype=F64, requires_grad=True)
    c = final(v0, u)
    assert (
        0.0 < low[0] < 2e-3
    )  # it landed (a free fall drops g dt^2 55 = 0.054 m in 10 steps), no penetration
    g_v, g_u = torch.autograd.grad(w @ c, (v0, u))
    assert g_v.norm() > 1e-2 and g_u.norm() > 1e-2
    rng = np.random.default_rng(0)
    h = 1e-6
    for g, x in ((g_v, "v0"), (g_u, "u")):
        d = torch.as_tensor(rng.normal(size=len(g)))
        with torch.no_grad():
            if x == "v0":
                fd = w @ (final(v0 + h * d, u) - final(v0 - h * d, u)) / (2 * h)
            else:
                fd = w @ (final(v0, u + h * d) - final(v0, u - h * d)) / (2 * h)
        assert abs(float(g @ d - fd)) < 1e-4 * float(g.norm() * d.norm()), (x, float(g @ d), float(fd))


@pytest.mark.parametrize("gains_from", ["mjcf", "params"])
def test_position_actuator_follows_the_implicit_pd_recursion(gains_from):
    """A position actuator (kp, kv, gear 2) pulls small swings toward its target ctrl / gear along implicit Euler's
    scalar recursion I_p (th' - 2 th + th_) / dt^2 + kv g^2 (th' - th) / dt + (m g l_c + kp g^2) th' = kp g ctrl,
    with its gains from the MJCF or overridden by Params.kp / kv (the MJCF's then 1 and 0)."""
    kp, kv, g, dt, ctrl = 3.0, 0.2, 2.0, 0.01, 0.04
    mjcf = (kp, kv) if gains_from == "mjcf" else (1.0, 0.0)
    art = _pendulum(actuator={"kind": "position", "kp": mjcf[0], "kv": mjcf[1], "gear": g})
    scene = Scene([], articulations=[art], dt=dt)
    params = scene.params()
    if gains_from == "params":
        params = params._replace(kp=torch.tensor([kp], dtype=F64), kv=torch.tensor([kv], dtype=F64))
    q0 = art.poses(torch.tensor([0.0], dtype=F64), torch.zeros(6, dtype=F64))
    action = Action(ctrl=torch.tensor([ctrl], dtype=F64))
    th = _angles(scene, rollout(scene, State(q0, q0.clone()), [action] * 150, params))
    om, I_p = _omega(art)
    k = om * om * I_p + kp * g * g
    ref = [0.0, 0.0]
    for _ in range(150):
        t, tp = ref[-1], ref[-2]
        ref.append(
            (I_p / dt**2 * (2 * t - tp) + kv * g * g / dt * t + kp * g * ctrl)
            / (I_p / dt**2 + kv * g * g / dt + k)
        )
    ref = np.array(ref[1:])
    assert np.abs(ref).max() > 0.01  # it moved
    assert np.abs(th - ref).max() < 2e-3 * np.abs(ref).max()  # sin th ~ th: 0.03 rad swings


def test_stiff_position_actuator_is_stable_and_differentiable():
    """kp = 1e4 N m/rad at dt = 0.01 (explicit PD would diverge: kp dt^2 / I_p ~ 10): the bar settles at the
    static balance of gravity and the PD spring, and the gradient of the final angle in the target matches finite
    differences."""
    kp, kv = 1e4, 10.0
    art = _pendulum(actuator={"kind": "position", "kp": kp, "kv": kv, "ctrlrange": (-1.0, 1.0)})
    scene = Scene([], articulations=[art], dt=0.01)
    q0 = art.poses(torch.tensor([0.0], dtype=F64), torch.zeros(6, dtype=F64))
    b = art.bodies[1]

    def final(u: torch.Tensor, n: int) -> torch.Tensor:
        traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=u[None])] * n)
        return scene.kinematics.coords(traj.q[-1][None])[0, 0]

    # static balance: kp (u - th) = m g l_c sin th
    th = float(final(torch.tensor(0.5, dtype=F64), 100))
    assert kp * (0.5 - th) == pytest.approx(b.mass * 9.81 * (L / 2) * math.sin(th), rel=1e-3)
    u = torch.tensor(0.3, dtype=F64, requires_grad=True)
    (g_u,) = torch.autograd.grad(final(u, 5), u)
    assert abs(float(g_u)) > 1e-2
    h = 1e-6
    with torch.no_grad():
        fd = (final(u + h, 5) - final(u - h, 5)) / (2 * h)
    assert float(g_u) == pytest.approx(float(fd), rel=1e-5)


def test_servo_gain_and_target_gradients_match_finite_differences():
    """The final angle of a servo-driven bar after 20 steps (it swings, not settled) is differentiable in the servo
    gains Params.kp and kv and the target ctrl: each gradient non-zero and equal to central differences."""
    art = _pendulum(
        actuator={"kind": "position", "kp": 5.0, "kv": 0.3, "gear": 1.5, "ctrlrange": (-1.0, 1.0)}
    )
    scene = Scene([], articulations=[art], dt=0.01)
    base = scene.params()
    q0 = art.poses(torch.tensor([0.1], dtype=F64), torch.zeros(6, dtype=F64))

    def final(kp: torch.Tensor, kv: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        params = base._replace(kp=kp, kv=kv)
        traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=u)] * 20, params)
        return scene.kinematics.coords(traj.q[-1][None])[0, 0]

    x = [torch.tensor([v], dtype=F64, requires_grad=True) for v in (5.0, 0.3, 0.4)]
    grads = torch.autograd.grad(final(*x), x)
    h = 1e-6
    for k, g in enumerate(grads):
        assert abs(float(g)) > 1e-3, k
        with torch.no_grad():
            up = [v + (h if i == k else 0.0) for i, v in enumerate(x)]
            dn = [v - (h if i == k else 0.0) for i, v in enumerate(x)]
            fd = (final(*up) - final(*dn)) / (2 * h)
        assert float(g) == pytest.approx(float(fd), rel=1e-5, abs=1e-9), k
    with pytest.raises(ValueError, match="params.kp must be >= 0"):
        step(scene, State(q0, q0.clone()), None, base._replace(kp=torch.tensor([-1.0], dtype=F64)))
    with pytest.raises(ValueError, match=r"params.kv must have shape \(1,\)"):
        step(scene, State(q0, q0.clone()), None, base._replace(kv=torch.zeros(2, dtype=F64)))


_SWEEPER = """
<mujoco model="sweeper">
  <worldbody>
    <body name="base">
      <geom type="sphere" size="0.02"/>
      <body name="arm">
        <joint name="yaw" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03"/>
        <body name="tip" pos="0.5 0 0">
          <joint name="bend" type="hinge" axis="0 0 1"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="yaw" gear="1"/></actuator>
</mujoco>"""


def test_kinematic_robot_follows_its_joints_exactly_and_pushes():
    """A kinematic two-link arm (articulation(..., kinematic=True)) sweeping through a free ball (no gravity): its
    links stand exactly where forward kinematics of Action.joints puts them, they push the ball, and the ball's
    final position is differentiable in the joint trajectory (non-zero, equal to central differences)."""
    from cfd_torch import rigid_body
    from cfd_torch.sim.articulation import articulation

    art = articulation(_SWEEPER, kinematic=True)
    ball = rigid_body(trimesh.creation.icosphere(2, 0.05), density=500.0)
    scene = Scene([ball], articulations=[art], dt=0.01, gravity=(0.0, 0.0, 0.0))
    assert (scene.num_actuators, scene.num_kinematic_coords) == (
        0,
        2,
    )  # a kinematic robot's motor plays no part
    assert scene.kinematic.tolist() == [2, 3] and len(scene.kinematics.bodies) == 1
    zero = torch.zeros(2, dtype=F64)
    q0 = torch.cat([torch.tensor([[0.4, 0.12, 0.0, 0.0, 0.0, 0.0]], dtype=F64), art.poses(zero)])
    state = State(q0, q0.clone())
    assert torch.equal(step(scene, state).q[1:], q0[1:])  # no joints: the robot stays put
    plan = torch.stack([torch.linspace(0.02, 0.3, 15), torch.linspace(0.0, -0.2, 15)], 1).to(F64)

    def run(plan: torch.Tensor):
        return rollout(scene, state, [Action(joints=j) for j in plan])

    traj = run(plan)
    for t in range(1, 16):
        assert torch.allclose(traj.q[t, 1:], art.poses(plan[t - 1]), rtol=0, atol=1e-12)
    assert float(traj.q[-1, 0, 1] - 0.12) > 0.01  # the ball was swept along +y
    assert torch.allclose(scene.kinematic_coords(traj.q[-1][None])[0], plan[-1], atol=1e-12)

    w = torch.tensor([0.3, 1.0, 0.0], dtype=F64)
    p = plan.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(run(p).q[-1, 0, :3] @ w, p)
    assert float(g.abs().max()) > 1e-2
    d = torch.randn(plan.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    h = 1e-6
    with torch.no_grad():
        fd = (run(plan + h * d).q[-1, 0, :3] @ w - run(plan - h * d).q[-1, 0, :3] @ w) / (2 * h)
    assert float((g * d).sum()) == pytest.approx(float(fd), rel=1e-5)
    with pytest.raises(ValueError, match=r"action.joints must have shape \(2,\)"):
        step(scene, state, Action(joints=torch.zeros(3, dtype=F64)))
    with pytest.raises(ValueError, match=r"action.ctrl must have shape \(0,\)"):
        step(scene, state, Action(ctrl=torch.zeros(1, dtype=F64)))
    with pytest.raises(
        ValueError, match=r"action.joints has a coordinate beyond 1e\+06 \(rad or m; first at coordinate 1\)"
    ):
        step(
            scene, state, Action(joints=torch.tensor([0.0, 1e20], dtype=F64))
        )  # (it turned the link arbitrarily)
    # a static block beside the arm: joints that put a link into it are refused, naming action.joints (the arm
    # overlapping its own static base is not contact)
    block = trimesh.creation.box((0.1, 0.1, 0.1))
    block.apply_translation((0.35, -0.3, 0.0))
    walled = Scene([ball, rigid_body(block, kind="static")], articulations=[art], gravity=(0.0, 0.0, 0.0))
    q1 = torch.cat([q0[:1], torch.zeros(1, 6, dtype=F64), q0[1:]])
    step(walled, State(q1, q1.clone()), Action(joints=torch.tensor([-0.3, 0.0], dtype=F64)))
    with pytest.raises(
        ValueError, match="action.joints: kinematic robot link 3 at its target penetrates static body 1"
    ):
        step(walled, State(q1, q1.clone()), Action(joints=torch.tensor([-0.9, 0.0], dtype=F64)))


def test_actuator_force_ranges():
    """A motor's forcerange narrows its control's clip; a position actuator's is refused (its force is implicit)."""
    art = _pendulum(actuator={"kind": "motor", "ctrlrange": (-1.0, 1.0), "forcerange": (-0.5, 2.0)})
    assert (art.ctrl_lower[0], art.ctrl_upper[0]) == (-0.5, 1.0)
    with pytest.raises(ValueError, match="position actuator 'act' has a forcerange"):
        _pendulum(actuator={"kind": "position", "kp": 1.0, "forcerange": (-1.0, 1.0)})
    with pytest.raises(ValueError, match="'velocity' actuator; motor and position actuators are supported"):
        _pendulum(actuator={"kind": "velocity", "kv": 1.0})


def test_mjcf_position_actuator_settles_at_its_target():
    """An MJCF hinge with a <position> actuator (gear 2) and no gravity settles where MuJoCo's law puts it,
    th = ctrl / gear, and its data are kp gear^2 and kv gear^2 on the joint."""
    from cfd_torch.sim.articulation import articulation

    xml = """
    <mujoco model="servo">
      <worldbody>
        <body name="base">
          <geom type="box" size="0.05 0.05 0.05"/>
          <body name="arm" pos="0 0 0.2">
            <joint name="hinge" axis="0 1 0"/>
            <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
          </body>
        </body>
      </worldbody>
      <actuator><position name="servo" joint="hinge" kp="20" kv="1" gear="2" ctrlrange="-1 1"/></actuator>
    </mujoco>"""
    art = articulation(xml)
    assert (float(art.pd_stiffness[0]), float(art.pd_damping[0]), float(art.ctrl_gain[0])) == (
        80.0,
        4.0,
        20.0,
    )
    scene = Scene([], articulations=[art], dt=0.01, gravity=(0.0, 0.0, 0.0))
    q0 = art.poses(torch.tensor([0.0], dtype=F64))
    traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=torch.tensor([0.6], dtype=F64))] * 300)
    th = _angles(scene, traj)
    assert abs(th[10]) > 0.05  # it moved toward the target
    assert th[-1] == pytest.approx(0.3, abs=1e-6)


def test_bad_ctrl_is_refused():
    art = _pendulum(gear=1.0)
    scene = Scene([], articulations=[art], dt=0.01)
    q0 = art.poses(torch.tensor([0.0], dtype=F64), torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match="action.ctrl must have shape"):
        step(scene, State(q0, q0), Action(ctrl=torch.zeros(2, dtype=F64)))
    # a batch dimension of one on an unbatched state, refused as for action.force (it was accepted)
    with pytest.raises(
        ValueError, match=r"action.ctrl must have shape \(1,\) .*state.q has no batch dimension"
    ):
        step(scene, State(q0, q0), Action(ctrl=torch.zeros(1, 1, dtype=F64)))
    with pytest.raises(ValueError, match="action.ctrl must be a float tensor"):
        step(scene, State(q0, q0), Action(ctrl=torch.zeros(1, dtype=torch.long)))
    batch = State(q0.expand(3, -1, -1), q0.expand(3, -1, -1))
    ctrl = torch.zeros(3, 1, dtype=F64)
    ctrl[2, 0] = float("nan")
    with pytest.raises(
        ValueError, match=r"action\.ctrl contains NaN or inf \(first at scene 2, actuator 0\)"
    ):
        step(scene, batch, Action(ctrl=ctrl))  # (it named neither)


def _xml(joints: str, root_joints: str = "") -> str:
    return f"""<mujoco><worldbody><body name="root" pos="0 0 1">{root_joints}<geom type="sphere" size="0.1"/>
        <body name="arm" pos="0 0 -0.3">{joints}<geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.05"/>
        </body></body></worldbody></mujoco>"""


def test_joint_layouts_that_cannot_be_recovered_are_refused():
    import dataclasses

    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import load_mjcf

    hinge = '<joint name="h{}" type="hinge" axis="{}"/>'
    with pytest.raises(ValueError, match="consecutive parallel hinges"):
        articulation(
            _xml(hinge.format(1, "0 1 0") + '<joint name="h2" type="hinge" axis="0 2 0" pos="0 0 -0.1"/>')
        )
    with pytest.raises(ValueError, match="at most three of each"):
        four = "".join(hinge.format(k, a) for k, a in enumerate(["1 0 0", "0 1 0", "0 0 1"]))
        articulation(_xml(four + '<joint name="h4" type="hinge" axis="1 0 0" pos="0 0 -0.1"/>'))
    slide = '<joint name="s{}" type="slide" axis="{}"/>'
    two = load_mjcf(_xml(slide.format(1, "1 0 0") + slide.format(2, "0 1 0")))  # MuJoCo refuses a third
    third = dataclasses.replace(two.links[1].joints[0], name="s3", axis=np.array([1.0, 1.0, 0.0]))
    arm = dataclasses.replace(two.links[1], joints=two.links[1].joints + (third,))
    with pytest.raises(ValueError, match="dependent axes"):
        Articulation(dataclasses.replace(two, links=(two.links[0], arm), joints=two.joints + (third,)))
    fixed_root = _xml(hinge.format(1, "0 1 0"))
    with pytest.raises(ValueError, match="mount places a fixed base"):
        articulation(fixed_root, mount=[0, 0, 1, 0, 0, 0])
    hung = articulation(
        _xml(hinge.format(1, "0 1 0"), root_joints=slide.format(0, "1 0 0")), mount=[0, 0, 1, 0, 0, 0]
    )
    with pytest.raises(ValueError, match="base"):
        hung.poses(torch.zeros(2, dtype=F64), torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match="mount must be"):
        articulation(_xml(hinge.format(1, "0 1 0"), root_joints=slide.format(0, "1 0 0")), mount=[0, 0, 1])
    for bad in ("abcdef", {}):  # (numpy's "could not convert string to float", float()'s TypeError)
        with pytest.raises(ValueError, match="mount must be a finite pose"):
            articulation(_xml(hinge.format(1, "0 1 0"), root_joints=slide.format(0, "1 0 0")), mount=bad)
    # the mount moves the whole robot: the root's frame is the mount's pose composed with the MJCF's pos="0 0 1"
    rows = hung.poses(torch.zeros(2, dtype=F64))
    assert float(rows[0, 2]) == pytest.approx(2.0, abs=1e-12)


def test_ant_forward_kinematics_matches_mujoco():
    import mujoco

    from cfd_torch.sim.articulation import _fk_frames
    from cfd_torch.sim.mjcf import gymnasium_ant_xml, load_mjcf

    model = load_mjcf(gymnasium_ant_xml())
    art = Articulation(model)
    mj = mujoco.MjModel.from_xml_string(model.xml)
    data = mujoco.MjData(mj)
    rng = np.random.default_rng(0)
    for _ in range(5):
        th = rng.uniform(-1.0, 1.0, art.num_joints)
        w = rng.normal(size=3)
        base = np.concatenate([rng.normal(size=3), w])
        quat = np.zeros(4)
        mujoco.mju_axisAngle2Quat(quat, w / np.linalg.norm(w), np.linalg.norm(w))
        data.qpos[:] = np.concatenate([base[:3], quat, th])  # joints in MJCF order = link order for the Ant
        mujoco.mj_kinematics(mj, data)
        R, p = _fk_frames(art, torch.tensor(np.concatenate([base, th]))[None], None)
        for k, link in enumerate(model.links):
            b = mj.body(link.bodies[0]).id
            assert np.abs(p[0, k].numpy() - data.xpos[b]).max() < 1e-10
            assert np.abs(R[0, k].numpy() - data.xmat[b].reshape(3, 3)).max() < 1e-10


GYM_ASSETS = (
    ("humanoid.xml", None), ("hopper.xml", None), ("walker2d.xml", None), ("swimmer.xml", None),
    ("inverted_double_pendulum.xml", None), ("point.xml", None), ("reacher.xml", "body0"),
    ("pusher.xml", "r_shoulder_pan_link"), ("half_cheetah.xml", None), ("ant.xml", None),
)  # fmt: skip


@pytest.mark.parametrize("asset,root", GYM_ASSETS, ids=[a for a, _ in GYM_ASSETS])
def test_gymnasium_assets_forward_kinematics_match_mujoco(asset, root):
    """Gymnasium's bundled robots (several joints per body, planar roots with nonzero ref, carts, fixed arms): link
    frames against mj_kinematics at random joint values within the joints' ranges (1e-10), and the joint values
    recovered from the link rows (1e-9)."""
    import importlib.resources

    import mujoco

    from cfd_torch.rotation import rotation_vector
    from cfd_torch.sim.articulation import _fk_frames, _fk_rows, _joint_values
    from cfd_torch.sim.mjcf import load_mjcf

    path = importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / asset
    model = load_mjcf(str(path), root=root)
    art = Articulation(model)
    mj = mujoco.MjModel.from_xml_string(model.xml)
    data = mujoco.MjData(mj)
    rng = np.random.default_rng(1)
    lo = np.where(
        np.isfinite(art.lower), art.lower, art.ref - np.where(np.array(art.joint_kind) == "hinge", 3.0, 1.0)
    )
    hi = np.where(
        np.isfinite(art.upper), art.upper, art.ref + np.where(np.array(art.joint_kind) == "hinge", 3.0, 1.0)
    )
    for _ in range(4):
        th = rng.uniform(lo, hi)
        data.qpos[:] = mj.qpos0
        for name, v in zip(art.joint_names, th, strict=True):
            data.qpos[mj.joint(name).qposadr[0]] = v
        q = torch.tensor(th)
        base = None
        if art.floating:
            w = rng.normal(size=3)
            w *= rng.uniform(0.0, 3.0) / np.linalg.norm(
                w
            )  # a rotation vector as the rows give it back (< pi)
            quat = np.zeros(4)
            mujoco.mju_axisAngle2Quat(quat, w / np.linalg.norm(w), np.linalg.norm(w))
            t = rng.normal(size=3)
            free = mj.body(art.names[0]).jntadr[0]
            data.qpos[mj.jnt_qposadr[free] : mj.jnt_qposadr[free] + 7] = np.concatenate([t, quat])
            q = torch.cat([torch.tensor(np.concatenate([t, w])), q])
        elif not art.root_moves:  # a joint-less fixed root stands where the MJCF puts it
            link0 = model.links[0]
            base = torch.cat([torch.tensor(link0.pos), rotation_vector(torch.tensor(link0.quat)[None])[0]])[
                None
            ]
        mujoco.mj_kinematics(mj, data)
        R, p = _fk_frames(art, q[None], base)
        for k, link in enumerate(model.links):
            b = mj.body(link.bodies[0]).id
            assert np.abs(p[0, k].numpy() - data.xpos[b]).max() < 1e-10, link.name
            assert np.abs(R[0, k].numpy() - data.xmat[b].reshape(3, 3)).max() < 1e-10, link.name
        rows = _fk_rows(art, q[None], base)
        assert torch.allclose(_joint_values(art, rows)[0], q, rtol=0.0, atol=1e-9)


def test_ant_falls_freely_with_its_joints_still():
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml())
    scene = Scene([], articulations=[ant], dt=0.01)
    th = torch.tensor([0.0, 0.7, 0.0, -0.7, 0.0, -0.7, 0.0, 0.7], dtype=F64)
    q0 = ant.poses(th, torch.tensor([0.0, 0.0, 0.75, 0.0, 0.0, 0.3], dtype=F64))
    traj = rollout(scene, State(q0, q0.clone()), 3)
    c = scene.kinematics.coords(traj.q)
    # implicit Euler from rest: z_k = z_0 - g dt^2 k (k + 1) / 2
    assert float(c[-1, 2]) == pytest.approx(0.75 - 9.81 * 0.01**2 * 6, abs=1e-9)
    assert torch.allclose(c[:, 6:], th.expand(4, -1), atol=1e-9)
    assert torch.allclose(c[:, 3:6], c[0, 3:6].expand(4, -1), atol=1e-9)


@pytest.mark.slow
def test_ant_dropped_on_a_floor_settles_standing():
    """Gymnasium's Ant (motors at zero control) dropped from 5 cm onto a floor (friction 1): 300 steps (3 s) with every
    vertex above the floor, the torso held up by its legs, and at rest at the end (about 2 minutes)."""
    from cfd_torch import rigid_body
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml())
    floor = trimesh.creation.box((3.0, 3.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    scene = Scene([rigid_body(floor, kind="static")], articulations=[ant], dt=0.01, friction=1.0)
    lo, hi = torch.as_tensor(ant.lower), torch.as_tensor(ant.upper)
    stance = torch.where((lo < 0) & (hi > 0), torch.zeros_like(lo), 0.5 * (lo + hi))

    def lowest(rows: torch.Tensor) -> torch.Tensor:  # (T, L, 6) -> (T,) the lowest vertex of the Ant
        return _lowest(ant.bodies, rows)

    rows = ant.poses(stance)
    base = torch.tensor([0.0, 0.0, 0.05 - float(lowest(rows[None])[0]), 0.0, 0.0, 0.0], dtype=F64)
    q0 = torch.cat([torch.zeros(1, 6, dtype=F64), ant.poses(stance, base)])
    traj = rollout(scene, State(q0, q0.clone()), 300)
    q = traj.q.detach()
    assert torch.isfinite(q).all()
    low = lowest(q[:, 1:])
    assert float(low.min()) > 0.0  # never through the floor
    assert float(low[-50:].max()) < 2e-3  # standing on it
    torso = q[:, 1, 2]
    assert (
        float(torso[-1]) > 0.2
    )  # held up by the legs (the torso sphere's radius is 0.25 m: not lying on it)
    c = scene.kinematics.coords(q[-2:])
    assert float((c[1] - c[0]).abs().max()) < 1e-4  # at rest


# --------------------------------------------------------------------- closed-form derivatives against torch.func
def _random_chain(name: str, seed: int, parents, patterns, refs: bool, mount=None) -> Articulation:
    """A tree of links with random offsets, COMs, joint axes and anchors (and refs), joints per link as patterns."""
    rng = np.random.default_rng(seed)
    links, joints = [], []
    for k, (par, kinds) in enumerate(zip(parents, patterns, strict=True)):
        js = tuple(
            NS(name=f"j{k}{i}" if refs else f"j{k}", kind=kind, axis=rng.normal(size=3), pos=rng.normal(size=3),
               range=None, damping=0.0, armature=0.0, stiffness=0.0, springref=0.0,
               **({"ref": float(rng.uniform(-1, 1))} if refs else {}))
            for i, kind in enumerate(kinds)
        )  # fmt: skip
        joints += list(js)
        quat = rng.normal(size=4)
        links.append(
            NS(name=f"l{k}", parent=par, pos=rng.normal(size=3), quat=quat / np.linalg.norm(quat), joints=js,
               mesh=trimesh.creation.box((0.1, 0.2, 0.3)), mass=1.0, com=rng.normal(size=3),
               second_moment=np.diag([0.1, 0.2, 0.3]))
        )  # fmt: skip
    model = NS(
        name=name, links=tuple(links), joints=tuple(joints), actuators=(), floating=False, friction=None
    )
    return Articulation(model, mount=None if mount is None else mount(rng))


def _multi_chain() -> Articulation:
    """A fixed base whose root has joints (slide, slide, hinge: a planar root), hung from a tilted mount, and links
    with several joints each (three hinges; hinge + slide; two hinges; slide, hinge, slide), tilted axes, anchors
    and nonzero refs."""
    patterns = (("slide", "slide", "hinge"), ("hinge",) * 3, ("hinge", "slide"), ("hinge", "hinge"),
                ("slide", "hinge", "slide"))  # fmt: skip
    return _random_chain("multi", 5, (-1, 0, 1, 1, 3), patterns, True, mount=lambda rng: rng.normal(size=6))


def _branchy_chain() -> Articulation:
    """A fixed-base tree of hinges and slides with tilted axes, offsets and anchors: root - hinge - slide - hinge,
    root - slide - hinge, and a second hinge on the first slide."""
    kinds = ((), ("hinge",), ("slide",), ("hinge",), ("slide",), ("hinge",), ("hinge",))
    return _random_chain("branchy", 3, (-1, 0, 1, 2, 0, 4, 2), kinds, False)


def _reference_rows(art: Articulation, q: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
    """(6 La,) the moving links' rows for one configuration q (Qa,), link by link, in ops whose forward-mode
    derivatives stay accurate at small angles (a series exp; log R = 2 atan(s / w) v / s of the quaternion
    [w, v], s = |v|, with atan's series where s << w). The library's value path (a two-term exp series below
    1e-4 rad, sin t / t above it, and atan2(s, w) / s) is exact in value but not under forward mode: its second
    derivatives lose about eps / theta^2 near theta = 0 (2e-10 at 1e-9 rad), where the closed form does not."""
    from cfd_torch.rotation import _rotation_derivatives_torch
    from cfd_torch.sim.articulation import _quat_from_matrix

    if art.floating:
        base = q[:6]
    else:
        base = torch.as_tensor(art.mount) if art.root_moves else root
    th = q[6:] if art.floating else q
    R0, p0 = _rotation_derivatives_torch(base[None, 3:], 0)[0][0], base[:3]
    Rs, ps = [], []
    for i in range(art.num_links):
        if i == 0 and not art.root_moves:
            Rs.append(R0)
            ps.append(p0)
            continue
        Rp, pp = (R0, p0) if i == 0 else (Rs[int(art.parent[i])], ps[int(art.parent[i])])
        R, p = Rp @ torch.as_tensor(art.offset_R[i]), pp + Rp @ torch.as_tensor(art.offset_p[i])
        for j in art.link_joints[i]:
            a, c, t = torch.as_tensor(art.axis[j]), torch.as_tensor(art.anchor[j]), th[j] - float(art.ref[j])
            if art.joint_kind[j] == "hinge":
                K = torch.linalg.cross(a.expand(3, 3), torch.eye(3, dtype=F64)).T  # [a]_x
                Rj = torch.eye(3, dtype=F64) + torch.sin(t) * K + (1.0 - torch.cos(t)) * (K @ K)
                R, p = R @ Rj, p + R @ (c - Rj @ c)
            else:
                p = p + R @ (a * t)
        Rs.append(R)
        ps.append(p)
    R = torch.stack(Rs)
    quat = _quat_from_matrix(R)
    w, v = quat[:, :1], quat[:, 1:]
    s2 = (v * v).sum(-1, keepdim=True)
    x2 = s2 / (w * w)
    small = x2 < 1e-2
    s = torch.sqrt(torch.where(small, torch.ones_like(s2), s2))
    series = sum((-x2) ** k / (2 * k + 1) for k in range(12)) / w  # atan(s / w) / s
    log = 2.0 * torch.where(small, series, torch.atan2(s, w) / s) * v
    rows = torch.cat([torch.stack(ps) + (R @ torch.as_tensor(art.com)[..., None])[..., 0], log], 1)
    return rows[art.first_moving :].reshape(-1)


def _reference_derivatives(art: Articulation, q: torch.Tensor, root: torch.Tensor, g: torch.Tensor):
    """J (A, 6 La, Qa) and sum_k g_k d2 row_k / dq dq (A, Qa, Qa) by nested forward mode (torch.func)."""

    def jac(qa, rt):
        J = torch.func.jacfwd(_reference_rows, argnums=1)(art, qa, rt)
        return J, J

    D2, J = torch.func.vmap(torch.func.jacfwd(jac, has_aux=True))(q, root)
    return J, torch.einsum("ak,akij->aij", g.reshape(g.shape[0], -1), D2)


@pytest.mark.parametrize("which", ["ant", "branchy", "multi"])
def test_closed_form_derivatives_match_torch_func(which):
    """The Jacobian of the link rows and their second derivatives contracted with a row gradient, against nested
    forward mode, with rotation vectors (the Ant's base; the branchy chain's first link) of norm 0 to near pi; and
    the joint values recovered from the rows (several joints per link, refs and a mounted root in "multi")."""
    from cfd_torch.rotation import rotation_matrix, rotation_vector
    from cfd_torch.sim.articulation import (
        _fk_derivatives,
        _fk_rows,
        _joint_values,
        _quat_from_matrix,
        articulation,
    )
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    rng = np.random.default_rng(7)
    norms = torch.tensor([0.0, 1e-9, 1e-5, 0.3, 2.0, math.pi - 1e-4, math.pi - 1e-8], dtype=F64)
    A = len(norms)
    u = torch.as_tensor(rng.normal(size=(A, 3)))
    rot = u / u.norm(dim=1, keepdim=True) * norms[:, None]  # (A, 3)
    if which == "ant":
        art = articulation(gymnasium_ant_xml())
        q = torch.cat(
            [torch.as_tensor(rng.normal(size=(A, 3))), rot, torch.as_tensor(rng.uniform(-3, 3, (A, 8)))], 1
        )
        root, fixed, lo = torch.zeros(A, 6, dtype=F64), None, 0
    elif which == "multi":  # angles within pi / 2 of ref: three hinges' middle angle has one such solution
        art = _multi_chain()
        q = torch.as_tensor(art.ref + rng.uniform(-1.5, 1.5, (A, art.num_coords)))
        root = torch.zeros(A, 6, dtype=F64)
        fixed, lo = root, 0
    else:  # the root turned so that link 1 has the rotation vector rot
        art = _branchy_chain()
        q = torch.as_tensor(rng.uniform(-1.5, 1.5, (A, art.num_coords)))
        R1 = rotation_matrix(rot) @ (
            torch.as_tensor(art.offset_R[1]) @ rotation_matrix(torch.as_tensor(art.axis[0]) * q[:, :1])
        ).transpose(-1, -2)
        root = torch.cat(
            [torch.as_tensor(rng.normal(size=(A, 3))), rotation_vector(_quat_from_matrix(R1))], 1
        )
        fixed, lo = root, 1
    rows = _fk_rows(art, q, fixed)[:, lo:]
    if which != "multi":
        assert torch.allclose(rows[:, 0, 3:].norm(dim=-1), norms, rtol=1e-9, atol=1e-14)
    g = torch.as_tensor(rng.normal(size=rows.shape))
    J, second = _fk_derivatives(art, q, fixed, lo, g)
    J_ref, second_ref = _reference_derivatives(art, q, root, g)
    assert torch.allclose(
        rows.reshape(A, -1), torch.vmap(lambda x, r: _reference_rows(art, x, r))(q, root), atol=1e-12
    )
    assert J_ref.abs().amax((1, 2)).min() > 0.5 and second_ref.abs().amax((1, 2)).min() > 0.5
    assert (J - J_ref).abs().max() < 1e-10
    assert (second - second_ref).abs().max() < 1e-10
    assert torch.equal(_fk_derivatives(art, q, fixed, lo, None)[0], J)
    # the inverse: the same coordinates, a hinge's up to whole turns (its value comes back in the turn centred on
    # its range, or its ref), the Ant's drawn beyond their ranges too
    back = _joint_values(art, _fk_rows(art, q, fixed))
    diff = back - q
    nj, hinge = art.num_joints, torch.tensor([k == "hinge" for k in art.joint_kind])
    turns = diff[:, -nj:][:, hinge] / (2 * math.pi)
    diff[:, -nj:][:, hinge] = 0.0 if turns.numel() == 0 else (turns - turns.round()) * 2 * math.pi
    assert diff.abs().max() < 1e-12
    centre = torch.as_tensor(art.centre)[hinge]
    assert ((back[:, -nj:][:, hinge] - centre).abs() <= math.pi + 1e-12).all()


@pytest.mark.slow
def test_ant_pushing_a_box_rollout_gradient_matches_finite_differences():
    """Gymnasium's Ant on position servos, dropped 2 mm onto a floor (friction 1) with a 0.3 m box 0.55 m ahead,
    walks a sinusoidal gait for 30 steps: the gradient of its torso's and the box's final poses in the 240 servo
    targets and the eight kp gains matches central differences (non-zero first), with the feet on the floor
    throughout (about a minute)."""
    from cfd_torch import rigid_body
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml(servos=(100.0, 5.0)))
    floor = trimesh.creation.box((3.0, 3.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    box = rigid_body(trimesh.creation.box((0.3, 0.3, 0.3)), density=50.0)
    scene = Scene([box, rigid_body(floor, kind="static")], articulations=[ant], dt=0.01, friction=1.0)
    lo, hi = torch.as_tensor(ant.lower), torch.as_tensor(ant.upper)
    stance = torch.where((lo < 0) & (hi > 0), torch.zeros_like(lo), 0.5 * (lo + hi)).to(F64)
    base = torch.tensor(
        [0.0, 0.0, 2e-3 - float(_lowest(ant.bodies, ant.poses(stance)[None])[0]), 0, 0, 0], dtype=F64
    )
    box_pose = torch.tensor([[0.55, 0.0, 0.152, 0.0, 0.0, 0.0]], dtype=F64)
    q0 = torch.cat([box_pose, torch.zeros(1, 6, dtype=F64), ant.poses(stance, base)])
    order = torch.as_tensor(ant.actuator_joint)
    t = torch.arange(30, dtype=F64)[:, None]
    phase = torch.tensor([0.0, math.pi / 2] * 2 + [math.pi, 3 * math.pi / 2] * 2, dtype=F64)
    plan = (stance + 0.25 * torch.sin(2 * math.pi * 1.5 * 0.01 * t + phase))[
        :, order
    ]  # (30, 8) servo targets
    kp0 = scene.params().kp
    w = torch.tensor([0.7, -0.4, 1.0, 0.2, 0.3, -0.5], dtype=F64)
    low = []

    def final(plan: torch.Tensor, kp: torch.Tensor) -> torch.Tensor:
        traj = rollout(
            scene, State(q0, q0.clone()), [Action(ctrl=u) for u in plan], scene.params()._replace(kp=kp)
        )
        low.append(float(_lowest(ant.bodies, traj.q[:, 2:]).min()))
        return traj.q[-1, 2] @ w + traj.q[-1, 0] @ w.flip(0)

    x = [plan.clone().requires_grad_(True), kp0.clone().requires_grad_(True)]
    grads = torch.autograd.grad(final(*x), x)
    assert 0.0 < low[0] < 2e-3  # on the floor, never through it
    gen = torch.Generator().manual_seed(0)
    h = 1e-6
    for k, (g, least) in enumerate(
        zip(grads, (1e-2, 1e-4), strict=True)
    ):  # per rad of target, per N m/rad of kp
        assert float(g.abs().max()) > least, k
        d = torch.randn(g.shape, dtype=F64, generator=gen)
        with torch.no_grad():
            up = [v + h * d if i == k else v for i, v in enumerate(x)]
            dn = [v - h * d if i == k else v for i, v in enumerate(x)]
            fd = (final(*up) - final(*dn)) / (2 * h)
        assert abs(float((g * d).sum() - fd)) < 1e-4 * float(g.norm() * d.norm()), (
            k,
            float((g * d).sum()),
            float(fd),
        )
    assert max(low) < 2e-3


@pytest.mark.parametrize("asset,root", GYM_ASSETS, ids=[a for a, _ in GYM_ASSETS])
def test_numba_link_rows_equal_the_torch_forward_kinematics(asset, root):
    """The link rows and the frames' first and second derivatives from the numba kernels (CPU, float64, no autograd
    wanted) equal those of the differentiable torch form, floating bases turned up to near pi included."""
    import importlib.resources

    from cfd_torch.sim.articulation import _chain, _fk_derivatives, _fk_rows
    from cfd_torch.sim.mjcf import load_mjcf

    path = importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / asset
    art = Articulation(load_mjcf(str(path), root=root))
    g = torch.Generator().manual_seed(5)
    A = 6
    q = 2.0 * torch.randn(A, art.num_coords, generator=g, dtype=F64)
    if art.floating:
        u = torch.nn.functional.normalize(torch.randn(A, 3, generator=g, dtype=F64), dim=1)
        q[:, 3:6] = (
            u * torch.tensor([0.0, 1e-9, 0.3, 2.0, math.pi - 1e-4, math.pi - 1e-8], dtype=F64)[:, None]
        )
    base = None if art.floating else torch.randn(A, 6, generator=g, dtype=F64)
    fast = _fk_rows(art, q, base)
    with torch.enable_grad():
        ref = _fk_rows(art, q.clone().requires_grad_(), base).detach()
    assert fast.shape == (A, art.num_links, 6)
    assert float((fast - ref).abs().max()) < 1e-12
    fast = _chain(art, q, base, 2)
    with torch.enable_grad():
        ref = [x.detach() for x in _chain(art, q.clone().requires_grad_(), base, 2)]
    assert len(fast) == len(ref) == 6
    assert float(fast[4].abs().max()) > 0  # second derivatives present
    for x, y in zip(fast, ref, strict=True):
        assert x.shape == y.shape
        assert float((x - y).abs().max()) < 1e-12
    # the rows' Jacobian and second-derivative contraction (the step's pull-back), from the numba loop
    lo = art.first_moving
    rg = torch.randn(A, art.num_links - lo, 6, generator=g, dtype=F64)
    J, S = _fk_derivatives(art, q, base, lo, rg)
    with torch.enable_grad():
        Jr, Sr = (x.detach() for x in _fk_derivatives(art, q.clone().requires_grad_(), base, lo, rg))
    assert J.shape == Jr.shape == (A, 6 * (art.num_links - lo), art.num_coords) and S.shape == Sr.shape
    assert float(Sr.abs().max()) > 1e-3  # a second-derivative term present
    assert float((J - Jr).abs().max()) < 1e-12 and float((S - Sr).abs().max()) < 1e-11
    assert torch.equal(_fk_derivatives(art, q, base, lo, None)[0], J)


@pytest.mark.parametrize("which", ["branchy", "multi"])
def test_numba_frames_equal_the_torch_chain_on_trees_with_anchors_and_refs(which):
    """The numba frames and derivatives on a branching tree of hinges and slides with anchors, and on links with
    several joints, refs and a mounted root that has joints (where an anchor or a slide enters every term)."""
    from cfd_torch.sim.articulation import _chain, _fk_derivatives, _fk_rows

    art = _branchy_chain() if which == "branchy" else _multi_chain()
    g = torch.Generator().manual_seed(11)
    q = torch.randn(4, art.num_coords, generator=g, dtype=F64)
    root = torch.randn(4, 6, generator=g, dtype=F64)
    with torch.enable_grad():
        ref = [x.detach() for x in _chain(art, q.clone().requires_grad_(), root, 2)]
        ref_rows = _fk_rows(art, q.clone().requires_grad_(), root).detach()
    assert float(ref[3].abs().max()) > 0.1 and float(ref[5].abs().max()) > 0.1
    for x, y in zip(_chain(art, q, root, 2), ref, strict=True):
        assert float((x - y).abs().max()) < 1e-12
    assert float((_fk_rows(art, q, root) - ref_rows).abs().max()) < 1e-12
    rg = torch.randn(4, art.num_links - art.first_moving, 6, generator=g, dtype=F64)
    J, S = _fk_derivatives(art, q, root, art.first_moving, rg)
    with torch.enable_grad():
        Jr, Sr = (
            x.detach() for x in _fk_derivatives(art, q.clone().requires_grad_(), root, art.first_moving, rg)
        )
    assert float(Sr.abs().max()) > 0.1
    assert float((J - Jr).abs().max()) < 1e-12 and float((S - Sr).abs().max()) < 1e-11


# ------------------------------------------------------------------------------------------------ audit regressions
def _arm_xml(joint: str = "", actuator: str = "", extra: str = "") -> str:
    """A 0.5 m capsule arm on a hinge about y, hung from a joint-less base at z = 1 (a fixed base)."""
    return f"""<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
      <body name="arm"><joint name="j" type="hinge" axis="0 1 0" {joint}/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody>
      <actuator>{actuator}</actuator>{extra}</mujoco>"""


def test_servo_past_pi_on_an_unlimited_hinge_settles_instead_of_spinning():
    """A position servo (kp 20, kv 0.3) toward 3.0 rad on an unlimited hinge, no gravity: the swing overshoots past
    pi and rings down to 3.0 (MuJoCo: 3.004 at 4 s). Before, the servo's spring was cut at ref + pi, its force
    flipped there, and the arm spun on (unwrapped angle 137 rad at 4 s); a joint spring toward 4.0 rad settles at
    4.0 - 2 pi, the same angle reached the short way."""
    from cfd_torch.sim.articulation import articulation

    for joint, act, ctrl, goal in (
        ("", '<position joint="j" kp="20" kv="0.3"/>', [3.0], 3.0),
        ('stiffness="20" springref="229.18" damping="0.3"', "", [], 4.0 - 2 * math.pi),  # degrees: 4.0 rad
    ):
        art = articulation(_arm_xml(joint, act))
        scene = Scene([], articulations=[art], gravity=(0.0, 0.0, 0.0))
        q0 = art.poses(torch.tensor([0.0], dtype=F64))
        traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=torch.tensor(ctrl, dtype=F64))] * 300)
        th = np.unwrap(scene.kinematics.coords(traj.q)[:, 0].numpy())
        assert th.max() < 2 * math.pi  # never a whole turn
        assert (
            abs(math.remainder(th[-1] - goal, 2 * math.pi)) < 0.05
        )  # 3 s: settled (2.99 and -2.283 measured)


def test_hinge_ranges_beyond_pi_from_ref():
    """A range of 0..300 degrees: a state at 4.0 rad reads back as 4.0 and steps (before: -2.28, below the range,
    and StepError); a range of +-200 degrees (wider than a turn) is refused by name."""
    from cfd_torch.sim.articulation import articulation

    art = articulation(_arm_xml('range="0 300"'))
    scene = Scene([], articulations=[art], gravity=(0.0, 0.0, 0.0))
    q0 = art.poses(torch.tensor([4.0], dtype=F64))
    assert abs(float(scene.kinematics.coords(q0[None])[0, 0]) - 4.0) < 1e-12
    step(scene, State(q0, q0.clone()))
    with pytest.warns(UserWarning, match="hinge joint 'j' has the range .* a whole turn or more"):
        wide = articulation(_arm_xml('range="-200 200"'))
    assert wide.lower.tolist() == [-math.inf] and wide.upper.tolist() == [math.inf]
    # a servo across the gap of a limited hinge goes round through the range, not the short way into a limit
    # (range +-170 degrees, from -2.5 to 2.9 rad: 2.9000 at 1.5 s, as in MuJoCo)
    art = articulation(_arm_xml('range="-170 170"', '<position joint="j" kp="20" kv="1" ctrlrange="-3 3"/>'))
    scene = Scene([], articulations=[art], gravity=(0.0, 0.0, 0.0))
    q0 = art.poses(torch.tensor([-2.5], dtype=F64))
    traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=torch.tensor([2.9], dtype=F64))] * 150)
    assert abs(float(scene.kinematics.coords(traj.q[-1:])[0, 0]) - 2.9) < 1e-3


def test_joint_outside_its_limits_is_refused_by_name():
    """Gymnasium's Ant at its MJCF pose (every joint 0) has its ankles outside their 30-70 degree ranges: a
    ValueError names the joint (before: StepError "infeasible Newton start")."""
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml())
    scene = Scene([], articulations=[ant], gravity=(0.0, 0.0, 0.0))
    q = ant.poses(torch.zeros(8, dtype=F64), torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64))
    with pytest.raises(
        ValueError, match="state.q: joint 'ant/ankle_1' \\(articulation 0\\) is at 0, outside its range"
    ):
        step(scene, State(q, q.clone()))


def test_mjcf_physics_the_step_does_not_model_is_refused(tmp_path, monkeypatch):
    from cfd_torch.sim.articulation import articulation

    monkeypatch.chdir(tmp_path)  # (MuJoCo writes its warning about the NaN below to MUJOCO_LOG.TXT here)

    two = """<mujoco><worldbody><body name="b" pos="0 0 1"><geom type="sphere" size="0.05"/>
      <body name="a1"><joint name="j1" type="hinge" axis="0 1 0" {j1}/><geom type="capsule" fromto="0 0 0 0 0 -0.5"
      size="0.03"/><body name="a2" pos="0 0 -0.5"><joint name="j2" type="hinge" axis="0 1 0"/><geom type="capsule"
      fromto="0 0 0 0 0 -0.4" size="0.03"/></body></body></body></worldbody>{extra}</mujoco>"""
    cases = [
        ('frictionloss="50"', "", "joint 'j1': frictionloss is not supported"),
        ('actuatorfrcrange="-0.1 0.1"', '<actuator><motor joint="j1"/></actuator>', "actuatorfrcrange"),
        (
            "",
            '<equality><joint joint1="j2" joint2="j1"/></equality>',
            "<equality> constraint .* is not supported",
        ),
        (
            "",
            '<tendon><fixed name="t" limited="true" range="-0.05 0.05"><joint joint="j1" coef="1"/>'
            '<joint joint="j2" coef="1"/></fixed></tendon>',
            "tendon 't': tendon limits",
        ),
    ]
    cases += [
        ('damping="-1"', "", "joint 'j1': damping must be finite and >= 0, got -1"),
        ('stiffness="-3"', "", "joint 'j1': stiffness must be finite and >= 0, got -3"),
        ('armature="inf"', "", "joint 'j1': armature must be finite and >= 0, got inf"),
        # a NaN limit loaded as no limit at all (MuJoCo only warned on stderr): the joint passed through it
        ('limited="true" range="nan 1"', "", r"joint 'j1': range must be finite, got \[nan, 0.0174"),
        ('limited="true" range="-inf 1"', "", r"joint 'j1': range must be finite, got \[-inf, 0.0174"),
        ('springref="inf"', "", r"joint 'j1': springref must be finite, got \[inf\]"),
        (
            "",
            '<actuator><position name="p" joint="j1" kp="-30"/></actuator>',
            "actuator 'p': kp and kv must be finite and >= 0",
        ),
        (
            "",
            '<actuator><motor name="m" joint="j1" gear="inf"/></actuator>',
            "actuator 'm': gear must be finite",
        ),
    ]
    for j1, extra, message in cases:
        with pytest.raises(ValueError, match=message):
            articulation(two.format(j1=j1, extra=extra))
    with pytest.raises(ValueError, match=r"the model \(MJCF or URDF\) is not well-formed XML"):
        articulation("<robot name='x'><link name='a'></robot>")
    with pytest.raises(ValueError, match="body 'a1': gravcomp is not supported"):
        articulation(two.format(j1="", extra="").replace('<body name="a1">', '<body name="a1" gravcomp="1">'))
    fluid = two.format(j1="", extra="").replace(
        "<worldbody>", '<option density="1000" viscosity="0.1"/><worldbody>'
    )
    with pytest.warns(
        UserWarning, match=r"<option density=1000.0 viscosity=0.1>: fluid forces are not modelled"
    ):
        articulation(fluid)
    # a link without geoms (valid MJCF: an <inertial> only) has no surface for the contact hierarchy
    bare = two.format(j1="", extra="").replace(
        '<geom type="capsule" fromto="0 0 0 0 0 -0.5"\n      size="0.03"/>',
        '<inertial pos="0 0 0" mass="0.1" diaginertia="1e-4 1e-4 1e-4"/>',
    )
    assert "inertial" in bare
    with pytest.raises(ValueError, match="link 'a1' has no geoms"):
        articulation(bare)
    # a visual-only geom (contype = conaffinity = 0) beside a colliding one: out of the collision mesh, in the mass;
    # a link with nothing else keeps it, with a warning
    tip = '<geom name="tip" type="sphere" pos="0 0 -0.5" size="0.02" contype="0" conaffinity="0"/>'
    plain, tipped = (
        articulation(_arm_xml()),
        articulation(_arm_xml().replace('size="0.03"/>', 'size="0.03"/>' + tip)),
    )
    assert tipped.bodies[1].bsh.num_faces == plain.bodies[1].bsh.num_faces
    assert tipped.bodies[1].mass > plain.bodies[1].mass
    alone = _arm_xml().replace(
        '<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/>',
        '<geom name="arm_vis" type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" contype="0" conaffinity="0"/>',
    )
    with pytest.warns(UserWarning, match=r"geoms \['arm_vis'\] have contype = conaffinity = 0"):
        articulation(alone)


def test_mjcf_file_with_an_include_next_to_it(tmp_path):
    from cfd_torch.sim.articulation import articulation

    (tmp_path / "defaults.xml").write_text(
        '<mujoco><default><joint damping="0.2" armature="0.01"/><geom size="0.03"/></default></mujoco>'
    )
    (tmp_path / "robot.xml").write_text(
        '<mujoco model="inc"><include file="defaults.xml"/><worldbody><body name="base" pos="0 0 1"><geom '
        'type="sphere" size="0.05"/><body name="arm"><joint name="j" type="hinge" axis="0 1 0"/><geom '
        'type="capsule" fromto="0 0 0 0 0 -0.5"/></body></body></worldbody></mujoco>'
    )
    art = articulation(tmp_path / "robot.xml")
    assert art.damping.tolist() == [0.2] and art.armature.tolist() == [0.01]


def test_mjcf_file_with_a_mesh_asset_next_to_it_loads_from_any_directory(tmp_path, monkeypatch):
    """A mesh file under the model's meshdir (a table in the worldbody; the robot's own geoms are primitives) is read
    relative to the model file, as MuJoCo reads it, whatever the working directory."""
    (tmp_path / "assets").mkdir()
    trimesh.creation.box(extents=(1.0, 1.0, 0.1)).export(tmp_path / "assets" / "table.stl")
    (tmp_path / "robot.xml").write_text(
        '<mujoco><compiler meshdir="assets"/><asset><mesh name="table" file="table.stl"/></asset><worldbody>'
        '<geom type="mesh" mesh="table" pos="0 0 -0.05"/><body name="bot" pos="0 0 0.5"><freejoint/><geom '
        'type="sphere" size="0.1"/><body name="arm" pos="0.1 0 0"><joint name="j" axis="0 1 0"/><geom '
        'type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/></body></body></worldbody></mujoco>'
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    art = articulation(tmp_path / "robot.xml")
    assert art.names == ("bot", "arm") and art.num_joints == 1


def test_servo_near_a_limit_of_a_narrow_slide_settles_at_its_target():
    """A gripper finger's 4 cm slide (range [0, 0.04] m) with a position servo (kp 100, kv 10, no gravity): the limit
    barrier acts within a tenth of the range of each limit, so targets 5 mm from a limit are reached (with the
    barrier 2 cm wide everywhere, the servo settled at 18.2 mm for a 5 mm target, 21.5 mm for 30 mm)."""
    xml = """<mujoco><worldbody><body name="palm"><geom type="box" size=".05 .05 .02"/>
      <body name="finger" pos="0 0 -.05"><joint name="f" type="slide" axis="1 0 0" range="0 0.04"/>
      <geom type="box" size=".01 .01 .03" mass="0.05"/></body></body></worldbody>
      <actuator><position name="p" joint="f" kp="100" kv="10"/></actuator></mujoco>"""
    art = articulation(xml)
    scene = Scene([], articulations=[art], dt=0.01, gravity=(0.0, 0.0, 0.0))
    for target in (0.005, 0.035):
        q = art.poses(torch.tensor([0.02], dtype=F64))
        s = State(q, q.clone())
        for _ in range(100):
            s = step(scene, s, Action(ctrl=torch.tensor([target], dtype=F64)))
        assert abs(float(scene.kinematics.coords(s.q[None])[0, 0]) - target) < 1e-5


def test_mjcf_refusals_look_at_the_loaded_subtree_only_and_a_zero_gear_motor_is_finite():
    from cfd_torch.sim.articulation import articulation

    door = '<body name="door" pos="2 0 1"><joint name="hinge" type="hinge" frictionloss="1"/><geom size="0.1"/></body>'
    xml = _arm_xml(actuator='<motor joint="j" gear="0"/>').replace("</worldbody>", door + "</worldbody>")
    art = articulation(xml, root="base")  # the door's frictionloss is not the robot's
    scene = Scene([], articulations=[art], gravity=(0.0, 0.0, -9.81))
    q0 = art.poses(torch.tensor([0.3], dtype=F64))
    nxt = step(scene, State(q0, q0.clone()), Action(ctrl=torch.tensor([1.0], dtype=F64)))
    assert bool(torch.isfinite(nxt.q).all())  # (gear 0: before, NaN from the servo target ctrl / gear)


def test_articulation_inputs_are_checked():
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml())
    j = torch.zeros(8, dtype=F64)
    with pytest.raises(ValueError, match=r"base must be a torch.float64 tensor of shape \(\[B,\] 6\)"):
        ant.poses(j, torch.zeros(7, dtype=F64))  # a MuJoCo qpos-style quaternion base
    with pytest.raises(ValueError, match="joints must be a float tensor"):
        ant.poses(torch.tensor(0.0, dtype=F64))
    with pytest.raises(ValueError, match="joints contains NaN"):
        ant.poses(torch.full((8,), math.nan, dtype=F64))
    scene = Scene([], articulations=[articulation(_arm_xml())], gravity=(0.0, 0.0, 0.0))
    q = scene.bodies[-1:] and scene.kinematics.poses(
        torch.zeros(1, 1, dtype=F64), torch.zeros(1, 2, 6, dtype=F64)
    )
    with pytest.raises(ValueError, match="action.joints drives kinematic robots"):
        step(scene, State(q[0], q[0].clone()), Action(joints=torch.zeros(5, 7, dtype=F64)))


def test_link_rows_that_do_not_fit_the_joints_are_refused():
    """A bar hinged about y: its row moved 0.3 m off the hinge and turned about x (no joint for it) used to be read
    as another joint angle (-0.535 rad instead of 0.3) and stepped on silently; rows from Articulation.poses pass,
    in float32 too."""
    xml = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="box" size="0.05 0.05 0.05"/>
    <body name="bar"><joint name="hinge" type="hinge" axis="0 1 0" range="-60 60"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    floor = rigid_body(trimesh.creation.box((3, 3, 0.2)), kind="static")
    scene = Scene([floor], articulations=[art], dt=0.01, gravity=(0, 0, 0))
    rows = art.poses(torch.tensor([0.3], dtype=F64), torch.tensor([0, 0, 1.0, 0, 0, 0], dtype=F64))
    q = torch.cat([torch.tensor([[0, 0, -0.1, 0, 0, 0]], dtype=F64), rows])
    nxt = step(scene, State(q, q.clone()))
    assert float((nxt.q - q).abs().max()) < 1e-9  # at rest, no gravity
    for shift, turn in ((0.3, 0.0), (0.0, 0.5), (1e-4, 0.0)):
        bad = q.clone()
        bad[2, 0] += shift
        bad[2, 3] += turn
        with pytest.raises(
            ValueError, match=r"state\.q: the link rows of articulation .* do not fit its joints: link 1"
        ):
            step(scene, State(bad, q.clone()))
    # q_prev is only an approximate configuration (q - dt v, a sub-step's blend): not checked
    step(scene, State(q.clone(), bad))
    # float32 rows far from the origin are rounded by more than 1e-5 m: the tolerance follows the dtype
    far = art.poses(torch.tensor([0.3], dtype=F64), torch.tensor([80.0, -60.0, 1.0, 0, 0, 0], dtype=F64))
    q32 = torch.cat([torch.tensor([[80.0, -60.0, -0.1, 0, 0, 0]], dtype=F64), far]).float()
    assert float((step(scene, State(q32, q32.clone())).q - q32).abs().max()) < 1e-4


def test_a_turning_robot_started_with_velocities_steps():
    """initial_state(q, v) sets q_prev = q - dt v row by row, which is a configuration only to O(dt^2): the step
    takes it (only state.q's rows must fit the joints), and the base keeps turning at about its 2 rad/s."""
    xml = """<mujoco><worldbody><body name="base" pos="0 0 1"><freejoint/><geom type="box" size="0.05 0.05 0.05"/>
    <body name="bar"><joint name="hinge" type="hinge" axis="0 1 0" range="-60 60"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    scene = Scene([], articulations=[art], dt=0.01, gravity=(0, 0, 0))
    q = art.poses(torch.tensor([0.6], dtype=F64), torch.tensor([0, 0, 1.0, 0, 0, 0], dtype=F64))
    w = torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    v = torch.zeros_like(q)
    v[:, :3] = torch.linalg.cross(w.expand_as(q[:, :3]), q[:, :3] - q[0, :3])
    v[:, 3:] = w
    s = step(scene, scene.initial_state(q, v))
    assert 1.7 < float((s.q[0, 5] - s.q_prev[0, 5]) / scene.dt) < 2.1


def test_a_joint_started_within_newton_tol_of_a_limit_is_refused():
    """Within about newton_tol of a limit the barrier's Newton step is about the distance to the limit, below the
    convergence threshold: the step ended where it began (an arm 1e-10 rad inside its limit stayed there under
    gravity). Such a start is refused by name; from 1e-5 inside the barrier pushes the arm out."""
    xml = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
      <body name="arm"><joint name="j" type="hinge" axis="0 1 0" range="-60 60"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    scene = Scene([], articulations=[art])
    hi = math.pi / 3
    r = art.poses(torch.tensor([hi - 1e-10], dtype=F64))
    with pytest.raises(ValueError, match="joint '.*/j' \\(articulation 0\\) is at .*within 1e-06 of a limit"):
        step(scene, State(r, r.clone()))
    r = art.poses(torch.tensor([hi - 1e-5], dtype=F64))
    moved = hi - 1e-5 - float(scene.kinematics.coords(step(scene, State(r, r.clone())).q[None])[0, 0])
    assert moved > 1e-3  # pushed out of the barrier (observed 0.014 rad)


def _tilted_box_on_a_hinge() -> Articulation:
    """A 0.4 x 0.2 x 0.1 m box on a hinge about z, tilted 30 degrees about x and its centre 0.15 m off the axis:
    the hinge is none of its principal axes and its centre of mass circles the axis."""
    return articulation(
        """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
        <body name="box"><joint name="spin" type="hinge" axis="0 0 1"/>
        <geom type="box" size="0.2 0.1 0.05" pos="0.15 0 0" euler="30 0 0"/></body></body></worldbody></mujoco>"""
    )


@pytest.mark.parametrize("which", ["bar", "tilted box"])
def test_a_link_spinning_freely_on_a_hinge_keeps_its_rate(which):
    """Without gravity a link turning on a fixed hinge keeps its rate (its centre of mass circles the axis; the
    tilted box is spun off its principal axes). With every link predicted as a free body and projected back onto
    the hinge, the bar slowed from 5 to 3.8 rad/s in 2 s at dt = 0.01 and the box lost 1.0 of its 5 rad/s;
    the joints' prediction keeps both to rounding."""
    art = _pendulum() if which == "bar" else _tilted_box_on_a_hinge()
    base = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
    w, dt, steps = 5.0, 0.01, 200
    scene = Scene([], articulations=[art], dt=dt, gravity=(0.0, 0.0, 0.0))
    q0 = art.poses(torch.tensor([0.0], dtype=F64), base)
    traj = rollout(scene, State(q0, art.poses(torch.tensor([-w * dt], dtype=F64), base)), steps)
    th = np.unwrap(_angles(scene, traj))
    rate = np.diff(th) / dt
    assert np.abs(rate - w).max() < 1e-9 * w
    assert abs(th[-1] - w * dt * steps) < 1e-9


GIMBAL = """<mujoco><option integrator="RK4" timestep="0.0005"/><worldbody>
  <body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="outer"><joint name="yaw" type="hinge" axis="0 0 1"/><geom type="box" size="0.3 0.02 0.02" pos="0 0 0.1"/>
  <body name="inner" pos="0 0 0.1"><joint name="pitch" type="hinge" axis="1 0 0"/>
  <geom type="box" size="0.2 0.1 0.03" pos="0.05 0 0.08" euler="10 20 30"/></body></body></body></worldbody></mujoco>"""
SWUNG_PENDULUM = """<mujoco><option integrator="RK4" timestep="0.0005"/><worldbody>
  <body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="upper"><joint name="j1" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/>
  <body name="lower" pos="0 0 -0.5"><joint name="j2" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0.1 0 -0.4" size="0.03"/></body></body></body></worldbody></mujoco>"""


@pytest.mark.parametrize(
    "xml,th0,v0,bound", [(GIMBAL, [0.0, 0.3], [5.0, 0.0], 0.01), (SWUNG_PENDULUM, [0.0, 0.7], [6.0, -2.0], 0.015)],
    ids=["gimbal", "double pendulum"],
)  # fmt: skip
def test_fast_chains_follow_mujoco_at_first_order(xml, th0, v0, bound):
    """Two hinged chains without gravity, started fast (a gimbal's yaw at 5 rad/s, its inner box asymmetric and
    off its hinge's axis: the pitch accelerates from the gyroscopic and centrifugal terms; a double pendulum
    swung at 6 and -2 rad/s): the joint angles after 1 s against MuJoCo's RK4 at 0.5 ms converge at first order
    in dt, from within ``bound`` rad at dt = 0.01 (0.0066 and 0.0088 rad; with links predicted as free bodies:
    0.085 and 0.57 rad, the rates falling behind). The gimbal's first-step accelerations are within 3.3e-3
    rad/s^2 of MuJoCo's at dt = 0.01 (0.29 before), halving with dt."""
    import mujoco

    art = articulation(xml)
    model = mujoco.MjModel.from_xml_string(xml)
    model.opt.gravity[:] = 0.0
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = th0, v0
    mujoco.mj_forward(model, data)
    acc = data.qacc.copy()
    for _ in range(2000):
        mujoco.mj_step(model, data)
    want = data.qpos.copy()
    base = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
    th0_, v0_ = torch.tensor(th0, dtype=F64), torch.tensor(v0, dtype=F64)
    err, acc_err = [], []
    for dt in (0.01, 0.005):
        scene = Scene([], articulations=[art], dt=dt, gravity=(0.0, 0.0, 0.0))
        traj = rollout(scene, State(art.poses(th0_, base), art.poses(th0_ - dt * v0_, base)), round(1.0 / dt))
        th = np.unwrap(scene.kinematics.coords(traj.q).detach().numpy(), axis=0)
        err.append(np.abs(th[-1] - want).max())
        acc_err.append(np.abs((th[1] - 2 * th[0] + (th0_ - dt * v0_).numpy()) / dt**2 - acc).max())
    assert err[0] < bound
    assert 1.7 < err[0] / err[1] < 2.4
    if xml is GIMBAL:  # (MuJoCo's accelerations at the swung pendulum's start include a contact of its links)
        assert acc_err[0] < 5e-3 and 1.7 < acc_err[0] / acc_err[1] < 2.3


def test_rollout_gradient_of_a_fast_floating_robot_matches_finite_differences():
    """A floating box with a bar on a hinge, turning at 2 rad/s and its bar swinging at 4 rad/s under gravity: the
    gradient of the bar's final position through 12 steps, in its initial angle and rate, the bar's mass and the
    base's second moment (the links' prediction and its Coriolis increment depend on all four), against central
    differences."""
    xml = """<mujoco><worldbody><body name="base" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.06 0.04"/>
    <body name="bar"><joint name="hinge" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0.1 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    dt = 0.01
    scene = Scene([], articulations=[art], dt=dt)
    p0 = scene.params()
    base = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.3], dtype=F64)
    turn = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 2.0 * dt], dtype=F64)

    def final(x: torch.Tensor) -> torch.Tensor:
        th, rate, m_bar, s_base = x
        q = art.poses(th[None], base)
        q_prev = art.poses((th - rate * dt)[None], base - turn)
        mass = torch.stack([p0.mass[0], m_bar])
        S = p0.second_moment.clone()
        S = torch.cat([(S[0] * s_base)[None], S[1:]])
        traj = rollout(scene, State(q, q_prev), 12, p0._replace(mass=mass, second_moment=S))
        return traj.q[-1, 1, :3].sum()

    x = torch.tensor([0.4, 4.0, float(p0.mass[1]), 1.0], dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(final(x), x)
    assert (g.abs() > 1e-4).all()
    h = torch.tensor([1e-6, 1e-5, 1e-6, 1e-6], dtype=F64)
    with torch.no_grad():
        fd = torch.stack(
            [(final(x + h[k] * e) - final(x - h[k] * e)) / (2 * h[k]) for k, e in enumerate(torch.eye(4))]
        )
    assert torch.allclose(g, fd, rtol=1e-5, atol=1e-9)


def _ring(limited: bool) -> Articulation:
    """A box on three hinges at one anchor, about z, x and y (a gimbal of hinges): (a, b, c) and (a + pi, pi - b,
    c + pi) give the same pose; with ``limited`` the outer two have the range +-60 degrees."""
    rng = ' range="-60 60"' if limited else ""
    return articulation(
        f"""<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
        <body name="ring"><joint name="a" type="hinge" axis="0 0 1"{rng}/><joint name="b" type="hinge" axis="1 0 0"/>
        <joint name="c" type="hinge" axis="0 1 0"{rng}/><geom type="box" size="0.2 0.1 0.03" pos="0.05 0.02 0.04"/>
        </body></body></worldbody></mujoco>"""
    )


def test_three_hinges_at_one_anchor_read_back_on_the_branch_that_fits():
    """Link poses do not tell (a, b, c) from (a + pi, pi - b, c + pi): the joint values read back are the posed
    ones where those are nearer ref (the middle hinge past pi / 2 included: the middle hinge alone used to decide,
    and (0, 1.6, 0) read back as (-pi, 1.54, -pi)), those within the outer hinges' ranges, and those nearest
    ``near`` when it is given."""
    from cfd_torch.sim.articulation import _wrap

    free = _ring(False)
    for x in ([0.0, 1.6, 0.0], [0.3, 2.5, -0.4], [-0.2, -1.9, 0.1]):
        th = torch.tensor(x, dtype=F64)
        assert torch.allclose(free.coords(free.poses(th)[None])[0], th, atol=1e-12)
        flipped = _wrap(th + torch.tensor([math.pi, 0.0, math.pi], dtype=F64))
        flipped[1] = _wrap(math.pi - th[1])
        near = free.coords(free.poses(th)[None], near=flipped[None] + 0.1)[0]
        assert torch.allclose(near, flipped, atol=1e-12)
    limited = _ring(True)
    th = torch.tensor(
        [0.9, -2.8, -0.7], dtype=F64
    )  # nearer ref flipped, but only this one is within the ranges
    assert torch.allclose(limited.coords(limited.poses(th)[None])[0], th, atol=1e-12)


def test_three_hinges_and_three_slides_read_back_within_every_range():
    """Three hinges with anchors and three limited slides on one link: link poses do not tell two configurations
    apart, and the one read back is the one with every joint within its range (the slides' ranges included: the
    hinges' alone used to decide, and the slide x came back at 0.1075, outside its +-0.05, the valid state then
    refused as beyond a limit)."""
    from cfd_torch.sim.articulation import ArticulatedKinematics

    xml = """<mujoco><compiler autolimits="true"/><worldbody><body name="root"><geom type="box" size=".1 .1 .1"/>
      <body name="l" pos="0 0 -.3">
        <joint name="hx" axis="1 0 0" pos="0 0 .05"/><joint name="hy" axis="0 1 0" pos=".05 0 0"/>
        <joint name="hz" axis="0 0 1" pos="0 .05 0"/><joint name="sx" type="slide" axis="1 0 0" range="-.05 .05"/>
        <joint name="sy" type="slide" axis="0 1 0" range="-.05 .05"/>
        <joint name="sz" type="slide" axis="0 0 1" range="-.05 .05"/>
        <geom type="sphere" size=".05"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    for x in ([2.0, 1.0, 2.0, 0.01, 0.02, -0.01], [-0.5, 2.2, 0.3, -0.04, 0.0, 0.03]):
        q = torch.tensor(x, dtype=F64)
        rows = art.poses(q)
        assert torch.allclose(
            art.coords(rows), q, rtol=0.0, atol=1e-12
        )  # unbatched rows, as poses gives them
        kin = ArticulatedKinematics(torch.zeros(0, dtype=torch.long), [art], [0], art.num_links)
        kin.check_within_limits(rows[None], "state.q")


def test_moving_rows_and_coords_check_their_inputs():
    """Articulation.moving_rows and .coords, the public faces of the forward kinematics and its inverse, refuse
    coordinates or rows of the wrong size (the numba kernel has no bounds checks: 6 of the Ant's 14 coordinates
    read past the array's end) and NaN."""
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    ant = articulation(gymnasium_ant_xml())
    for width in (6, 8, 15):
        with pytest.raises(ValueError, match=r"coords must be a float tensor of shape \(A, 14\)"):
            ant.moving_rows(torch.zeros(1, width, dtype=F64), None)
    with pytest.raises(ValueError, match="coords contains NaN"):
        ant.moving_rows(torch.full((1, 14), math.nan, dtype=F64), None)
    rows = ant.poses(torch.zeros(8, dtype=F64), torch.zeros(6, dtype=F64))  # (9, 6)
    assert ant.coords(rows).shape == (14,) and ant.coords(rows[None]).shape == (1, 14)
    with pytest.raises(ValueError, match=r"rows must be a float tensor of shape \(\[A,\] 9, 6\)"):
        ant.coords(rows[None, :8])
    with pytest.raises(ValueError, match="rows contains NaN"):
        ant.coords(torch.full((1, 9, 6), math.nan, dtype=F64))
    with pytest.raises(ValueError, match=r"near must be a torch.float64 tensor of shape \(\[A,\] 14\)"):
        ant.coords(rows[None], near=torch.zeros(1, 8, dtype=F64))
    with pytest.raises(ValueError, match=r"near must be a torch.float64 tensor"):
        ant.coords(rows, near=[0.0] * 14)
    arm = articulation(_arm_xml())  # a joint-less fixed root: its pose is needed
    with pytest.raises(ValueError, match=r"root must be a torch.float64 tensor of shape \(2, 6\)"):
        arm.moving_rows(torch.zeros(2, arm.num_coords, dtype=F64), None)


def test_three_hinges_turning_past_the_middle_quarter_turn_step_on_one_branch():
    """The ring turning under gravity from b = 1.7 rad (past the middle hinge's quarter turn) with its outer hinges
    limited to +-60 degrees: the start was refused (read as a = 0.2 - pi, outside its range); now 60 steps run,
    every step's joint values within the ranges and within 0.2 rad of the last (mod 2 pi)."""
    from cfd_torch.sim.articulation import _wrap

    art = _ring(True)
    dt = 0.01
    scene = Scene([], articulations=[art], dt=dt)
    th0 = torch.tensor([0.2, 1.7, -0.1], dtype=F64)
    v0 = torch.tensor([0.5, 2.0, 0.3], dtype=F64)
    traj = rollout(scene, State(art.poses(th0), art.poses(th0 - dt * v0)), 60)
    th = scene.kinematics.coords(traj.q)
    assert (th[:, [0, 2]].abs() < math.radians(60)).all()
    assert float(_wrap(th[1:] - th[:-1]).abs().max()) < 0.2
    assert float(_wrap(th[-1, 1] - th[0, 1]).abs()) > 0.5  # it did turn


BALL_JOINT = """<mujoco><worldbody><body name="torso" pos="0 0 1"><geom type="capsule" fromto="0 -0.07 0 0 0.07 0"
  size="0.07"/><body name="thigh" pos="0 0.1 -0.1"><joint name="hx" type="hinge" axis="1 0 0"/>
  <joint name="hz" type="hinge" axis="0 0 1"/><joint name="hy" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0.01 -0.34" size="0.06"/></body></body></worldbody></mujoco>"""


def _kinetic(scene: Scene, q_a: torch.Tensor, q_b: torch.Tensor) -> float:
    """The moving bodies' kinetic energy between poses q_a and q_b a step apart (velocities by differences; the
    angular one from the body-frame increment R_a^T R_b)."""
    from scipy.spatial.transform import Rotation

    from cfd_torch.rotation import rotation_matrix

    p, rows = scene.params(), scene.kinematics.bodies
    a, b = q_a[rows].detach(), q_b[rows].detach()
    v = (b[:, :3] - a[:, :3]) / scene.dt
    inc = rotation_matrix(a[:, 3:]).transpose(1, 2) @ rotation_matrix(b[:, 3:])
    w = torch.from_numpy(Rotation.from_matrix(inc.numpy()).as_rotvec()) / scene.dt
    S = p.second_moment
    inertia = S.diagonal(dim1=1, dim2=2).sum(1)[:, None, None] * torch.eye(3, dtype=F64) - S
    return float(0.5 * (p.mass * (v * v).sum(1)).sum() + 0.5 * torch.einsum("ni,nij,nj->", w, inertia, w))


@pytest.mark.parametrize(
    "xml,th0,v0,steps", [(BALL_JOINT, [-0.1, -0.2, -0.5], [1.0, 2.0, -3.0], 100),
                         (SWUNG_PENDULUM, [0.0, 0.7], [6.0, -2.0], 300)],
    ids=["ball joint", "double pendulum"],
)  # fmt: skip
def test_fast_chains_without_gravity_keep_their_energy(xml, th0, v0, steps):
    """Without gravity, damping or limits a chain's kinetic energy is conserved: a link on three hinges at one
    anchor turning at (1, 2, -3) rad/s, and the swung double pendulum, at dt = 0.01, keep theirs within 1 %
    (with links predicted as free bodies they lost 12 % in 1 s and 69 % in 4 s; with the joints' prediction and
    its Coriolis term as a force in the energy they gained until the step failed, in 0.33 s and 6 s)."""
    art = articulation(xml)
    dt = 0.01
    scene = Scene([], articulations=[art], dt=dt, gravity=(0.0, 0.0, 0.0))
    th0_, v0_ = torch.tensor(th0, dtype=F64), torch.tensor(v0, dtype=F64)
    traj = rollout(scene, State(art.poses(th0_), art.poses(th0_ - dt * v0_)), steps)
    K = [_kinetic(scene, traj.q[k], traj.q[k + 1]) for k in range(0, steps, 10)]
    assert K[0] > 1.0
    assert max(abs(k / K[0] - 1.0) for k in K) < 1e-2


def test_carry_moves_free_bodies_and_floating_bases():
    """ArticulatedKinematics.carry (a start that carries the moving bodies along with a kinematic pusher) shifts
    the free bodies' and the floating bases' translations and nothing else (it wrote a view of its output into
    itself and raised)."""
    xml = """<mujoco><worldbody><body name="base" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.06 0.04"/>
    <body name="bar"><joint name="hinge" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0.1 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    ball = rigid_body(trimesh.creation.icosphere(1, 0.05))
    scene = Scene([ball, ball], articulations=[articulation(xml)])
    kin = scene.kinematics
    for A in (1, 2):  # (one scene: the write of the view raised)
        q = torch.randn(A, kin.num_coords, dtype=F64)
        shift = torch.tensor([[0.1, -0.2, 0.3], [1.0, 2.0, 3.0]], dtype=F64)[:A]
        out = kin.carry(q, shift)
        want = q.clone()
        for k in (0, 6, 12):  # the two balls' and the base's translations
            want[:, k : k + 3] += shift
        assert torch.equal(out, want)


@pytest.mark.parametrize("mount_z, ball_x", [(1.2, None), (0.1, 3.0)])
def test_robot_hung_from_its_mount_stays_at_rest_away_from_the_origin(mount_z, ball_x):
    """A fixed base whose root has joints hangs from its mount, a world-frame pose: the step's frame near the moving
    bodies (1 m or more from the origin: the arm itself at table height, or a free ball 3 m away) must not move
    it. Such a robot used to be displaced by the frame's whole shift (2 m at a mount 1.2 m up) in one step."""
    import importlib.resources

    assets = importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets"
    arm = articulation(str(assets / "reacher.xml"), root="body0", mount=(0.0, 0.0, mount_z, 0.0, 0.0, 0.0))
    bodies, rows = [], arm.poses(torch.zeros(arm.num_joints, dtype=F64), None)
    if ball_x is not None:
        bodies = [rigid_body(trimesh.creation.icosphere(1, radius=0.1))]
        rows = torch.cat([torch.tensor([[ball_x, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=F64), rows])
    scene = Scene(bodies, articulations=[arm], gravity=(0.0, 0.0, 0.0))
    state = State(rows, rows)
    for _ in range(2):
        state = step(scene, state, Action(ctrl=torch.zeros(scene.num_actuators, dtype=F64)))
    moved = float((state.q - rows).abs().max())
    assert moved < 1e-9, moved


def _reacher_beside_box(off: tuple[float, float, float]) -> tuple[Scene, torch.Tensor, torch.Tensor]:
    """Gymnasium's reacher mounted beside a box sliding with friction on a floor, all moved by ``off`` [m], at a
    tenth of the scale (the small-scale settings of the translation test in tests/test_robustness.py): the scene,
    the start poses and the start velocities (the box at sqrt(0.1) m/s along x)."""
    import importlib.resources

    assets = importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets"
    s = 0.1
    kw = {"dt": 0.01 * math.sqrt(s), "margin": 1e-3 * s, "mu": 1e-8 * s**5, "ccd_spacing": 0.01 * s,
          "newton_tol": 1e-9 * s, "friction_eps_v": 1e-4 * math.sqrt(s)}  # fmt: skip
    floor = rigid_body(trimesh.creation.box((4 * s, 4 * s, 0.2 * s)), kind="static")
    box = rigid_body(trimesh.creation.box((0.2 * s, 0.15 * s, 0.1 * s)))
    mount = (off[0] + 0.5, off[1], off[2] + 0.05, 0.0, 0.0, 0.0)
    arm = articulation(str(assets / "reacher.xml"), root="body0", mount=mount)
    rows = arm.poses(torch.zeros(arm.num_joints, dtype=F64), None)
    q0 = torch.cat([torch.tensor([[0, 0, -0.1 * s, 0, 0, 0], [0, 0, 0.052 * s, 0, 0, 0]], dtype=F64), rows])
    q0[:2, :3] += torch.tensor(off, dtype=F64)
    v0 = torch.zeros(len(q0), 6, dtype=F64)
    v0[1, 0] = math.sqrt(s)
    return Scene([floor, box], friction=0.5, articulations=[arm], **kw), q0, v0


def test_scene_with_a_mounted_robot_steps_as_well_far_from_the_origin():
    """A mounted robot beside a box sliding with friction, the whole scene and the mount translated by 1 km: the
    step's frame moves the mount with it, so the trajectory matches the one at the origin (solved in the world frame
    it raised StepError)."""

    def slide(off):
        scene, q0, v0 = _reacher_beside_box(off)
        with torch.no_grad():
            q = rollout(scene, scene.initial_state(q0, v0), 20).q.clone()
        q[..., :3] -= torch.tensor(off, dtype=F64)
        return q

    a = slide((0.0, 0.0, 0.0))
    assert float((a[-1, 1, :3] - a[0, 1, :3]).norm()) > 0.01 * 0.1  # the box slides
    b = slide((1e3, -1e3, 1e3))
    assert float((b - a)[..., :3].abs().max()) < 1e-10


def test_a_batch_of_mounted_scenes_far_apart_is_solved_in_their_own_frames():
    """Scenes of one Scene with a mounted robot, 1 km apart in one batch: each group of scenes is solved in the
    frame it has alone (a frame shared by the batch, between them, made the 1 km scene fail: StepError), so the
    batch equals the scenes stepped alone, forward and backward."""
    scene, near, v = _reacher_beside_box((1e3, -1e3, 1e3))  # the box beside the robot, 1 km out
    away = near.clone()
    away[:2] = _reacher_beside_box((0.0, 0.0, 0.0))[1][:2]  # the floor and the box at the origin
    away[0, 2] -= 50.0
    away[:2, 0] -= 1000.0  # the box in free fall at the origin's side, its floor 50 m below
    v0 = torch.stack([v, v]).requires_grad_(True)

    def run(q, v):
        st = scene.initial_state(q, v)
        for _ in range(3):
            st = step(scene, st)
        return st.q

    both = run(torch.stack([near, away]), v0)
    (g_both,) = torch.autograd.grad(both[:, 1, :3].sum(), v0)
    for b, q in enumerate((near, away)):
        alone = run(q, v0[b])
        (g_alone,) = torch.autograd.grad(alone[1, :3].sum(), v0)
        assert float(g_alone[b].abs().max()) > 1e-3  # about 3 dt
        assert torch.equal(both[b], alone)
        torch.testing.assert_close(g_both[b], g_alone[b], rtol=1e-12, atol=1e-15)


def test_errors_of_scenes_solved_in_their_own_frames_name_the_batch_scene():
    """In a batch solved in groups, a bad scene is named by its index in the batch (it was its index in its group,
    "scene 1" for batch scene 2) and the message says which scenes the group holds."""
    scene, near, _ = _reacher_beside_box((1e3, -1e3, 1e3))
    away = near.clone()
    away[:2] = _reacher_beside_box((0.0, 0.0, 0.0))[1][:2]
    away[0, 2] -= 50.0
    away[:2, 0] -= 1000.0
    sunk = away.clone()
    sunk[1, 2] = sunk[0, 2] + 0.015 - 0.001  # the box 1 mm into its floor
    q = torch.stack([near, away, sunk])
    with pytest.raises(ValueError) as caught:
        step(scene, State(q, q.clone()))
    assert str(caught.value) == (
        "scenes [1, 2] of the batch, solved in their own frame: state.q: bodies penetrate (within the contact "
        "margin 0.0001): pairs (0, 1) (scene 2)"
    )


_STATIC_ROOT_ARM = """<mujoco><worldbody><body name="base"><geom type="sphere" size="0.04"/>
 <body name="upper"><joint name="yaw" type="hinge" axis="0 0 1" damping="0.5"/>
  <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" density="1000"/>
  <body name="fore" pos="0.4 0 0"><joint name="bend" type="hinge" axis="0 0 1" range="-120 120" damping="0.1"/>
   <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" density="1000"/></body></body></body></worldbody>
<actuator><motor joint="yaw" gear="5" ctrlrange="-1 1"/><position joint="bend" kp="20" kv="1"/></actuator></mujoco>"""


@pytest.mark.parametrize("with_box", [False, True])
def test_gradient_in_the_row_of_a_joint_less_root(with_box):
    """A fixed-base arm whose MJCF root has no joint stands where the state's root row puts it, its links hung from
    that row: the gradient in the row (where the arm stands) matches central differences, alone (tilted, gravity
    swings it) and sweeping a box on a floor. The adjoint held the links' poses and Jacobian fixed in the root's
    row, and missed the contact Hessian through the links: gradients 100 % off."""
    arm = articulation(_STATIC_ROOT_ARM)
    assert arm.first_moving == 1  # a joint-less root: a static body placed by the state
    ground = trimesh.creation.box((3.0, 3.0, 0.2))
    ground.apply_translation((0.0, 0.0, -0.1))
    bodies = (
        [rigid_body(trimesh.creation.box((0.1, 0.1, 0.1)), density=300.0), rigid_body(ground, kind="static")]
        if with_box
        else []
    )
    scene = Scene(bodies, articulations=[arm], dt=0.01, friction=0.5)
    th0, v0 = torch.tensor([0.0, 0.3], dtype=F64), torch.tensor([3.0, -1.0], dtype=F64)
    pre = [torch.tensor([[0.55, 0.22, 0.052, 0.0, 0.0, 0.0]], dtype=F64), torch.zeros(1, 6, dtype=F64)]
    pre = pre if with_box else []
    ctrl = torch.tensor([0.7, 0.5], dtype=F64)
    T = 8 if with_box else 3
    weights = torch.arange(1, 6 * scene.num_bodies + 1, dtype=F64).reshape(-1, 6).sin()

    def loss(root):
        q0 = torch.cat([*pre, arm.poses(th0, root)])
        qp = torch.cat([*pre, arm.poses(th0 - 0.01 * v0, root)])
        traj = rollout(scene, State(q0, qp), [Action(ctrl=ctrl)] * T)
        return (traj.q[-1] * weights).sum()

    root = torch.tensor([0.0, 0.0, 0.1, 0.0 if with_box else 0.5, 0.0, 0.0], dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(loss(root), root)
    assert float(g[3:].abs().max()) > 1e-3
    h = 1e-6
    with torch.no_grad():
        fd = torch.stack(
            [(loss(root + h * e) - loss(root - h * e)) / (2 * h) for e in torch.eye(6, dtype=F64)]
        )
    torch.testing.assert_close(g, fd, rtol=0, atol=1e-6 * float(fd.norm()))


def test_servo_gains_are_checked_on_servos_only():
    """Params.kp / kv entries of motors are unused: a negative one is accepted and changes nothing; a servo's
    negative gain is refused naming its actuator."""
    arm = articulation(_STATIC_ROOT_ARM)  # actuator 0 a motor, 1 a position servo
    scene = Scene([], articulations=[arm], dt=0.01)
    q = arm.poses(torch.tensor([0.0, 0.3], dtype=F64), torch.zeros(6, dtype=F64))
    state, action = State(q, q.clone()), Action(ctrl=torch.tensor([0.7, 0.5], dtype=F64))
    p = scene.params()
    assert p.kp.tolist() == [0.0, 20.0]
    ref = step(scene, state, action, p)
    odd = step(scene, state, action, p._replace(kp=torch.tensor([-3.0, 20.0], dtype=F64)))
    assert torch.equal(odd.q, ref.q)
    with pytest.raises(ValueError, match=r"params\.kv must be >= 0 \(a servo gain\) \(first at actuator 1\)"):
        step(scene, state, action, p._replace(kv=torch.tensor([0.0, -1.0], dtype=F64)))


def test_model_base_places_the_robot_where_mujoco_does():
    """``poses(joints)`` stands a fixed base's root at the origin (documented); ``Articulation.model_base`` is the
    MJCF's pose of it, so ``poses(joints, art.model_base)`` gives MuJoCo's centres of mass and inertia frames (an
    arm declared at z = 1 and posed with the default started inside its floor)."""
    import mujoco

    from cfd_torch.rotation import rotation_matrix

    xml = """<mujoco><worldbody><body name="base" pos="0.2 -0.1 1" euler="0 0 30"><geom type="sphere" size="0.05"/>
      <body name="arm"><joint name="j" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
    art = articulation(xml)
    assert torch.allclose(
        art.model_base, torch.tensor([0.2, -0.1, 1.0, 0.0, 0.0, math.radians(30)], dtype=F64)
    )
    rows = art.poses(torch.tensor([0.4], dtype=F64), art.model_base)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = [0.4]
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(rows[:, :3].numpy(), d.xipos[1:], rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        rotation_matrix(rows[:, 3:]).numpy(), d.ximat[1:].reshape(-1, 3, 3), atol=1e-12
    )


def test_a_link_with_a_mesh_geom_rests_where_the_same_link_built_of_a_box_does():
    """An arm whose bob is a mesh geom (a cube given by its 8 vertices, MuJoCo's hull of them) swings down onto a
    table and comes to rest where the same arm with a box geom does: the mesh's triangles collide and its mass
    properties equal the box's (to MuJoCo's float32 vertices); the two triangulations of the cube differ, so the
    rest poses agree to the contact's scale (6e-6 m measured), not to rounding."""
    cube = " ".join(f"{x} {y} {z}" for z in (-0.05, 0.05) for y in (-0.05, 0.05) for x in (-0.05, 0.05))
    xml = f"""<mujoco><compiler angle="radian"/><asset><mesh name="cube" vertex="{cube}"/></asset>
      <worldbody><body name="base" pos="0 0 0.5"><geom type="box" size=".03 .03 .03"/>
        <body name="arm"><joint name="j" axis="0 1 0" damping="0.5"/>
          <geom type="capsule" fromto="0 0 0 .4 0 0" size=".01"/>{{bob}}</body></body></worldbody></mujoco>"""
    ends = {}
    for kind, bob in (("mesh", '<geom type="mesh" mesh="cube" pos=".45 0 0"/>'), ("box", '<geom size=".05 .05 .05" '
                      'type="box" pos=".45 0 0"/>')):  # fmt: skip
        assert [g.kind for g in load_mjcf(xml.format(bob=bob)).links[1].geoms] == ["capsule", kind]
        arm = articulation(xml.format(bob=bob))
        table = rigid_body(trimesh.creation.box((0.4, 0.4, 0.3)), kind="static")  # its top at z = 0.15
        scene = Scene([table], articulations=[arm], dt=0.01)
        rows = arm.poses(torch.zeros(1, dtype=F64), torch.tensor([0, 0, 0.5, 0, 0, 0], dtype=F64))
        q = torch.cat([torch.tensor([[0.45, 0.0, 0.0, 0, 0, 0]], dtype=F64), rows])
        traj = rollout(scene, State(q, q), [Action(ctrl=torch.zeros(0, dtype=F64))] * 80)
        ends[kind] = traj.q[-1, 2]
        assert abs(float(traj.q[-1, 2, 2] - traj.q[-2, 2, 2])) < 1e-6  # at rest
        assert float(traj.q[-1, 2, 2]) > 0.15 + 0.05 * 0.9  # on the table, not through it
    mesh_arm, box_arm = (
        load_mjcf(xml.format(bob=b)).links[1]
        for b in (
            '<geom type="mesh" mesh="cube" pos=".45 0 0"/>',
            '<geom size=".05 .05 .05" type="box" pos=".45 0 0"/>',
        )
    )
    assert mesh_arm.mass == pytest.approx(box_arm.mass, rel=1e-7)
    np.testing.assert_allclose(mesh_arm.second_moment, box_arm.second_moment, rtol=0, atol=1e-7)
    torch.testing.assert_close(ends["mesh"], ends["box"], rtol=0, atol=2e-5)
