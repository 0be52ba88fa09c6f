"""daemon.yaml's ``opcua_server`` and ``aqdef_dir``: off when absent, loopback unless
``allow_remote``, every file checked at load time with one line naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from contracts.yaml_files import ConfigError
from daemon.config import load_daemon_config
from daemon.opcua.config import NODESETS


def opcua_yaml(tmp: Path, **over: str) -> Path:
    nodesets = tmp / "nodesets"
    nodesets.mkdir(exist_ok=True)
    for n in NODESETS:
        (nodesets / n).write_text("<UANodeSet/>")
    trusted = tmp / "trusted"
    trusted.mkdir(exist_ok=True)
    (trusted / "client.der").write_bytes(b"\x30\x00")
    pw = tmp / "pw"
    pw.write_text("a-password-of-16-chars-or-more")
    pw.chmod(0o600)
    keys = {"trusted_dir": str(trusted), "users": f"{{quality: {pw}}}",
            "nodesets_dir": str(nodesets),
            "machines": "{mill1: {manufacturer: Acme, serial_number: SN-1}}", **over}
    body = ", ".join(f"{k}: {v}" for k, v in keys.items())
    return write_daemon_yaml(tmp, extra_top=f"opcua_server: {{{body}}}\naqdef_dir: spc")


def test_off_by_default_and_loaded_when_given(tmp_path):
    cfg = load_daemon_config(write_daemon_yaml(tmp_path))
    assert cfg.opcua_server is None and cfg.aqdef_dir is None
    cfg = load_daemon_config(opcua_yaml(tmp_path))
    o = cfg.opcua_server
    assert (o.host, o.port) == ("127.0.0.1", 4850)
    assert o.users == {"quality": "a-password-of-16-chars-or-more"}
    assert o.identification["mill1"].manufacturer == "Acme"
    assert cfg.aqdef_dir == tmp_path / "spc"


@pytest.mark.parametrize(("over", "expect"), [
    ({"host": "0.0.0.0"}, "opcua_server: host 0.0.0.0 is not loopback"),
    ({"machines": "{mill9: {manufacturer: A, serial_number: S}}"},
     "opcua_server.machines: ['mill9'] not configured machines"),
    ({"nodesets_dir": "/nonexistent"}, "opcua_server.nodesets_dir: /nonexistent lacks"),
    ({"trusted_dir": "/nonexistent"}, "opcua_server.trusted_dir: /nonexistent is not a folder"),
    ({"security": "none"}, "opcua_server.security"),
    ({"users": "{}"}, "opcua_server.users"),
])
def test_bad_opcua_server_section_is_one_line(tmp_path, over, expect):
    with pytest.raises(ConfigError) as e:
        load_daemon_config(opcua_yaml(tmp_path, **over))
    assert expect in str(e.value) and "\n" not in str(e.value).strip(), str(e.value)


def test_password_file_readable_by_others_is_refused(tmp_path):
    path = opcua_yaml(tmp_path)
    (tmp_path / "pw").chmod(0o644)
    with pytest.raises(ConfigError, match=r"opcua_server.users.quality: token file .* "
                                          "readable by others"):
        load_daemon_config(path)
