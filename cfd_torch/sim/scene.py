"""A simulation's model: its bodies, time step, gravity and the three config objects, with the layout the step
needs computed once (which bodies are simulated, which pairs interact, the kinematics map, the contact model)."""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch

from .._validate import (
    FLOATS,
    body_pair,
    check_pair_eps,
    check_pair_mu,
    closed_surface,
    is_real,
    usable_device,
)
from ..config import ContactConfig, FrictionConfig, SolverConfig, with_potential
from ..contact._traverse import build_forest
from ..contact.bsh import BSH
from ..contact.cfd import CfdContact
from ..contact.ipc import IpcContact
from ..contact.model import ContactModel
from ..contact.scene import body_pairs
from ..contact.sdrs import SdrsContact
from ._checks import check_pose_range, check_state_tensor
from .articulation import ArticulatedKinematics, Articulation
from .bodies import RigidBody, inner_radius, refine_obstacles, thickness
from .kinematics import FreeBodies
from .rest import warn_hovering
from .types import Params, State

__all__ = ["Scene"]

_MIN_DT = 1e-12  # [s]: below it a step's motion is at float64's rounding of the positions

# shorthand keywords of Scene(...) and the config field each one sets
_SHORTHAND = {
    "mu": ("contact", "stiffness"),
    "margin": ("contact", "margin"),
    "eps": ("contact", "eps"),
    "split": ("contact", "split"),
    "pair_tol": ("contact", "pair_tol"),
    "pair_max_iter": ("contact", "pair_max_iter"),
    "backend": ("contact", "backend"),
    "refine_obstacles": ("contact", "refine_obstacles"),
    "potential": ("contact", "potential"),
    "dhat": ("contact", "dhat"),
    "barrier_stiffness": ("contact", "barrier_stiffness"),
    "friction_eps_v": ("friction", "eps_v"),
    "friction_active": ("friction", "active"),
    "newton_tol": ("solver", "newton_tol"),
    "max_newton_iter": ("solver", "max_newton_iter"),
    "ccd_spacing": ("solver", "ccd_spacing"),
    "reach_shrink": ("solver", "reach_shrink"),
    "substeps": ("solver", "substeps"),
    "fast": ("solver", "fast"),
}


def _gravity(gravity: object) -> tuple[float, float, float]:
    """``gravity`` as 3 finite floats; a clear error naming it otherwise (its gradient is not kept: refused)."""
    if isinstance(gravity, (str, bytes)) or not isinstance(gravity, Iterable):
        raise TypeError(f"gravity must be 3 numbers, got {gravity!r}")
    if isinstance(gravity, torch.Tensor) and gravity.shape != (3,):
        raise ValueError(f"gravity must be 3 finite numbers, got a tensor of shape {tuple(gravity.shape)}")
    items = list(gravity)
    if any(isinstance(x, torch.Tensor) and x.requires_grad for x in items) or (
        isinstance(gravity, torch.Tensor) and gravity.requires_grad
    ):
        raise TypeError(
            "gravity must be numbers, not a tensor that requires grad: a scene's gravity is not differentiable"
        )
    if any(
        isinstance(x, (bool, np.bool_)) or (isinstance(x, torch.Tensor) and x.dtype == torch.bool)
        for x in items
    ):
        raise TypeError(f"gravity must be 3 numbers, got {gravity!r} (bools)")
    try:
        g = tuple(float(x) for x in items)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"gravity must be 3 numbers, got {gravity!r}") from err
    if len(g) != 3 or not all(math.isfinite(x) for x in g):
        raise ValueError(f"gravity must be 3 finite numbers, got {gravity!r}")
    return g


def _check_contact_model(model: object, bodies: Sequence[RigidBody]) -> None:
    """A given contact model implements :class:`ContactModel` and was built for these bodies, in this order (its
    ``num_bodies``, and the hierarchies of the built-in models)."""
    if not isinstance(model, ContactModel):
        raise TypeError(
            f"contact_model must implement cfd_torch.contact.ContactModel, got {type(model).__name__} (to choose a "
            "built-in model, pass potential='cfd', 'ipc' or 'sdrs')"
        )
    n = getattr(model, "num_bodies", len(bodies))
    if n != len(bodies):
        raise ValueError(f"contact_model was built for {n} bodies, the scene has {len(bodies)}")
    for i, (mine, body) in enumerate(zip(getattr(model, "bshes", ()), bodies, strict=False)):
        if mine is not body.bsh and not _same_surface(mine, body.bsh):
            raise ValueError(
                f"contact_model's hierarchy {i} is not body {i}'s surface: build it from the scene's bodies' "
                "hierarchies (refined or not), in the scene's order"
            )


