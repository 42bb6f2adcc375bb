"""A copy of a URDF with some links' inertial parameters replaced (an identified robot model).

Everything else of the file is kept as it is (joints, sensors, meshes, comments); each replaced link's
``<inertial>`` gets its mass, its centre of mass as ``<origin xyz>`` with ``rpy="0 0 0"``, and its rotational
inertia about the centre of mass in the link frame's axes. Values are written with 17 significant digits, so
the file reads back to the same parameters.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

from pipeline.core.io import write_text
from pipeline.physics.urdf import LinkInertial, RobotModelError


def _num(x: float) -> str:
    return repr(float(x))


def _set_inertial(link: ET.Element, inertial: LinkInertial) -> None:
    element = link.find("inertial")
    if element is None:
        element = ET.SubElement(link, "inertial")
    for child in list(element):
        if child.tag in ("origin", "mass", "inertia"):
            element.remove(child)
    ET.SubElement(element, "origin", xyz=" ".join(map(_num, inertial.com)), rpy="0 0 0")
    ET.SubElement(element, "mass", value=_num(inertial.mass))
    i = inertial.inertia
    names = {"ixx": i[0, 0], "ixy": i[0, 1], "ixz": i[0, 2], "iyy": i[1, 1], "iyz": i[1, 2], "izz": i[2, 2]}
    ET.SubElement(element, "inertia", {k: _num(v) for k, v in names.items()})


def write_inertials(src: str | Path, dst: str | Path, inertials: Mapping[str, LinkInertial]) -> None:
    """Write `src` (a URDF file) to `dst` (atomically) with the links of `inertials` given those values
    (mass kg; com (3,) m in the link frame; inertia (3, 3) kg m^2 about the com, link axes).

    Raises:
        RobotModelError: `src` is not valid XML, or a link of `inertials` is not in it.
    """
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    try:
        tree = ET.parse(src, parser=parser)
    except (ET.ParseError, OSError) as exc:
        raise RobotModelError(f"{src}: cannot read the URDF ({exc})") from None
    links = {el.get("name"): el for el in tree.getroot().findall("link")}
    for name, inertial in inertials.items():
        if name not in links:
            raise RobotModelError(f"{src}: no link {name!r} to write identified inertial parameters to")
        _set_inertial(links[name], inertial)
    ET.indent(tree, space="  ")
    write_text(dst, '<?xml version="1.0" ?>\n' + ET.tostring(tree.getroot(), encoding="unicode") + "\n")


__all__ = ["write_inertials"]
