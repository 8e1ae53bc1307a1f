"""The only defaults of the library's numerical and physical settings, in three frozen config objects.

Names are unambiguous: ``stiffness`` is the contact coefficient mu of the potential P = mu E (SPEC section 2), and
``coefficient`` is Coulomb's friction coefficient; they are never both called "mu" or "friction".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

from ._validate import check_count, check_stiffness, is_real

__all__ = ["ContactConfig", "FrictionConfig", "SolverConfig", "SPLIT_RULES", "POTENTIALS", "DEFAULT_CONTACT"]

SPLIT_RULES = ("both", "larger")
POTENTIALS = ("cfd", "ipc", "sdrs")


def _got(value: object) -> str:
    """How an error shows a setting's value: with its type when it is not a real number (a tensor, a string)."""
    return (
        f"{value!r}" if is_real(value) else f"{value!r} of type {type(value).__name__} (give a Python float)"
    )


def _positive(owner: str, name: str, value: object) -> None:
    if not (is_real(value) and 0 < value < math.inf):
        raise ValueError(f"{owner}.{name} must be a finite positive number, got {_got(value)}")


def _count(owner: str, name: str, value: object, most: int = 10**6) -> None:
    """A positive int of at most ``most`` (an iteration cap or a count of sub-steps: more is never meant)."""
    check_count(value, f"{owner}.{name}", most)


