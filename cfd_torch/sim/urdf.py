"""URDF front end of articulated bodies: a URDF is read as the MJCF that MuJoCo's URDF importer makes of it, and
:mod:`.mjcf` reads that."""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET

import mujoco

__all__ = ["is_urdf", "urdf_as_mjcf"]


def is_urdf(xml: str) -> bool:
    """Whether the model text is URDF (its root element ``<robot>``)."""
    try:
        return ET.fromstring(xml).tag == "robot"
    except ET.ParseError:
        return False  # (reported as the MJCF's)


def urdf_as_mjcf(urdf: str, base: str | None, meshdir: str | None = None) -> str:
    """The MJCF MuJoCo's URDF importer makes of ``urdf`` (asset files read relative to the folder ``base``; mesh
    files by their names alone in its meshdir, as MuJoCo reads URDF: ``<mujoco><compiler meshdir=.../></mujoco>``
    in the URDF sets it), with the bodies of fixed joints kept (``fusestatic`` off: they are welded into their link
    here anyway) and no joint effort limits (URDF has no actuators; MuJoCo turns ``<limit effort>`` into
    ``actuatorfrcrange``, which would clamp actuators added to the model, not modelled here). MuJoCo writes
    numbers with 6 significant digits. ``meshdir``: in place of the URDF's own."""
    tree = ET.fromstring(urdf)
    mimics = [j.get("name", "?") for j in tree.iter("joint") if j.find("mimic") is not None]
    if mimics:
        warnings.warn(
            f"URDF joints {mimics[:8]}{' ...' if len(mimics) > 8 else ''} have a <mimic>, which MuJoCo's importer "
            "drops: here they move on their own",
            UserWarning,
            stacklevel=4,
        )
    if _name_geometry(tree):
        urdf = ET.tostring(tree, encoding="unicode")
    try:
        spec = mujoco.MjSpec.from_string(urdf)
        if base is not None:
            spec.modelfiledir = base
        if meshdir is not None:
            spec.meshdir = meshdir
        spec.compiler.fusestatic = False
        # (the importer drops the URDF's visual elements unless its own <mujoco><compiler> keeps them; kept, they
        # have no mass and no contact, and load_mjcf leaves them out as visual geoms)
        spec.compiler.discardvisual = False
        for joint in spec.joints:
            joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE
        spec.compile()
        return spec.to_xml()
    except ValueError as e:  # (MuJoCo's parse and compile errors)
        hint = (
            "; MuJoCo reads a URDF's mesh files by their names alone, from its meshdir (relative to the URDF's "
            'folder): pass meshdir=, or set it in the URDF, <mujoco><compiler meshdir="..."/></mujoco>'
            if "Error opening file" in str(e)
            else ""
        )
        raise ValueError(f"the URDF could not be read by MuJoCo's importer: {e}{hint}") from None


def _name_geometry(tree: ET.Element) -> bool:
    """Name each unnamed <collision> and <visual> of the URDF ``tree`` after its link ("arm/collision1"), in place:
    the geoms MuJoCo makes of them carry the names (in messages), and its importer stops printing a warning for
    each unnamed one. Whether any was named."""
    taken = {e.get("name") for e in tree.iter() if e.tag in ("collision", "visual") and e.get("name")}
    named = False
    for link in tree.iter("link"):
        for kind in ("collision", "visual"):
            for k, element in enumerate(link.findall(kind)):
                if element.get("name"):
                    continue
                claim_name(element, f"{link.get('name', '')}/{kind}{k}", taken)
                named = True
    return named


def claim_name(element: ET.Element, name: str, taken: set[str]) -> None:
    """Name ``element`` ``name``, with "_" appended while that is ``taken``, and add it to ``taken``."""
    while name in taken:
        name += "_"
    element.set("name", name)
    taken.add(name)
