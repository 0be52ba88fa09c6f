"""The SINUMERIK OPC UA profile: the daemon's link against the simulator's SINUMERIK front-end on
free loopback ports, with Basic256Sha256 SignAndEncrypt, generated certificates and user/password
— the program through the file system and Select, NC start left to the machine (and said so),
results from the program's own R parameters with the R188/R189 handshake, the shop's GUDs for
the start-of-shift handshake, and the server's refusals as a plain OPC UA client meets them."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.client.ua_file_transfer import UaDirectory, UaFile

from benchmarks.rigs.transport_sim import latched_equal, make_truth
from contracts.jobs import ProgramJob, Verdict
from contracts.opcua_certs import ensure_certificate
from contracts.setup_files import plan_from_dict
from contracts.yaml_files import ConfigError
from drivers.base import ControllerAborted, LinkError
from drivers.registry import link_config
from drivers.sinumerik.link import SinumerikLink
from drivers.sinumerik.schema import SinumerikLinkConfig
from programs.generate import generate
from simulators.controller import VirtualController
from simulators.frontends.sinumerik import SinumerikFrontend

USERS = {"rumba": "s3cret-Passw0rd"}
pytestmark = pytest.mark.asyncio(loop_scope="module")
GUDS = ("RUMBA_REQ", "RUMBA_BUSY", "RUMBA_DONE", "RUMBA_VERDICT", "RUMBA_READY")


def job_for(truth, poses=((0.0, 0.0), (30.0, 60.0)), handshake: bool = True) -> ProgramJob:
    """The generated, safety-checked Siemens program with the result handshake."""
    plan = plan_from_dict({"name": "sinumerik-test", "poses": [list(p) for p in poses],
                           "stylus_diameter_mm": truth.errors.probe.stylus_diameter_mm})
    g = generate(truth.machine, truth.machine_file, truth.artefact, plan, "siemens",
                 handshake=handshake)
    table = g.touch_table()
    return ProgramJob(run_id="t", text=g.text, dialect="siemens", touch_count=len(table),
                      touches=table, codec=g.dialect)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def truth():
    return make_truth()


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def pki(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pki")
    await ensure_certificate(tmp / "client" / "cert.der", tmp / "client" / "key.pem",
                             "urn:rumba-cnc:daemon", server=False)
    (tmp / "trusted").mkdir()
    shutil.copy(tmp / "client" / "cert.der", tmp / "trusted" / "daemon.der")
    return tmp


def secure_cfg(pki: Path, fe: SinumerikFrontend, **kw) -> SinumerikLinkConfig:
    return SinumerikLinkConfig(**{
        "transport": "sinumerik", "url": fe.endpoint, "certificate": pki / "client/cert.der",
        "private_key": pki / "client/key.pem", "server_certificate": fe.server_certificate,
        "user": {"name": "rumba", "password": USERS["rumba"]}, "connect_timeout_s": 3, **kw})


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def secure(pki, truth):
    """A SINUMERIK-like server with security, the shop's GUDs declared, its PLC starting the
    program on program_ready."""
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, cert_dir=pki / "server", users=USERS,
                           trusted_client_certs=[pki / "trusted"], guds=GUDS)
    await fe.start()
    yield ctrl, fe
    await fe.stop()


async def until(pred, timeout_s: float = 10.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not pred():
            await asyncio.sleep(0.01)


async def test_program_through_the_file_system_results_from_r_parameters(pki, secure, truth):
    """SignAndEncrypt + user: the program is written and selected, the PLC starts it, every
    touch arrives from the R parameters the program wrote, the ring held the control while the
    link read (the ring of 8 is smaller than the program), the ack is the last touch."""
    ctrl, fe = secure
    job = job_for(truth)
    link = SinumerikLink(secure_cfg(pki, fe))
    steps: list = []
    link.on_step = steps.append
    await link.connect()
    try:
        hits = [h async for h in link.run(job)]
    finally:
        await link.close()
    latched_equal(hits, ctrl, job, tol_mm=1e-9)  # R parameters are Doubles: no rounding
    assert fe.selected is not None and fe.selected.data.decode() == job.text
    assert fe.pacer.holds >= 1 and ctrl.variables["R188"] == float(job.touch_count)
    assert steps[0].startswith("while waiting for NC start at the machine") and steps[-1] is None
    assert ctrl.state == "done" and fe.nc_starts >= 1


async def test_waits_for_nc_start_at_the_machine_and_says_so(truth):
    """No PLC start: the link says it waits for NC start and nothing runs; the operator's NC
    start runs the program to its end."""
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, security="none", plc_starts=False)
    await fe.start()
    link = SinumerikLink(SinumerikLinkConfig(transport="sinumerik", url=fe.endpoint,
                                             security="none"))
    steps: list = []
    link.on_step = steps.append
    await link.connect()
    job = job_for(truth, poses=((0.0, 0.0),))
    got: list = []

    async def consume() -> None:
        got.extend([h async for h in link.run(job)])
    task = asyncio.create_task(consume())
    try:
        await until(lambda: bool(steps))
        await asyncio.sleep(0.3)  # nothing starts the program by itself
        assert "waiting for NC start" in steps[0] and ctrl.state == "idle" and not got
        assert ctrl.variables["R5"] == 1.0  # program_ready for the PLC
        await fe.nc_start()  # the operator
        async with asyncio.timeout(30):
            await task
        assert len(got) == job.touch_count and ctrl.variables["R5"] == 0.0
    finally:
        task.cancel()
        await link.close()
        await fe.stop()


async def test_stop_ends_the_program_without_an_alarm(truth):
    """rumba's stop (R189 = 1) ends the program at its next touch with M30; one given before
    NC start makes the program end at once when it is started."""
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, security="none", plc_starts=False)
    await fe.start()
    link = SinumerikLink(SinumerikLinkConfig(transport="sinumerik", url=fe.endpoint,
                                             security="none"))
    await link.connect()
    try:
        job = job_for(truth)
        agen = link.run(job)
        first = asyncio.ensure_future(anext(agen))
        await until(lambda: ctrl.variables.get("R5") == 1.0)
        await fe.nc_start()
        assert (await first).seq == 1
        await link.abort()
        assert ctrl.state == "done" and ctrl.alarm is None
        assert "RUMBA RUN STOPPED BY RUMBA" in ctrl.messages
        assert len(ctrl.touches) < job.touch_count
        with pytest.raises(LinkError, match="stop request"):
            async for _ in agen:
                pass
        # a stop before NC start: the program, when started, ends before its first touch
        ctrl.messages.clear()
        agen = link.run(job_for(truth, poses=((0.0, 0.0),)))
        pending = asyncio.ensure_future(anext(agen))
        await until(lambda: ctrl.variables.get("R5") == 1.0)
        await link.abort()
        await fe.nc_start()
        await until(lambda: ctrl.state == "done")
        assert ctrl.touches == [] and "RUMBA RUN STOPPED BY RUMBA" in ctrl.messages
        pending.cancel()
        await asyncio.gather(pending, return_exceptions=True)
    finally:
        await link.close()
        await fe.stop()


async def test_reset_at_the_control_is_reported_as_aborted_there(truth):
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, security="none")
    await fe.start()
    link = SinumerikLink(SinumerikLinkConfig(transport="sinumerik", url=fe.endpoint,
                                             security="none"))
    await link.connect()
    try:
        got = []
        job = job_for(truth)
        with pytest.raises(ControllerAborted, match="RESET or an alarm"):
            async for h in link.run(job):
                got.append(h)
                if len(got) == 3:
                    await ctrl.abort()  # RESET at the machine
        # the touches made before the RESET (already in the ring) still count, in order
        assert [h.seq for h in got] == list(range(1, len(got) + 1))
        assert 3 <= len(got) == len(ctrl.touches) < job.touch_count
    finally:
        await link.close()
        await fe.stop()


async def test_start_of_shift_handshake_through_the_shops_guds(pki, secure):
    """The shop maps request / busy / done / verdict / program_ready onto its GUDs: the
    PLC's request starts the wait, the verdict lands in the GUD and in the controller."""
    ctrl, fe = secure
    nodes = {r: f"ns={fe._ns};s=/NC/_N_NC_GD3_ACX/{g}" for r, g in zip(
        ("request", "busy", "done", "verdict", "program_ready"), GUDS, strict=True)}
    fe.handshake.update({r: g for r, g in zip(nodes, GUDS, strict=True)})
    link = SinumerikLink(secure_cfg(pki, fe, nodes=nodes))
    await link.connect()
    try:
        waiting = asyncio.create_task(link.wait_start_request())
        await asyncio.sleep(0.2)
        assert not waiting.done()
        ctrl.raise_start_request()
        async with asyncio.timeout(10):
            req = await waiting
        assert req.source == "cnc" and "RUMBA_REQ" in req.detail
        await until(lambda: ctrl.variables.get("RUMBA_BUSY") == 1.0 and ctrl.busy)
        await link.write_verdict(Verdict("WARN", "r1"))
        await until(lambda: ctrl.verdict == 2 and ctrl.done)
        assert ctrl.variables["RUMBA_VERDICT"] == 2.0 and ctrl.variables["R4"] == 2.0
        assert ctrl.variables["RUMBA_BUSY"] == 0.0
    finally:
        fe.handshake.update({r: f"R{i}" for i, r in enumerate(nodes, 1)})
        ctrl.request = False
        await link.close()


