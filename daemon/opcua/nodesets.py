"""Load the official OPC UA companion nodesets (XML from the npm package node-opcua-nodesets,
taken at install time) into an asyncua server, with the two repairs asyncua 2.1 needs.

1. Nodes marked ``DesignToolOnly`` (DI's nine "Configuration" examples) have no parent in the
   address space; asyncua refuses them, so they are left out, as the attribute says servers may.
2. asyncua's XML reader takes the indentation between the elements of an ExtensionObject value
   (e.g. Machinery Result's EnumValues) for content; whitespace-only text is removed from values.
Nothing else is changed: every NodeId, BrowseName and reference is the official one."""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

from asyncua import Server

from contracts.yaml_files import ConfigError

UANODESET = "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
DI_URI = "http://opcfoundation.org/UA/DI/"
MACHINERY_URI = "http://opcfoundation.org/UA/Machinery/"
RESULT_URI = "http://opcfoundation.org/UA/Machinery/Result/"


def cleaned(path: Path) -> str:
    """The nodeset's XML text with the two repairs of the module docstring."""
    ET.register_namespace("", UANODESET)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise ConfigError(f"{path}: not a readable nodeset: {e}") from None
    for e in [e for e in root if e.get("DesignToolOnly") == "true"]:
        root.remove(e)
    for value in root.iter(f"{{{UANODESET}}}Value"):
        for x in value.iter():
            if x.text is not None and not x.text.strip():
                x.text = None
            if x.tail is not None and not x.tail.strip():
                x.tail = None
    return ET.tostring(root, encoding="unicode")


async def load(server: Server, nodesets: tuple[Path, ...]) -> dict[str, int]:
    """Import the nodesets in order and generate their data types (ResultDataType …);
    the namespace index of DI, Machinery and Machinery Result."""
    # the importer logs a warning per reference it re-parents (hundreds, all harmless)
    for name in ("asyncua.common.xmlimporter", "asyncua.common.structures104",
                 "asyncua.common.xmlparser"):
        logging.getLogger(name).setLevel(logging.ERROR)
    for path in nodesets:
        try:
            await server.import_xml(xmlstring=cleaned(path))
        except ConfigError:
            raise
        except Exception as e:  # asyncua raises what its importer meets
            raise ConfigError(f"{path}: cannot import the nodeset: {e}") from None
    await server.load_data_type_definitions()
    ns = await server.get_namespace_array()
    missing = [u for u in (DI_URI, MACHINERY_URI, RESULT_URI) if u not in ns]
    if missing:
        raise ConfigError(f"nodesets {', '.join(p.name for p in nodesets)} do not define "
                          f"{', '.join(missing)}")
    return {u: ns.index(u) for u in (DI_URI, MACHINERY_URI, RESULT_URI)}
