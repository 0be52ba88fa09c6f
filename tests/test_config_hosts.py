"""A host in the configuration is a host name or an IP address: an empty one (``mqtt.host:
''``) passed ``rumba run --check`` and the daemon then tried to reach nothing, every few
seconds. Every host field (MQTT broker, e-mail server, HMI, OPC UA results server, Modbus and
LinuxCNC links) refuses it with the key named."""

from __future__ import annotations

import pytest

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from contracts.yaml_files import ConfigError
from daemon.config import load_daemon_config

BAD = ["''", "' '", "'mqtt://broker'", "'broker:1883'", "'two words'", "'-x.example'"]


def _top(key: str, host: str) -> str:
    return {
        "mqtt": f"mqtt: {{host: {host}, site: shop}}",
        "notify.email": ("notify:\n  email: {host: " + host + ", from: rumba@shop.example, "
                         "to: [q@shop.example]}"),
        "opcua_server": f"opcua_server: {{host: {host}, trusted_dir: /tmp, users: {{}}}}",
    }[key]


@pytest.mark.parametrize("host", BAD)
@pytest.mark.parametrize("key", ["mqtt", "notify.email", "opcua_server"])
def test_a_section_host_that_is_no_host_is_refused(tmp_path, key, host):
    path = write_daemon_yaml(tmp_path, extra_top=_top(key, host))
    with pytest.raises(ConfigError) as e:
        load_daemon_config(path)
    assert f"{key}.host" in str(e.value) and "expected a host name or an IP address" in \
        str(e.value), e.value


@pytest.mark.parametrize("host", BAD)
@pytest.mark.parametrize("link", ["modbus", "linuxcnc"])
def test_a_link_host_that_is_no_host_is_refused(tmp_path, link, host):
    path = write_daemon_yaml(tmp_path, link=f"{{transport: {link}, host: {host}}}",
                             dialect="linuxcnc" if link == "linuxcnc" else "fanuc")
    with pytest.raises(ConfigError) as e:
        load_daemon_config(path)
    assert "host" in str(e.value) and "expected a host name or an IP address" in str(e.value)


def test_the_hmi_host_is_checked_and_good_hosts_pass(tmp_path):
    path = write_daemon_yaml(tmp_path)
    path.write_text(path.read_text().replace("hmi: {host: 127.0.0.1,", "hmi: {host: '',"))
    with pytest.raises(ConfigError, match=r"hmi\.host: '': expected a host name"):
        load_daemon_config(path)
    for good in ("broker.shop.example", "10.0.0.7", "::1", "mqtt_1"):
        cfg = load_daemon_config(write_daemon_yaml(
            tmp_path, extra_top=f"mqtt: {{host: '{good}', site: shop}}"))
        assert cfg.mqtt.host == good