async def test_wrong_password_and_unsecured_client_are_refused(pki, secure):
    _, fe = secure
    with pytest.raises(LinkError, match="rejected"):
        link = SinumerikLink(secure_cfg(pki, fe, user={"name": "rumba", "password": "nope"}))
        await link.connect()
    link = SinumerikLink(SinumerikLinkConfig(transport="sinumerik", url=fe.endpoint,
                                             security="none", connect_timeout_s=2))
    with pytest.raises(LinkError):
        await link.connect()


async def test_a_mapped_node_that_does_not_exist_fails_at_connect(pki, secure):
    _, fe = secure
    link = SinumerikLink(secure_cfg(pki, fe, nodes={
        "request": f"ns={fe._ns};s=/NC/_N_NC_GD3_ACX/NOT_DECLARED"}))
    with pytest.raises(LinkError, match=r"request = .*NOT_DECLARED"):
        await link.connect()


async def test_the_servers_refusals_as_a_plain_client_meets_them(truth):
    """File system (Part 20 status codes), Select, R parameter types, and no NC start."""
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, security="none", plc_starts=False)
    url = await fe.start()
    try:
        async with Client(url) as c:
            ns = await c.get_namespace_index("SinumerikVarProvider")
            root = await c.nodes.objects.get_child(f"{ns}:Sinumerik")
            folder = await root.get_child([f"{ns}:FileSystem", f"{ns}:Part Programs"])
            d = UaDirectory(folder)
            node_id, _ = await d.create_file("PROBE.MPF", False)
            with pytest.raises(ua.uaerrors.BadBrowseNameDuplicated):
                await d.create_file("PROBE.MPF", False)
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await d.create_file("bad name.txt", False)
            f = UaFile(c.get_node(node_id), 2 | 4)
            await f.open()
            with pytest.raises(ua.uaerrors.BadInvalidState):  # open once for writing
                await UaFile(c.get_node(node_id), 2).open()
            await f.write(b"G4 F1\nM30\n")
            await f.close()
            reader = UaFile(c.get_node(node_id), 1)
            await reader.open()
            with pytest.raises(ua.uaerrors.BadInvalidState):  # a read handle does not write
                await reader.write(b"X")
            assert await reader.read() == b"G4 F1\nM30\n"
            await reader.close()
            methods = await root.get_child(f"{ns}:Methods")
            names = {(await m.read_browse_name()).Name for m in await methods.get_children()}
            assert names == {"Select"}  # no NC start, no reset: the machine does those
            select = await methods.get_child(f"{ns}:Select")
            u32 = ua.VariantType.UInt32
            with pytest.raises(ua.uaerrors.BadInvalidArgument):  # no such program
                await methods.call_method(select, "/_N_MPF_DIR/_N_NONE_MPF", ua.Variant(1, u32))
            with pytest.raises(ua.uaerrors.BadInvalidArgument):  # another channel
                await methods.call_method(select, "/_N_MPF_DIR/_N_PROBE_MPF", ua.Variant(2, u32))
            await methods.call_method(select, "/_N_MPF_DIR/_N_PROBE_MPF", ua.Variant(1, u32))
            sel = c.get_node(f"ns={ns};s=/Channel/ProgramInfo/selectedWorkPProg")
            assert await sel.read_value() == "/_N_MPF_DIR/_N_PROBE_MPF"
            r10 = c.get_node(f"ns={ns};s=/Channel/Parameter/R[u1,10]")
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await r10.write_value(ua.Variant(3, ua.VariantType.Int32))
            await r10.write_value(ua.Variant(3.5, ua.VariantType.Double))
            assert ctrl.variables["R10"] == 3.5
            with pytest.raises(ua.uaerrors.BadNodeIdUnknown):  # beyond MD28050
                await c.get_node(f"ns={ns};s=/Channel/Parameter/R[u1,200]").read_value()
    finally:
        await fe.stop()


