"""The transport record (drivers/registry.py) is complete: each name has its config schema, a
link module that exists, and the handshake set names registered transports only."""

from __future__ import annotations

import importlib.util
from typing import get_args

import pytest

from drivers.registry import _CONFIGS, HANDSHAKE, TRANSPORTS, link_config


@pytest.mark.parametrize("name", sorted(TRANSPORTS))
def test_every_transport_has_its_schema_and_link(name):
    module, _ = TRANSPORTS[name]
    assert importlib.util.find_spec(module) is not None, module
    assert get_args(_CONFIGS[name].model_fields["transport"].annotation) == (name,)


def test_the_registry_and_the_schemas_name_the_same_transports():
    assert set(_CONFIGS) == set(TRANSPORTS)
    assert not HANDSHAKE - set(TRANSPORTS)


def test_an_unknown_transport_names_the_known_ones():
    from contracts.yaml_files import ConfigError

    with pytest.raises(ConfigError, match=r"link: transport: expected one of \['haas'"):
        link_config({"transport": "profinet"})
