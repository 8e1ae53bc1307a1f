"""A task's scene in MuJoCo, stepped with the task's own actions and scored with its own reward terms.

The baseline "MuJoCo with finite differences" of the paper's experiments needs the same task in MuJoCo: same meshes,
masses, friction, gravity and action semantics, with only the contact model (and integrator) different.
:class:`MujocoTwin` builds that model from a :class:`~cfd_torch.envs.core.TaskCore`'s scene, for every task:

- every body's own triangle mesh (its hierarchy's body-frame vertices and faces) as a collision mesh geom (MuJoCo
  collides the meshes' convex hulls; every mesh of these tasks is convex); dynamic bodies with their mass (MuJoCo
  takes the inertia of the mesh's volume, like the simulator) and a free joint, or, in a planar scene, slide joints
  along x and y and a hinge about z (in the horizontal plane of the state's pose); static bodies as mocap bodies
  placed at the state's poses;
- an articulated robot (AntPush's Ant; at most one per scene, on a floating base) from the MJCF the core built it
  from (``core.mjcf``) as MuJoCo reads it: its joints, limits, damping, armature, actuators (motors or position
  servos), geoms (MuJoCo's own capsules, not the simulator's meshes of them), contact filters, margins, friction
  and integrator (Gymnasium's Ant: RK4); the MJCF's worldbody geoms (the Ant's floor plane) are switched off, the
  scene's own static bodies take their place; the robot's state goes over as its base pose and joint angles;
- Coulomb friction ``scene.friction.coefficient`` on every geom, in MuJoCo's elliptic (isotropic) cone (torsional
  and rolling friction off; ``condim`` 1, frictionless, when the coefficient is 0), the scene's gravity, MuJoCo's
  default soft contacts, several contact points per pair of meshes (``multiccd``);
- the time step: each task step is ``substeps`` MuJoCo steps of dt / substeps (semi-implicit Euler unless the
  robot's MJCF says otherwise), during which the task's action holds: the core's own ``_action`` (forces and
  torques at the centres of mass, computed from the poses at the start of the step and one step earlier, e.g. the
  pushers' PD law) goes to ``data.xfrc_applied``, its actuator controls (``Action.ctrl``) to ``data.ctrl``;
- the score: the core's ``reward_terms`` on the MuJoCo poses after each step.

    core = make_core("cfd_torch/Push-v0")
    twin = MujocoTwin(core)
    state = core.reset(seed=0, batch_size=1)
    actions = torch.zeros(50, core.action_dim, dtype=torch.float64)  # (T, A) or (T, 1, A), in [-1, 1]
    distances, alive = twin.rollout(state, actions)  # (T,) the task's distance after each step [m], (T,) alive
    nxt, physics, distance, done = twin.step(state, actions[0])  # one step; MuJoCo's exact state after it
    distances, _ = twin.rollout(nxt, actions[1:], physics)       # continues from that state bit for bit
    xml = twin.xml()                                 # the MJCF
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from cfd_torch._validate import is_int
from cfd_torch.rotation import quaternion, quaternion_multiply, rotation_matrix, rotation_vector

from .core import EnvState, TaskCore

__all__ = ["MujocoTwin"]


class MujocoTwin:
    """MuJoCo model of ``core``'s scene (module docstring).

    Args:
        core: a task core whose scene has dynamic and static rigid bodies and at most one articulation, a floating
            robot that is not kinematic (its MJCF in ``core.mjcf``).
        substeps: MuJoCo steps per task step (default 10: 1 ms at the tasks' dt = 0.01 s).

    Raises:
        ValueError: a kinematic body, more than one articulation or one that is kinematic or has a fixed base, a
            missing MJCF, or substeps < 1.
    """

    def __init__(self, core: TaskCore, substeps: int = 10) -> None:
        scene = core.scene
        arts = scene.articulations
        if len(arts) > 1 or any(a.kinematic or not a.floating for a in arts):
            raise ValueError(
                "core: MujocoTwin takes at most one articulation, a floating robot that is not kinematic"
            )
        if len(core.mjcf) != len(arts):
            raise ValueError(
                f"core.mjcf must hold the MJCF of each of the scene's {len(arts)} articulations, got "
                f"{len(core.mjcf)}"
            )
        if any(b.kind == "kinematic" for b in scene.bodies):
            raise ValueError(
                "core: MujocoTwin takes dynamic and static bodies only (this scene has kinematic ones)"
            )
        if not (is_int(substeps) and substeps >= 1):
            raise ValueError(f"substeps must be an int >= 1, got {substeps!r}")
        self.core, self.substeps = core, substeps
        self.planar = bool(scene.planar)
        mu = float(scene.friction.coefficient)
        spec = mujoco.MjSpec.from_string(core.mjcf[0]) if arts else mujoco.MjSpec()
        # the robot's own world geoms (a floor plane) give way to the scene's static bodies
        for g in spec.worldbody.geoms:
            g.contype, g.conaffinity, g.rgba = 0, 0, [0.0, 0.0, 0.0, 0.0]
        spec.option.timestep = scene.dt / substeps
        spec.option.gravity = list(scene.gravity)
        # several contact points per pair of convex meshes (one, by default, lets a box on a floor rock and sink)
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_MULTICCD
        # Coulomb's isotropic cone, as the scene's friction (MuJoCo's default pyramid bounds |f_x| + |f_y| in the
        # contact's own axes: a box sliding at 45 degrees to them met 0.74 of its friction, at 22.5 degrees a force
        # 7 degrees off its velocity); the Ant's MJCF leaves the cone at that default too
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
        # the articulation's state rows [first, first + L)
        self._art = arts[0] if arts else None
        first = scene.articulation_rows[0] if arts else 0
        self._art_rows = range(first, first + arts[0].num_links) if arts else range(0)
        for i, body in enumerate(scene.bodies):
            if i in self._art_rows:
                continue
            mesh = spec.add_mesh()
            mesh.name = f"mesh{i}"
            mesh.uservert = body.bsh.vertices.double().numpy().ravel().tolist()
            mesh.userface = body.bsh.faces.numpy().ravel().tolist()
            static = body.kind == "static"
            b = spec.worldbody.add_body(name=f"body{i}", mocap=static)
            if static:
                pass
            elif self.planar:
                for k, axis in enumerate(((1, 0, 0), (0, 1, 0))):
                    b.add_joint(name=f"body{i}_{'xy'[k]}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=list(axis))
                b.add_joint(name=f"body{i}_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1])
            else:
                b.add_freejoint(name=f"body{i}_free")
            geom = b.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name, condim=3 if mu > 0 else 1)
            geom.friction = [mu, 0.0, 0.0]
            # MuJoCo's defaults, whatever the robot's MJCF sets as its own (the Ant's: conaffinity 0, margin 1 cm)
            geom.contype, geom.conaffinity, geom.margin = 1, 1, 0.0
            if not static:
                geom.mass = float(body.mass)
        self.spec = spec
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        rigid = [i for i in range(len(scene.bodies)) if i not in self._art_rows]
        self._dynamic = [i for i in rigid if scene.bodies[i].kind != "static"]
        self._static = [i for i in rigid if scene.bodies[i].kind == "static"]
        names = {i: f"body{i}" for i in rigid}
        if arts:
            names.update(zip(self._art_rows, arts[0].names, strict=True))
        self._body_id = [self.model.body(names[i]).id for i in range(len(scene.bodies))]
        if arts:
            m = self.model
            root = m.body(arts[0].names[0]).id
            self._root_q = int(m.jnt_qposadr[m.body_jntadr[root]])
            self._root_v = int(m.jnt_dofadr[m.body_jntadr[root]])
            self._joint_q = np.array([m.joint(n).qposadr[0] for n in arts[0].joint_names])
            self._joint_v = np.array([m.joint(n).dofadr[0] for n in arts[0].joint_names])
            if m.nu != scene.num_actuators:
                raise ValueError(
                    f"core.mjcf: MuJoCo reads {m.nu} actuators, the scene has {scene.num_actuators}"
                )
        self._qadr = [
            int(self.model.jnt_qposadr[self.model.body_jntadr[self._body_id[i]]]) for i in self._dynamic
        ]
        self._vadr = [
            int(self.model.jnt_dofadr[self.model.body_jntadr[self._body_id[i]]]) for i in self._dynamic
        ]

    def xml(self) -> str:
        """The model as MJCF (meshes inline)."""
        return self.spec.to_xml()

    # ------------------------------------------------------------------------------------------- state transfer
    def _set_state(self, state: EnvState) -> None:
        d, dt = self.data, self.core.scene.dt
        mujoco.mj_resetData(self.model, d)
        q, qp = state.q[0].detach().double(), state.q_prev[0].detach().double()
        for i in self._static:
            mid = self.model.body_mocapid[self._body_id[i]]
            d.mocap_pos[mid] = q[i, :3].numpy()
            d.mocap_quat[mid] = quaternion(q[i, 3:]).numpy()
        for k, i in enumerate(self._dynamic):
            qa, va = self._qadr[k], self._vadr[k]
            v = ((q[i, :3] - qp[i, :3]) / dt).numpy()
            w = _angular_velocity(q[i, 3:], qp[i, 3:], dt)
            if self.planar:
                if bool((q[i, 3:5] != 0).any()):
                    raise ValueError(
                        f"state.q: body {i} of a planar scene is tilted (rotation vector {q[i, 3:]})"
                    )
                self.model.body_pos[self._body_id[i], 2] = float(q[i, 2])  # the plane it moves in
                d.qpos[qa : qa + 3] = [float(q[i, 0]), float(q[i, 1]), float(q[i, 5])]
                d.qvel[va : va + 3] = [v[0], v[1], float(w[2])]
            else:
                d.qpos[qa : qa + 3] = q[i, :3].numpy()
                d.qpos[qa + 3 : qa + 7] = quaternion(q[i, 3:]).numpy()
                d.qvel[va : va + 3] = v
                # MuJoCo: a free joint's angular velocity is local
                d.qvel[va + 3 : va + 6] = (rotation_matrix(q[i, 3:]).T @ w).numpy()
        if self._art is not None:
            rows = list(self._art_rows)
            c = self._art.coords(q[None, rows])[0]
            cp = self._art.coords(qp[None, rows], near=c[None])[0]  # the earlier state on the same branch
            qa, va = self._root_q, self._root_v
            d.qpos[qa : qa + 3] = c[:3].numpy()
            d.qpos[qa + 3 : qa + 7] = quaternion(c[3:6]).numpy()
            d.qpos[self._joint_q] = c[6:].numpy()
            d.qvel[va : va + 3] = ((c[:3] - cp[:3]) / dt).numpy()
            d.qvel[va + 3 : va + 6] = (
                rotation_matrix(c[3:6]).T @ _angular_velocity(c[3:6], cp[3:6], dt)
            ).numpy()
            turn = (
                torch.remainder(c[6:] - cp[6:] + torch.pi, 2 * torch.pi) - torch.pi
            )  # hinge angles wrap at pi
            d.qvel[self._joint_v] = (turn / dt).numpy()
        mujoco.mj_forward(self.model, d)

    def _poses(self, like: torch.Tensor) -> torch.Tensor:
        """(1, N, 6) the scene's poses now (static bodies from ``like``)."""
        q = like.detach().clone()
        d = self.data
        for k, i in enumerate(self._dynamic):
            qa = self._qadr[k]
            if self.planar:
                x, y, yaw = d.qpos[qa : qa + 3]
                z = self.model.body_pos[self._body_id[i], 2]
                q[0, i] = torch.tensor([x, y, z, 0.0, 0.0, yaw], dtype=q.dtype)
            else:
                q[0, i, :3] = torch.from_numpy(d.qpos[qa : qa + 3].copy())
                q[0, i, 3:] = rotation_vector(torch.from_numpy(d.qpos[qa + 3 : qa + 7].copy()))
        if self._art is not None:
            qa = self._root_q
            base = torch.cat(
                [
                    torch.from_numpy(d.qpos[qa : qa + 3].copy()),
                    rotation_vector(torch.from_numpy(d.qpos[qa + 3 : qa + 7].copy())),
                ]
            )
            joints = torch.from_numpy(d.qpos[self._joint_q].copy())
            q[0, list(self._art_rows)] = self._art.poses(joints, base).to(q.dtype)
        return q

    # ------------------------------------------------------------------------------------------------- rollout
    def rollout(
        self, state: EnvState, actions: torch.Tensor, physics: np.ndarray | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The task's distance term after each of T steps from ``state`` (one environment) under ``actions``
        ((T, A) or (T, 1, A), in [-1, 1]): (T,) [m], the negated ``reward_distance`` of the core on MuJoCo's
        poses, and (T,) ``alive`` as in :func:`~cfd_torch.envs.rollout` (1 until and including the first step
        at which the core's ``terminated`` holds, then 0; the steps after it are still simulated).

        MuJoCo starts from ``state``'s poses and their finite-difference velocities, or, with ``physics`` (what
        :meth:`step` returned with ``state``), from that exact MuJoCo state."""
        a = self._check_actions(actions)
        out = torch.empty(len(a), dtype=torch.float64)
        alive = torch.ones_like(out)
        done = False
        for t, (_, dist, term) in enumerate(self._steps(state, a, physics)):
            out[t] = dist
            alive[t] = 0.0 if done else 1.0
            done = done or term
        return out, alive

    def step(
        self, state: EnvState, action: torch.Tensor, physics: np.ndarray | None = None
    ) -> tuple[EnvState, np.ndarray, float, bool]:
        """One task step in MuJoCo from ``state`` (one environment; with ``physics``, from that MuJoCo state, as
        in :meth:`rollout`) under ``action`` ((A,) or (1, A)): the next state (MuJoCo's poses), MuJoCo's state
        after the step (``mj_getState``, ``mjSTATE_INTEGRATION``: what the next :meth:`step` or :meth:`rollout`
        continues from exactly), the task's distance term [m] and whether the task terminated."""
        A = self.core.action_dim
        if not isinstance(action, torch.Tensor):
            raise TypeError(f"action must be a torch tensor, got {type(action).__name__}")
        if tuple(action.shape) not in ((A,), (1, A)):
            raise ValueError(f"action must be ({A},) or (1, {A}), got {tuple(action.shape)}")
        ((nxt, dist, term),) = list(self._steps(state, self._check_actions(action.reshape(1, A)), physics))
        # in the core's dtype and device, so that the core can step on from it
        return self.core._to(nxt), self._get_physics(), dist, term

    # ------------------------------------------------------------------------------------------------ internals
    def _check_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """(T, A) float64 ``actions``, checked for shape and finiteness."""
        A = self.core.action_dim
        if not isinstance(actions, torch.Tensor):
            raise TypeError(f"actions must be a torch tensor, got {type(actions).__name__}")
        if tuple(actions.shape[1:]) not in ((A,), (1, A)):
            raise ValueError(
                f"actions must be (T, {A}) or (T, 1, {A}), got {tuple(getattr(actions, 'shape', ()))}"
            )
        a = actions.detach().double().reshape(actions.shape[0], A)
        if not bool(torch.isfinite(a).all()):
            first = int(torch.nonzero(~torch.isfinite(a))[0, 0])
            raise ValueError(f"actions contain NaN or inf (first at step {first})")
        return a

    def _get_physics(self) -> np.ndarray:
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        out = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, out, spec)
        return out

    def _set_physics(self, state: EnvState, physics: np.ndarray) -> None:
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        size = mujoco.mj_stateSize(self.model, spec)
        if not isinstance(physics, np.ndarray) or physics.shape != (size,):
            raise ValueError(
                f"physics must be a ({size},) array from MujocoTwin.step, got {getattr(physics, 'shape', physics)!r}"
            )
        if self.planar:  # the plane each body moves in is a model field, not part of MuJoCo's state
            for i in self._dynamic:
                self.model.body_pos[self._body_id[i], 2] = float(state.q[0, i, 2])
        # no mj_forward: it would overwrite the warm start of the constraint solver that the next mj_step reads
        mujoco.mj_setState(self.model, self.data, physics.astype(np.float64), spec)
        q = state.q.detach().double()
        gap = float((self._poses(q) - q).abs().max())
        # (a float32 state holds MuJoCo's poses rounded to float32)
        tol = (
            1e-9
            if state.q.dtype == torch.float64
            else 2 * torch.finfo(state.q.dtype).eps * max(1.0, float(q.abs().max()))
        )
        if gap > tol:
            raise ValueError(f"physics does not hold state's poses (they differ by {gap:.3g})")

    def _steps(self, state: EnvState, a: torch.Tensor, physics: np.ndarray | None):
        """Yield (next state, distance term [m], terminated) after each step of the checked actions ``a`` (T, A)
        from ``state``."""
        core = self.core
        if state.batch_size != 1:
            raise ValueError(
                f"state: MujocoTwin.rollout takes one environment, got a batch of {state.batch_size}"
            )
        if physics is None:
            self._set_state(state)
        else:
            self._set_physics(state, physics)
        d = self.data
        cur = EnvState(state.q.detach().double(), state.q_prev.detach().double(), state.t, state.task)
        ids = np.array(self._body_id)
        for t in range(a.shape[0]):
            act = core._action(cur, a[t : t + 1].clamp(-1.0, 1.0))  # (as TaskCore.step clips them)
            d.xfrc_applied[:] = 0.0
            if act.force is not None:
                d.xfrc_applied[ids, :3] = act.force[0].numpy()
            if act.torque is not None:
                d.xfrc_applied[ids, 3:] = act.torque[0].numpy()
            if act.ctrl is not None:
                d.ctrl[:] = act.ctrl.detach().reshape(-1, self.model.nu)[0].double().numpy()
            for _ in range(self.substeps):
                mujoco.mj_step(self.model, d)
            nxt = EnvState(self._poses(cur.q), cur.q, cur.t + 1, cur.task)
            yield (
                nxt,
                float(-core.reward_terms(cur, a[t : t + 1], nxt)["distance"][0]),
                bool(core.terminated(nxt)[0]),
            )
            cur = nxt


def _angular_velocity(r: torch.Tensor, r_prev: torch.Tensor, dt: float) -> torch.Tensor:
    """(3,) world-frame angular velocity of the rotation from rotation vector ``r_prev`` to ``r`` over ``dt``."""
    conj = torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=r.dtype)
    return rotation_vector(quaternion_multiply(quaternion(r), conj * quaternion(r_prev))) / dt