async def test_config_errors_name_the_key():
    base = {"transport": "sinumerik", "url": "opc.tcp://10.0.0.21:4840", "security": "none"}
    for extra, match in (({"nodes": {"requets": "ns=2;s=/x"}}, "unknown role"),
                         ({"nodes": {"request": "R1"}}, "not an OPC UA node id"),
                         ({"program_name": "rumba prog"}, "part-program name"),
                         ({"channel": 0}, "channel"),
                         ({"colour": "red"}, "colour")):
        with pytest.raises(ConfigError, match=match):
            link_config({**base, **extra})
    with pytest.raises(ConfigError, match="certificate"):
        link_config({**base, "security": "Basic256Sha256_SignAndEncrypt"})


async def test_a_program_without_the_handshake_is_refused_before_anything_is_written(truth):
    ctrl = VirtualController(truth, dialect="siemens")
    fe = SinumerikFrontend(ctrl, security="none")
    await fe.start()
    link = SinumerikLink(SinumerikLinkConfig(transport="sinumerik", url=fe.endpoint,
                                             security="none"))
    await link.connect()
    try:
        with pytest.raises(LinkError, match="no result handshake"):
            async for _ in link.run(job_for(truth, handshake=False)):
                pass
        assert fe.folders["Part Programs"].files == {}
    finally:
        await link.close()
        await fe.stop()