def _same_surface(a: BSH, b: BSH) -> bool:
    """Whether two hierarchies hold the same surface, one possibly a refinement of the other (midpoint splits keep
    the surface): the same bounding box and area, to rounding."""
    box_a = torch.stack([a.vertices.amin(0), a.vertices.amax(0)]).double()
    box_b = torch.stack([b.vertices.amin(0), b.vertices.amax(0)]).double()
    scale = float(box_a.abs().max()) + 1e-300

    def area(h: BSH) -> float:
        t = h.triangles.double()
        return float(0.5 * torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).norm(dim=-1).sum())

    return bool((box_a - box_b).abs().max() <= 1e-9 * scale) and math.isclose(area(a), area(b), rel_tol=1e-9)


# the constructor's arguments other than the bodies, each kept as the attribute of its name (the contact model
# given as ``_given_contact_model``): what ``Scene.replace`` carries over
_REPLACEABLE = (
    "dt", "gravity", "contact", "friction", "solver", "exclude", "pair_eps", "pair_mu", "contact_model",
    "articulations", "planar",
)  # fmt: skip


class Scene:
    """Bodies and every physical and numerical setting of a simulation.

    Args:
        bodies: the N bodies (:func:`cfd_torch.rigid_body`), in state order.
        dt: time step [s], at least 1e-12.
        gravity: (3,) gravitational acceleration [m/s^2].
        contact: the contact potential's settings (default ``ContactConfig()``).
        friction: a :class:`FrictionConfig`, or Coulomb's coefficient alone (default 0: off, unless a step's
            ``Params.friction`` says otherwise: the coefficient is its default).
        solver: the Newton solve's settings (default ``SolverConfig()``).
        exclude: body pairs (i, j) with no contact between them (e.g. joined bodies).
        pair_eps: body pairs (i, j) whose blend width (``ContactConfig.eps``) is their own, {(i, j): eps}: e.g. a
            wide band between a pusher and the boxes it should find, whose far field is then one smooth slope,
            while the boxes' contact with the floor keeps the narrow default (a wide band there only costs leaf
            pairs). This library's potential only: with a baseline ``potential`` or a ``contact_model`` it raises
            ValueError (they have no blend).
        pair_mu: body pairs (i, j) whose contact stiffness (``ContactConfig.stiffness``, ``mu``) is their own,
            {(i, j): mu}: e.g. a lower stiffness between a small, light body and the floor (the default stiffness
            leaves centimetre bodies of grams hovering millimetres to centimetres up, with a
            :class:`~cfd_torch.RestGapWarning`; :func:`cfd_torch.stiffness_for_rest_gap` gives the value) beside
            decimetre bodies that keep the default. This library's potential only, like ``pair_eps``.
        articulations: robots (:func:`cfd_torch.sim.articulation.articulation`); their links are the state rows
            after ``bodies``, each robot's consecutive (``articulation_rows``), with no contact between two links
            of one robot.
        contact_model: a :class:`cfd_torch.contact.ContactModel` built for these bodies (default: the one
            ``contact.potential`` names, with ``contact``'s settings).
        planar: the dynamic bodies move in their horizontal planes and turn about the vertical only: the step
            solves for each one's x, y and yaw, and keeps its height, roll and pitch (which must be zero) from the
            start state (:class:`~cfd_torch.sim.kinematics.FreeBodies`). For table-top scenes such as billiards:
            no table is needed and no contact can lift a body out of its plane. Not with articulations.
        **shorthand: a config field by a flat name, e.g. ``mu`` (``contact.stiffness``), ``margin``, ``eps``,
            ``split``, ``pair_tol``, ``pair_max_iter``, ``backend``, ``refine_obstacles``, ``potential`` ("cfd", "ipc"
            or "sdrs": the contact potential), ``dhat``, ``barrier_stiffness``, ``friction_eps_v``
            (``friction.eps_v``), ``friction_active``, ``newton_tol``, ``max_newton_iter``, ``ccd_spacing``,
            ``reach_shrink``, ``substeps``, ``fast``; it overrides that field of a config given as well.

    A scene is read-only once built (its contact model, pairs and tables are built from its settings): assigning
    an attribute raises AttributeError; :meth:`replace` builds one with other settings.

    Attributes (computed once): ``bodies`` as simulated (static and kinematic bodies coarser than the dynamic
    bodies they touch are refined, ``ContactConfig.refine_obstacles``, unless a ``contact_model`` is given),
    ``dynamic`` (Nd,), ``kinematic`` (K,) and ``static_mask`` (N,) of the bodies, ``num_kinematic_bodies`` (the
    kinematic rigid bodies, ``Action.target``'s rows), ``articulation_rows`` (each robot's first state row),
    ``pairs`` (P, 2) the interacting body pairs (at least one dynamic body, not excluded), ``kinematics`` the map
    from the step's unknowns to poses, ``contact_model`` (given, or built from ``contact``; ``contact`` is then
    the model's own ``config``, or the defaults for a model without one), ``path_spacing`` [m] the largest vertex
    displacement between two samples of the no-tunnelling path checks (``ccd_spacing``, or half the thinnest
    moving body's thickness plus the contact margin where that is less), ``inner_radius`` (N,) [m] each dynamic
    body's largest ball about its centre of mass inside its solid (0 for an open surface, a centre of mass outside
    the solid, and the other bodies), which the end-of-step check refuses another body's centre to pass through.
    """

    def __init__(
        self,
        bodies: Sequence[RigidBody],
        *,
        dt: float = 0.01,
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        contact: ContactConfig | None = None,
        friction: FrictionConfig | float | None = None,
        solver: SolverConfig | None = None,
        exclude: Sequence[tuple[int, int]] = (),
        pair_eps: Mapping[tuple[int, int], float] | None = None,
        pair_mu: Mapping[tuple[int, int], float] | None = None,
        contact_model: ContactModel | None = None,
        articulations: Sequence[Articulation] = (),
        planar: bool = False,
        **shorthand: float | int | str,
    ) -> None:
        if isinstance(bodies, RigidBody) or not isinstance(bodies, Iterable):
            raise TypeError(f"bodies must be a sequence of RigidBody, got {type(bodies).__name__}")
        bodies = tuple(bodies)
        self._given_bodies = bodies  # as given (before obstacle refinement): what ``replace`` rebuilds from
        arts = tuple(articulations)
        if not all(isinstance(a, Articulation) for a in arts):
            raise TypeError(
                "articulations must be a sequence of Articulation (see cfd_torch.sim.articulation)"
            )
        wrong = [i for i, b in enumerate(bodies) if not isinstance(b, RigidBody)]
        if wrong:  # (a ValueError, as it always was, so that code catching it keeps working)
            raise ValueError(
                f"bodies must be a sequence of RigidBody (see cfd_torch.rigid_body), got "
                f"{type(bodies[wrong[0]]).__name__} at index {wrong[0]}"
            )
        if not (bodies or arts):
            raise ValueError("bodies must be a non-empty sequence of RigidBody (see cfd_torch.rigid_body)")
        self.articulations = arts
        #: how many of ``bodies`` are kinematic (``Action.target``'s rows; kinematic robots' links come after them)
        self.num_kinematic_bodies = sum(b.kind == "kinematic" for b in bodies)
        rows, first = len(bodies), []
        robot_pairs = []
        for a in arts:
            first.append(rows)
            robot_pairs += [
                (rows + i, rows + j) for i in range(a.num_links) for j in range(i + 1, a.num_links)
            ]
            bodies = bodies + a.bodies
            rows += a.num_links
        #: the first state row of each articulation
        self.articulation_rows = tuple(first)
        if not any(b.kind == "dynamic" for b in bodies):
            raise ValueError("a scene needs at least one dynamic body")
        if not is_real(dt):
            raise ValueError(f"dt must be a real number (a Python or NumPy float), got {type(dt).__name__}")
        if not _MIN_DT <= dt < math.inf:
            raise ValueError(
                f"dt must be a finite number of at least {_MIN_DT:g} s (a shorter step loses the motion to float64 "
                f"rounding, and 1/dt^2 overflows below 1e-154), got {dt!r}"
            )
        gravity = _gravity(gravity)
        if is_real(friction):
            friction = FrictionConfig(coefficient=float(friction))
        for name, value, kind in (
            ("contact", contact, ContactConfig),
            ("friction", friction, FrictionConfig),
            ("solver", solver, SolverConfig),
        ):
            if value is not None and not isinstance(value, kind):
                what = " or a number (the coefficient)" if name == "friction" else ""
                raise TypeError(f"{name} must be a {kind.__name__}{what} or None, got {type(value).__name__}")
        cfg = {
            "contact": contact or ContactConfig(),
            "friction": friction or FrictionConfig(),
            "solver": solver or SolverConfig(),
        }
        updates: dict[str, dict] = {"contact": {}, "friction": {}, "solver": {}}
        for key, value in shorthand.items():
            if key not in _SHORTHAND:
                raise TypeError(f"Scene() got an unexpected keyword argument {key!r}")
            which, name = _SHORTHAND[key]
            updates[which][name] = value
        for which, kw in updates.items():
            if kw:
                cfg[which] = dataclasses.replace(cfg[which], **kw)  # validates
        self.dt = float(dt)
        self.gravity = gravity
        self.contact: ContactConfig = cfg["contact"]
        self.friction: FrictionConfig = cfg["friction"]
        self.solver: SolverConfig = cfg["solver"]
        if isinstance(exclude, (str, bytes)) or not isinstance(exclude, Iterable):
            raise TypeError(f"exclude must be a sequence of body pairs (i, j), got {exclude!r}")
        self.exclude = tuple(body_pair(p, "exclude") for p in exclude)
        N = len(bodies)
        self.pair_eps = check_pair_eps(pair_eps, N)
        self.pair_mu = check_pair_mu(pair_mu, N)
        if contact_model is not None:  # its settings are the model's own (its ``config``, else the defaults)
            own = getattr(contact_model, "config", None)
            own = own if isinstance(own, ContactConfig) else ContactConfig()
            if self.contact not in (ContactConfig(), own):
                changed = [
                    f.name
                    for f in dataclasses.fields(ContactConfig)
                    if getattr(self.contact, f.name) != getattr(own, f.name)
                ]
                raise ValueError(
                    "contact settings (contact=, or shorthand such as margin= or mu=) beside a contact_model must "
                    "be the model's own (its config, or the defaults for a model without one): leave them out "
                    f"(these differ: {', '.join(changed)})"
                )
            self.contact = own
        if self.pair_eps and (contact_model is not None or self.contact.potential != "cfd"):
            raise ValueError(
                "pair_eps sets blend widths of this library's potential; the contact model "
                + ("given" if contact_model is not None else f"potential={self.contact.potential!r}")
                + " has no blend: leave pair_eps out (Scene.replace carries it over: replace(..., pair_eps=None))"
            )
        if self.pair_mu and (contact_model is not None or self.contact.potential != "cfd"):
            raise ValueError(
                "pair_mu sets stiffnesses of this library's potential; the contact model "
                + ("given" if contact_model is not None else f"potential={self.contact.potential!r}")
                + " has its own: leave pair_mu out (Scene.replace carries it over: replace(..., pair_mu=None))"
            )
        #: every body pair without contact: ``exclude`` and the pairs of links of one robot
        self.no_contact = self.exclude + tuple(robot_pairs)
        pairs = body_pairs(N, torch.tensor([b.kind != "dynamic" for b in bodies]), self.no_contact)
        for name, table, what in (
            ("pair_eps", self.pair_eps, "blend width"),
            ("pair_mu", self.pair_mu, "stiffness"),
        ):
            for i, j in table:
                if not bool((pairs == torch.tensor([min(i, j), max(i, j)])).all(1).any()):
                    raise ValueError(
                        f"{name}: {(i, j)} is a pair without contact (neither body is dynamic, or the pair is "
                        f"excluded or two links of one robot): its {what} would never be used"
                    )
        if (
            self.contact.refine_obstacles is not None
            and contact_model is None
            and self.contact.potential == "cfd"
        ):
            bodies = refine_obstacles(bodies, pairs, self.contact.refine_obstacles)
        self.bodies = bodies
        if contact_model is None:  # (robots' links hang from their joints: not theirs to rest)
            warn_hovering(
                bodies[: len(bodies) - sum(a.num_links for a in arts)],
                self.contact,
                gravity,
                planar,
                self.pair_mu,
            )
        self.dynamic = torch.tensor(
            [i for i, b in enumerate(bodies) if b.kind == "dynamic"], dtype=torch.long
        )
        self.kinematic = torch.tensor(
            [i for i, b in enumerate(bodies) if b.kind == "kinematic"], dtype=torch.long
        )
        self.static_mask = torch.tensor([b.kind == "static" for b in bodies])
        self.pairs = pairs
        if not isinstance(planar, bool) or (planar and arts):
            raise ValueError(f"planar must be a bool, and False with articulations; got {planar!r}")
        self.planar = planar
        moving = [(a, r) for a, r in zip(arts, first, strict=True) if not a.kinematic]
        #: the kinematic robots and their first rows (their links are posed by ``Action.joints``)
        self.kinematic_articulations = tuple((a, r) for a, r in zip(arts, first, strict=True) if a.kinematic)
        if moving:
            links = {r + k for a, r in moving for k in range(a.num_links)}
            free = torch.tensor([int(i) for i in self.dynamic if int(i) not in links], dtype=torch.long)
            self.kinematics = ArticulatedKinematics(free, [a for a, _ in moving], [r for _, r in moving], N)
        else:
            self.kinematics = FreeBodies(self.dynamic, N, planar)
        self._given_contact_model = contact_model
        if contact_model is not None:
            _check_contact_model(contact_model, bodies)
            self.contact_model = contact_model
        elif self.contact.potential != "cfd":
            c = self.contact
            kappa = {} if c.barrier_stiffness is None else {"stiffness": c.barrier_stiffness}
            bshes = [b.bsh for b in bodies]
            self.contact_model = (
                IpcContact(bshes, c.dhat, **kappa) if c.potential == "ipc"
                else SdrsContact(bshes, c.dhat, margin=c.margin, **kappa)
            )  # fmt: skip
        else:
            self.contact_model = CfdContact(
                [b.bsh for b in bodies], self.contact, self.pair_eps, self.pair_mu
            )
        # farthest vertex of each body from its frame origin: bounds vertex displacements
        self.extent = torch.tensor(
            [float(b.bsh.vertices.norm(dim=1).max()) for b in bodies], dtype=torch.float64
        )
        #: [m] the spacing of the path checks' samples (moves of the iterate, kinematic sweeps, reachability):
        #: ccd_spacing, or half the thickness plus margins of the thinnest moving body where that is less; a body
        #: is within the margin of a surface it crosses over a displacement of at least its thickness plus two
        #: margins, so a sample lands on the crossing (a 5 mm ball fell through a 10 cm floor between samples 1 cm
        #: apart; a flat kinematic sheet gets samples a margin apart, which every path check then pays for)
        moving = {
            id(b.bsh): b.bsh for b in bodies if b.kind != "static"
        }.values()  # (shared hierarchies once)
        margin = getattr(self.contact_model, "margin", self.contact.margin)  # IPC's: 1e-6 dhat
        self.path_spacing = min(
            [self.solver.ccd_spacing]
            + [0.5 * thickness(t.vertices.numpy(), t.faces.numpy()) + margin for t in moving]
        )
        # which bodies are closed, consistently wound surfaces, and their hierarchies in one node table (CPU,
        # float64; each body's root ``probe_root``): the start-of-step check that no body lies wholly inside another
        uniq: dict[int, int] = {}
        for b in bodies:
            uniq.setdefault(id(b.bsh), len(uniq))
        trees = tuple({id(b.bsh): b.bsh for b in bodies}.values())
        shut = [closed_surface(t.vertices.numpy(), t.faces.numpy()) for t in trees]
        self.closed = torch.tensor([shut[uniq[id(b.bsh)]] for b in bodies], dtype=torch.bool)
        # [m] each moving body's largest ball about its centre of mass inside its solid (0 for the others): the
        # reachability check refuses a step in which another body's centre of mass passes through it
        inner = {
            id(b.bsh): inner_radius(b.bsh.vertices.numpy(), b.bsh.faces.numpy())
            for b in bodies
            if b.kind == "dynamic" and shut[uniq[id(b.bsh)]]
        }
        self.inner_radius = torch.tensor([inner.get(id(b.bsh), 0.0) for b in bodies], dtype=torch.float64)
        self.probe_forest = build_forest(trees, torch.float64, torch.device("cpu")) if any(shut) else None
        self.probe_root = (
            self.probe_forest.roots[torch.tensor([uniq[id(b.bsh)] for b in bodies])]
            if self.probe_forest is not None
            else None
        )
        self._built = True

    def __setattr__(self, name: str, value: object) -> None:
        if self.__dict__.get("_built", False):
            hint = (
                f"scene.replace({name}=...) builds one with it changed"
                if name in _REPLACEABLE or name in _SHORTHAND
                else "scene.replace(...) builds one with other settings"
            )
            raise AttributeError(
                f"a Scene is read-only once built (its contact model, pairs and tables come from its settings), "
                f"so {name!r} cannot be set: {hint}"
            )
        object.__setattr__(self, name, value)

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"a Scene is read-only once built, so {name!r} cannot be deleted")

    def _in_frame(self, kinematics: FreeBodies | ArticulatedKinematics) -> Scene:
        """A shallow copy whose map from the step's unknowns to poses is ``kinematics`` (the step's solve frame;
        this scene is not changed)."""
        new = copy.copy(self)
        object.__setattr__(new, "kinematics", kinematics)
        return new

    @property
    def num_bodies(self) -> int:
        """N, the bodies of the scene (a robot's links included): a state's rows."""
        return len(self.bodies)

    @property
    def simulates_joints(self) -> bool:
        """Whether the step solves for joints (the scene has robots that are not kinematic)."""
        return isinstance(self.kinematics, ArticulatedKinematics)

    @property
    def num_actuators(self) -> int:
        """U, the actuators of the simulated (not kinematic) robots: ``Action.ctrl``'s length."""
        return self.kinematics.num_actuators if self.simulates_joints else 0

    def servo_gains(self, dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        """(U,) kp and (U,) kv of the simulated robots' actuators as the MJCF gives them (``Params.kp`` / ``kv``'s
        default; empty without robots)."""
        if self.simulates_joints:
            return self.kinematics.servo_gains(dtype, device)
        return (torch.zeros(0, dtype=dtype, device=device),) * 2

    @property
    def num_kinematic_coords(self) -> int:
        """The coordinates of the kinematic robots: ``Action.joints``'s length."""
        return sum(a.num_coords for a, _ in self.kinematic_articulations)

    def kinematic_link_poses(self, joints: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """(B, Kl, 6) the poses of the kinematic robots' moving links (their rows of ``Scene.kinematic``, in order)
        for their coordinates ``joints`` (B, Qk) (per robot: base pose if floating, then joint values), a
        joint-less fixed root standing where ``q`` (B, N, 6) has it. Differentiable in ``joints``."""
        out, c = [], 0
        for art, r in self.kinematic_articulations:
            out.append(art.moving_rows(joints[:, c : c + art.num_coords], q[:, r]))
            c += art.num_coords
        return torch.cat(out, 1)

    def kinematic_coords(self, q: torch.Tensor) -> torch.Tensor:
        """(B, Qk) the kinematic robots' coordinates at poses ``q`` (B, N, 6) (the inverse of
        :meth:`kinematic_link_poses`)."""
        return torch.cat([a.coords(q[:, r : r + a.num_links]) for a, r in self.kinematic_articulations], 1)

    def __getattr__(self, name: str):
        """The constructor's shorthand names read the config fields too (``scene.margin`` is
        ``scene.contact.margin``)."""
        if name in _SHORTHAND:
            which, field = _SHORTHAND[name]
            return getattr(self.__dict__[which], field)
        raise AttributeError(f"'Scene' object has no attribute {name!r}")

    def replace(self, **changes) -> Scene:
        """A copy with some arguments changed (e.g. ``dt``, ``friction``, or any shorthand); a change of the
        contact settings, the potential, ``refine_obstacles``, ``exclude`` or the articulations builds it from the
        bodies as given (their obstacles refined afresh); ``friction=`` a number changes only the coefficient; a
        change of ``potential`` resets the settings the new potential does not read (``mu`` for IPC, ``dhat`` for
        this library's) to their defaults."""
        kw = {k: getattr(self, "_given_contact_model" if k == "contact_model" else k) for k in _REPLACEABLE}
        if is_real(changes.get("friction")):
            changes = {
                **changes,
                "friction": dataclasses.replace(self.friction, coefficient=changes["friction"]),
            }
        if "potential" in changes and "contact" not in changes:
            kw["contact"] = with_potential(self.contact, changes["potential"])
        kw.update(changes)
        # the obstacles as refined here serve unless a change can change their refinement (refining them again
        # would cost each sub-step retry's replace(dt=...) about 0.1 s)
        refining = {"contact", "potential", "refine_obstacles", "contact_model", "exclude", "articulations"}
        if refining.isdisjoint(changes):
            n = len(self.bodies) - sum(a.num_links for a in self.articulations)
            out = Scene(self.bodies[:n], **kw)
            object.__setattr__(
                out, "_given_bodies", self._given_bodies
            )  # what a later replace() refines from
            return out
        return Scene(self._given_bodies, **kw)

    def params(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> Params:
        """The scene's differentiable physical parameters as tensors of ``dtype`` on ``device`` (set requires_grad
        for their gradients): mass and second moment, one row per body the kinematics map moves; the friction
        coefficient (``FrictionConfig.coefficient``); the servos' gains kp and kv from the articulations' MJCF
        (empty without simulated robots).

        Raises:
            ValueError: ``dtype`` is not torch.float32 or torch.float64 (the dtypes ``step`` takes), or ``device``
                is not one this torch build can hold data on."""
        if dtype not in FLOATS:
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
        device = usable_device(device)
        d = self.kinematics.bodies.tolist()
        return Params(
            torch.tensor([self.bodies[i].mass for i in d], dtype=dtype, device=device),
            torch.stack([self.bodies[i].second_moment for i in d]).to(dtype=dtype, device=device),
            torch.tensor(float(self.friction.coefficient), dtype=dtype, device=device),
            *self.servo_gains(dtype, device),
        )

    def initial_state(self, poses: torch.Tensor, velocities: torch.Tensor | None = None) -> State:
        """State at rest (or moving with constant generalised ``velocities``) at ``poses``, both ([B,] N, 6).

        A dynamic body's pose places its centre of mass (its frame, :func:`cfd_torch.rigid_body`); a static or
        kinematic body's places its mesh's own frame.

        The velocities are rates of the pose coordinates: the translation's (m/s), and the rotation vector's (its
        rate of change, q_prev = poses - dt velocities), which equals the angular velocity only where the rotation
        vector is parallel to it or zero (a body at rotation 0, or spinning about its rotation vector's axis). The
        rows of static and kinematic bodies start at rest whatever ``velocities`` holds there (a static body never
        moves; a kinematic one moves to the targets of each step's action).

        Raises:
            TypeError: poses or velocities is not a tensor.
            ValueError: poses or velocities of the wrong shape, dtype or device, with NaN/inf, a translation
                beyond 1e30 m, a rotation vector longer than 1e6 rad, or (a planar scene) velocities out of its
                plane."""
        check_state_tensor(poses, "poses", self.num_bodies)
        check_pose_range(poses, "poses")
        if velocities is None:
            return State(poses, poses.clone())
        check_state_tensor(velocities, "velocities", self.num_bodies, like=poses, like_name="poses")
        if velocities.shape != poses.shape:
            raise ValueError(f"velocities must have the shape of poses {tuple(poses.shape)}")
        v = velocities.clone()
        v[..., self.static_mask | _mask(self.kinematic, self.num_bodies), :] = 0.0
        if self.planar and bool((v[..., 2:5] != 0).any()):
            raise ValueError(
                "velocities: a planar scene's bodies move in x, y and yaw only; columns 2-4 (z, and the rotation "
                "vector's x and y) must be 0 for its dynamic bodies"
            )
        return State(poses, poses - self.dt * v)


def _mask(index: torch.Tensor, n: int) -> torch.Tensor:
    m = torch.zeros(n, dtype=torch.bool)
    m[index] = True
    return m