@dataclass(frozen=True)
class ContactConfig:
    """Settings of the contact potential (SPEC sections 2-4).

    Attributes:
        stiffness: mu, the scale of the potential P = mu E (E mixes dimensionless and 1/m terms). Bodies rest
            where its repulsion, growing like mu / gap^2 near contact, balances their weight: the default suits
            bodies of decimetres and kilograms; a 1 cm, 1 g cube hovers centimetres above its floor at it and rests
            1.2 mm above it at 1e-12 (scale mu like size^5 with the margin like size).
        margin: delta, the distance below which the potential is +inf [m].
        eps: relative width of the hierarchy's blend band, d2 = d1 + max(eps d1, 2 margin) (never narrower than
            twice the margin: see :mod:`cfd_torch.contact.central`).
        split: which node of a node pair the traversal descends: "both", or the "larger" sphere (both on a tie).
        pair_tol: relative gradient tolerance of each leaf pair's plane solve.
        pair_max_iter: Newton iteration cap of the plane solve (a pair that does not converge raises).
        backend: "auto" (numba kernels on the CPU, batched tensors elsewhere) or "torch": the contact model's
            traversal and pair solves as batched tensors on the CPU too (the GPU's route for them). The
            simulator's other CPU kernels (body, friction and joint terms, rotations, the per-pair sums, triangle
            checks) choose numba for CPU float64 tensors either way, and the collision query of its feasibility
            checks runs on the CPU either way.
        refine_obstacles: a :class:`cfd_torch.Scene` refines each static or kinematic body whose triangles have
            edges longer than twice this times the longest edge of the finest dynamic body it interacts with, to
            edges of at most this times it (midpoint splits, the same surface; see
            :func:`cfd_torch.sim.bodies.refine_obstacles`); None keeps every mesh as given. A leaf sphere much
            larger than its partner's makes every partner triangle inside it an exact leaf pair, so a coarse floor
            costs several times a fine one.
        potential: the contact potential a :class:`cfd_torch.Scene` simulates: "cfd" (this library's, the fields
            above); or one of the locally supported baselines, whose forces and gradients vanish beyond ``dhat``
            (obstacles are not refined for them): "ipc", IPC's log barrier over vertex-face and edge-edge pairs
            (:class:`cfd_torch.contact.ipc.IpcContact`, ipc-toolkit's definition), or "sdrs", the local plane
            barrier over triangle pairs (:class:`cfd_torch.contact.sdrs.SdrsContact`, with ``margin``). Friction
            and the solver are the same for all.
        dhat: the baselines' activation distance [m].
        barrier_stiffness: the baselines' kappa; None: the model's default (IPC 1e6 N / m^3, SDRS 10).

    A field the chosen ``potential`` does not read must stay at its default (ValueError naming it otherwise, as a
    setting silently ignored would be): ``dhat`` and ``barrier_stiffness`` with "cfd"; ``stiffness``, ``eps``,
    ``split``, ``pair_tol``, ``pair_max_iter``, ``backend`` and ``refine_obstacles`` (None included) with a
    baseline. ``margin`` is read by all (SDRS's margin, and a length scale of the step's line search).
    """

    stiffness: float = 1e-8
    margin: float = 1e-3
    eps: float = 0.01
    split: Literal["both", "larger"] = "both"
    pair_tol: float = 1e-12
    pair_max_iter: int = 100
    backend: Literal["auto", "torch"] = "auto"
    refine_obstacles: float | None = 2.0
    potential: Literal["cfd", "ipc", "sdrs"] = "cfd"
    dhat: float = 1e-2
    barrier_stiffness: float | None = None

    def __post_init__(self) -> None:
        if self.potential not in POTENTIALS:
            raise ValueError(f"ContactConfig.potential must be one of {POTENTIALS}, got {self.potential!r}")
        _positive("ContactConfig", "dhat", self.dhat)
        if self.barrier_stiffness is not None:
            _positive("ContactConfig", "barrier_stiffness", self.barrier_stiffness)
        if self.refine_obstacles is not None:
            _positive("ContactConfig", "refine_obstacles", self.refine_obstacles)
        if self.backend not in ("auto", "torch"):
            raise ValueError(f"ContactConfig.backend must be 'auto' or 'torch', got {self.backend!r}")
        for name in ("stiffness", "margin", "eps", "pair_tol"):
            _positive("ContactConfig", name, getattr(self, name))
        check_stiffness(self.stiffness, "ContactConfig.stiffness")
        if not self.pair_tol < 1:
            raise ValueError(
                f"ContactConfig.pair_tol must be below 1 (a relative tolerance), got {self.pair_tol!r}"
            )
        _count("ContactConfig", "pair_max_iter", self.pair_max_iter)
        if self.split not in SPLIT_RULES:
            raise ValueError(f"ContactConfig.split must be one of {SPLIT_RULES}, got {self.split!r}")
        # a setting the chosen potential does not read must keep its default (it would be silently ignored)
        unused = _BASELINE_ONLY if self.potential == "cfd" else _CFD_ONLY
        changed = [n for n in unused if getattr(self, n) != _CONTACT_DEFAULTS[n]]
        if changed:
            names = ", ".join(f"{n} (Scene's {_SHORT.get(n, n)}=)" for n in changed)
            whose = "the baselines' barrier" if self.potential == "cfd" else "this library's potential"
            raise ValueError(
                f"ContactConfig {names} {'sets' if len(changed) == 1 else 'set'} {whose}, which "
                f"potential={self.potential!r} does not use: leave "
                f"{'it' if len(changed) == 1 else 'them'} at the default"
            )


# the settings only one kind of potential reads (``margin`` is the SDRS barrier's too, and a length scale of the
# step's line search for every potential)
_CFD_ONLY = ("stiffness", "eps", "split", "pair_tol", "pair_max_iter", "backend", "refine_obstacles")
_BASELINE_ONLY = ("dhat", "barrier_stiffness")
_SHORT = {"stiffness": "mu"}
_CONTACT_DEFAULTS = {f.name: f.default for f in fields(ContactConfig)}


def with_potential(config: ContactConfig, potential: str) -> ContactConfig:
    """``config`` with another ``potential``, the settings that potential does not read back at their defaults
    (``Scene.replace(potential=...)``: a scene's ``mu`` does not carry over to IPC, nor IPC's ``dhat`` to ours)."""
    unused = _BASELINE_ONLY if potential == "cfd" else _CFD_ONLY
    return replace(config, potential=potential, **{n: _CONTACT_DEFAULTS[n] for n in unused})


DEFAULT_CONTACT = ContactConfig()  # the contact functions' keyword defaults read this (no literal elsewhere)


# the smallest friction slip scale [m/s]: (eps_v dt)^2 underflows float64 from about 1e-160 m/s at dt = 0.01
_MIN_EPS_V = 1e-30


