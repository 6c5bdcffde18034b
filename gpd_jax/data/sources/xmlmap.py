"""Opening an XML map file (Lanelet2 `.osm`, CommonRoad `.xml`) with the checks both readers need.

Below the readers and `gpd_jax.data.sources.maps`, which dispatches to them, so nothing imports in a circle.
"""

from __future__ import annotations

import os

from gpd_jax.data.errors import DataError


def xml_root(path: str, what: str, root_tag: str):
    """The root element of the XML map file `path` (ElementTree: nothing in it runs, expat refuses entity-expansion
    bombs, external entities are never fetched); DataError naming the file when it is missing, not XML, or its
    root is not `<root_tag>` (`what` names the format in the messages)."""
    import xml.etree.ElementTree as ET

    if not os.path.isfile(path):
        raise DataError(path, "no such map file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise DataError(path, f"not a {what} (XML) file: {e}") from None
    if root.tag != root_tag:
        raise DataError(path, f"not a {what} file: the root element is <{root.tag}>, expected <{root_tag}>")
    return root