async def test_compensation_program_into_part_programs_not_selected(pki, secure, truth):
    """The reviewed $TC_CARR program goes into "Part Programs" (a second one replaces it), is
    neither selected nor started; a control that cannot be reached is one clear error."""
    from drivers.sinumerik.transfer import send_part_program, send_part_program_blocking

    ctrl, fe = secure
    text = "; RUMBA COMPENSATION\n$TC_CARR15[1]=-0.038056\nM30\n"
    selected_before = fe.selected
    assert await send_part_program(secure_cfg(pki, fe), "RUMBA_CARR", text) == "RUMBA_CARR.MPF"
    cfg = secure_cfg(pki, fe)
    assert await asyncio.to_thread(send_part_program_blocking, cfg, "RUMBA_CARR",
                                   text.replace("-0.038056", "0")) == "RUMBA_CARR.MPF"
    f = fe.folders["Part Programs"].file("RUMBA_CARR.MPF")
    assert f is not None and b"$TC_CARR15[1]=0\n" in f.data
    assert fe.selected is selected_before and ctrl.state not in ("running", "hold")
    with pytest.raises(LinkError, match="part-program name"):
        await send_part_program(cfg, "rumba carr", text)
    dead = SinumerikLinkConfig(transport="sinumerik", url="opc.tcp://127.0.0.1:9/",
                               security="none", connect_timeout_s=1)
    with pytest.raises(LinkError, match="refused"):
        await send_part_program(dead, "RUMBA_CARR", text)
