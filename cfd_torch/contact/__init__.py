"""The contact model: the exact pair potential, the central potential and blend, the sphere hierarchy, the BSH
potential of body pairs and scenes built from them, the protocol the simulator talks to, and the baselines' models
behind it (IPC's log barrier, SDRS's local plane barrier).

Its public names are re-exported by :mod:`cfd_torch` and here, except the baselines' models (IpcContact,
SdrsContact) and sum_pairs, which are here only.
"""

from .bsh import BSH
from .central import blend_weight, central_potential, smoothstep
from .cfd import CfdContact
from .ipc import IpcContact
from .mesh import MeshDerivatives, mesh_potential, mesh_potential_derivatives
from .model import ContactEval, ContactModel, LaggedContacts, sum_pairs
from .pair import PairDerivatives, PairSolveError, pair_potential, pair_potential_derivatives
from .reference import mesh_potential_reference
from .scene import ContactPotential, contact_potential
from .sdrs import SdrsContact

__all__ = [
    "BSH", "CfdContact", "ContactEval", "ContactModel", "ContactPotential", "IpcContact", "LaggedContacts",
    "MeshDerivatives", "PairDerivatives", "PairSolveError", "blend_weight", "central_potential",
    "contact_potential", "mesh_potential", "mesh_potential_derivatives", "mesh_potential_reference",
    "pair_potential", "pair_potential_derivatives", "SdrsContact", "smoothstep", "sum_pairs",
]  # fmt: skip