@dataclass(frozen=True)
class FrictionConfig:
    """Lagged, smoothed Coulomb friction (SPEC section 5).

    Attributes:
        coefficient: Coulomb's coefficient mu_f, the default of ``Params.friction`` (``Scene.params()``); friction is
            off (no lagged data, no cost) in a step whose ``Params.friction`` is 0 and does not require grad, so a
            step given ``Params(friction=0.5)`` has friction in a scene built with 0.
        eps_v: slip velocity below which friction is in its smoothed static regime [m/s], at least 1e-30.
        active: friction acts on the leaf pairs whose lagged normal force is at least this fraction of the largest
            in their body pair (0: on all of them); the others carry almost none of the load and only cost time.
    """

    coefficient: float = 0.0
    eps_v: float = 1e-4
    active: float = 1e-6

    def __post_init__(self) -> None:
        c = self.coefficient
        if not (is_real(c) and 0 <= c < math.inf):
            raise ValueError(f"FrictionConfig.coefficient must be a finite number >= 0, got {_got(c)}")
        _positive("FrictionConfig", "eps_v", self.eps_v)
        if self.eps_v < _MIN_EPS_V:
            raise ValueError(
                f"FrictionConfig.eps_v must be at least {_MIN_EPS_V:g} m/s, got {self.eps_v!r}: the friction law "
                "works with (eps_v dt)^2, which underflows float64 from about 1e-160 m/s at dt = 0.01 (the step's "
                "energy or Hessian is then not finite); 1e-30 keeps far from it"
            )
        a = self.active
        if not (is_real(a) and 0 <= a < 1):
            raise ValueError(f"FrictionConfig.active must be a number in [0, 1), got {a!r}")


@dataclass(frozen=True)
class SolverConfig:
    """The step's Newton solve and its feasibility checks (SPEC section 5).

    Attributes:
        newton_tol: converged when the undamped Newton step is at most this in every coordinate [m, rad] at a
            positive definite Hessian; that last step is taken too, so forces too weak to move a body by this
            much per step still move it (a step's error is about the square of this step, not this).
        max_newton_iter: Newton iterations of one solve before the step raises :class:`cfd_torch.StepError` (a
            step pushing bodies out of a kinematic body's way runs a solve per stage, each with this cap).
        ccd_spacing: [m] no tunnelling: a move of the iterate is accepted only if its straight path stays feasible
            at points at most this far apart (largest vertex displacement), or half the thinnest moving body's
            thickness plus the margin where that is less (``Scene.path_spacing``), and one Newton iteration
            moves no vertex more than 20 times this.
        reach_shrink: the end-of-step reachability check shrinks the moving bodies by this fraction about their
            centres of mass (an interpolated path is not the body's motion; dipping a few millimetres into a
            support it rests or lands on is not tunnelling).
        substeps: on a :class:`cfd_torch.StepError`, retry the step as 2, 4, ... up to this many equal sub-steps
            (kinematic targets interpolated); 1 raises at once.
        fast: False takes the plain reference path, for tests and debugging: every body iterates until its scene
            converges, with one line search per scene (no frozen bodies, no islands), and every plane solve
            starts cold (no warm starts). The result is the same to the solver's tolerances.
    """

    newton_tol: float = 1e-9
    max_newton_iter: int = 200
    ccd_spacing: float = 0.01
    reach_shrink: float = 0.1
    substeps: int = 1
    fast: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.fast, bool):
            raise ValueError(f"SolverConfig.fast must be a bool, got {self.fast!r}")
        _positive("SolverConfig", "newton_tol", self.newton_tol)
        _positive("SolverConfig", "ccd_spacing", self.ccd_spacing)
        _count("SolverConfig", "max_newton_iter", self.max_newton_iter)
        _count("SolverConfig", "substeps", self.substeps, 2**16)
        if not (is_real(self.reach_shrink) and 0 <= self.reach_shrink < 1):
            raise ValueError(
                f"SolverConfig.reach_shrink must be a number in [0, 1), got {self.reach_shrink!r}"
            )
