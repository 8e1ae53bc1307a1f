"""A task's scene in MuJoCo, stepped with the task's own actions and scored with its own reward terms.

The baseline "MuJoCo with finite differences" of the paper's experiments needs the same task in MuJoCo: same meshes,
masses, friction, gravity and action semantics, with only the contact model (and integrator) different.
:class:`MujocoTwin` builds that model from a :class:`~cfd_torch.envs.core.TaskCore`'s scene, for the tasks made of
rigid bodies (Billiards, Push, Sort, Gather; not AntPush's articulated Ant):

- every body's own triangle mesh (its hierarchy's body-frame vertices and faces) as a collision mesh geom (MuJoCo
  collides the meshes' convex hulls; every mesh of these tasks is convex); dynamic bodies with their mass (MuJoCo
  takes the inertia of the mesh's volume, like the simulator) and a free joint, or, in a planar scene, slide joints
  along x and y and a hinge about z (in the horizontal plane of the state's pose); static bodies as mocap bodies
  placed at the state's poses;
- Coulomb friction ``scene.friction.coefficient`` on every geom (torsional and rolling friction off; ``condim`` 1,
  frictionless, when the coefficient is 0), the scene's gravity, MuJoCo's default soft contacts, several contact
  points per pair of meshes (``multiccd``);
- the time step: each task step is ``substeps`` MuJoCo steps of dt / substeps (semi-implicit Euler), during
  which the task's action holds: the core's own ``_action`` (forces and torques at the centres of mass, computed
  from the poses at the start of the step and one step earlier, e.g. the pushers' PD law) goes to
  ``data.xfrc_applied``;
- the score: the core's ``reward_terms`` on the MuJoCo poses after each step.

    twin = MujocoTwin(make_core("cfd_torch/Push-v0"))
    state = core.reset(seed=0, batch_size=1)
    distances = twin.rollout(state, actions)         # (T,) the task's distance after each step [m]
    xml = twin.xml()                                 # the MJCF
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from cfd_torch.rotation import quaternion, quaternion_multiply, rotation_matrix, rotation_vector

from .core import EnvState, TaskCore

__all__ = ["MujocoTwin"]


class MujocoTwin:
    """MuJoCo model of ``core``'s scene (module docstring).

    Args:
        core: a task core whose scene has only rigid bodies (dynamic or static).
        substeps: MuJoCo steps per task step (default 10: 1 ms at the tasks' dt = 0.01 s).

    Raises:
        ValueError: an articulated or kinematic body in the scene, or substeps < 1.
    """

    def __init__(self, core: TaskCore, substeps: int = 10) -> None:
        scene = core.scene
        if scene.articulations:
            raise ValueError(
                "core: MujocoTwin takes scenes of rigid bodies only (this one has articulations)"
            )
        if any(b.kind == "kinematic" for b in scene.bodies):
            raise ValueError(
                "core: MujocoTwin takes dynamic and static bodies only (this scene has kinematic ones)"
            )
        if not (isinstance(substeps, int) and substeps >= 1):
            raise ValueError(f"substeps must be an int >= 1, got {substeps!r}")
        self.core, self.substeps = core, substeps
        self.planar = bool(scene.planar)
        mu = float(scene.friction.coefficient)
        spec = mujoco.MjSpec()
        spec.option.timestep = scene.dt / substeps
        spec.option.gravity = list(scene.gravity)
        # several contact points per pair of convex meshes (one, by default, lets a box on a floor rock and sink)
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_MULTICCD
        self._bodies = []  # MuJoCo body id of each scene body
        for i, body in enumerate(scene.bodies):
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
            if not static:
                geom.mass = float(body.mass)
        self.spec = spec
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._dynamic = [i for i, b in enumerate(scene.bodies) if b.kind != "static"]
        self._static = [i for i, b in enumerate(scene.bodies) if b.kind == "static"]
        self._body_id = [self.model.body(f"body{i}").id for i in range(len(scene.bodies))]
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
            # angular velocity of the rotation from the previous pose to this one, world frame
            R = rotation_matrix(q[i, 3:])
            conj = torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)
            w = rotation_vector(quaternion_multiply(quaternion(q[i, 3:]), conj * quaternion(qp[i, 3:]))) / dt
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
                d.qvel[va + 3 : va + 6] = (
                    R.T @ w
                ).numpy()  # MuJoCo: a free joint's angular velocity is local
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
        return q

    # ------------------------------------------------------------------------------------------------- rollout
    def rollout(self, state: EnvState, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The task's distance term after each of T steps from ``state`` (one environment) under ``actions``
        ((T, A) or (T, 1, A), in [-1, 1]): (T,) [m], the negated ``reward_distance`` of the core on MuJoCo's
        poses, and (T,) ``alive`` as in :func:`~cfd_torch.envs.rollout` (1 until and including the first step
        at which the core's ``terminated`` holds, then 0; the steps after it are still simulated)."""
        core = self.core
        if state.batch_size != 1:
            raise ValueError(
                f"state: MujocoTwin.rollout takes one environment, got a batch of {state.batch_size}"
            )
        a = actions.detach().double().reshape(actions.shape[0], -1)
        if a.shape[1] != core.action_dim:
            raise ValueError(
                f"actions must be (T, {core.action_dim}) or (T, 1, {core.action_dim}), got {tuple(actions.shape)}"
            )
        self._set_state(state)
        d = self.data
        cur = EnvState(state.q.detach().double(), state.q_prev.detach().double(), state.t, state.task)
        out = torch.empty(a.shape[0], dtype=torch.float64)
        alive = torch.ones(a.shape[0], dtype=torch.float64)
        done = False
        ids = np.array(self._body_id)
        for t in range(a.shape[0]):
            act = core._action(cur, a[t : t + 1])
            d.xfrc_applied[:] = 0.0
            if act.force is not None:
                d.xfrc_applied[ids, :3] = act.force[0].numpy()
            if act.torque is not None:
                d.xfrc_applied[ids, 3:] = act.torque[0].numpy()
            for _ in range(self.substeps):
                mujoco.mj_step(self.model, d)
            nxt = EnvState(self._poses(cur.q), cur.q, cur.t + 1, cur.task)
            out[t] = -core.reward_terms(cur, a[t : t + 1], nxt)["distance"][0]
            alive[t] = 0.0 if done else 1.0
            done = done or bool(core.terminated(nxt)[0])
            cur = nxt
        return out, alive
