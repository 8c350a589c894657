"""The electronic data sheet (CiA 306 EDS and DCF, ``hil eds``) against canopen's own
reader, and the running drive against the EDS.

References: canopen's ``import_od`` (an implementation nobody here wrote) reads every
object back with the type, access, PDO mapping, limits and default the catalog
(:mod:`io_adapters.can_catalog`) and the drive's power-on values give it; CiA 306's
DeviceInfo keys; and the drive itself, asked by SDO through canopen's client: every
object the EDS declares answers its declared default (what the drive measures or the
master sends excepted), and a write one step beyond a declared limit is refused with
CiA 301's "too high" / "too low" abort.
"""

import argparse
import configparser
import re

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord
from canopen.sdo import SdoAbortedError

from hil.drive import EmulatedDrive
from hil.drive.objects import DriveObjects
from hil.eds import DYNAMIC, add_arguments, device_values, run_from_args, write_eds
from io_adapters import open_endpoint
from io_adapters.can_catalog import (
    INT_RANGE,
    PRODUCT_CODE,
    REVISION,
    VENDOR_ID,
    entries,
    spec,
)
from plant import Plant
from plant.config import load_machine
from tests.conftest import CONFIGS
from tests.test_can_cia402 import master_network, no_leaked_threads, virtual_channel  # noqa: F401

ARROW = CONFIGS / "arrow500_x.toml"
XY = CONFIGS / "machines" / "arrow500_xy.toml"
NODE, RATED_MA = 5, 28000
QUERY = f"node={NODE}&rated_current_ma={RATED_MA}&sync_timeout_ms=60000"
ABORT_HIGH, ABORT_LOW = 0x06090031, 0x06090032


def imported(tmp_path, dcf: bool = False, config=ARROW, url=None):
    url = url or f"can://virtual/x?{QUERY}&bitrate=500000"
    dev = device_values(config, url)[0]
    path = write_eds(dev, tmp_path / f"node{NODE}.{'dcf' if dcf else 'eds'}", dcf)
    return dev, canopen.import_od(str(path), None if dcf else NODE)


def variables(od):
    for index in od:
        obj = od[index]
        yield from obj.values() if isinstance(obj, (ODRecord, ODArray)) else [obj]


def test_canopens_reader_takes_every_object_as_the_catalog_declares_it(tmp_path):
    dev, od = imported(tmp_path)
    seen = set()
    for var in variables(od):
        key = (var.index, var.subindex)
        s = spec(*key)
        low, high = dev.limits.get(key, (None, None))
        assert (var.data_type, var.access_type, var.pdo_mappable) == \
            (s.data_type, s.access, s.pdo), key
        assert var.default == dev.values[key], key
        assert (var.min, var.max) == (low, high), key
        seen.add(key)
    assert seen == set(entries())
    # a negative default and limit read back as such (canopen's own writer writes
    # -2**31 as 0x-80000000, which its reader cannot take)
    assert od[0x607D][1].min is None and od[0x60C2][2].min == -6
    assert od[0x60C2][2].default == -3
    assert od[0x1800][1].default == 0x180 + NODE  # $NODEID+0x180


def test_every_object_is_listed_once_in_the_section_of_its_index_range(tmp_path):
    """As an EDS checker reads CiA 306: MandatoryObjects holds 1000h, 1001h and 1018h;
    ManufacturerObjects every object of 2000h-5FFFh (2F00h, the fault injection, is
    there); OptionalObjects the rest of 1000h-1FFFh and 6000h-FFFFh; each list's
    SupportedObjects is its count, numbered 1..N, and every object section of the file is
    in exactly one list."""
    imported(tmp_path)
    eds = configparser.ConfigParser()
    eds.optionxform = str
    eds.read(tmp_path / f"node{NODE}.eds")
    listed = {}
    for name in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        section = eds[name]
        n = int(section["SupportedObjects"])
        assert set(section) == {"SupportedObjects", *map(str, range(1, n + 1))}, name
        listed[name] = [int(section[str(k)], 16) for k in range(1, n + 1)]
    assert listed["MandatoryObjects"] == [0x1000, 0x1001, 0x1018]
    assert 0x2F00 in listed["ManufacturerObjects"]
    assert all(0x2000 <= i <= 0x5FFF for i in listed["ManufacturerObjects"])
    assert all(i < 0x2000 or i >= 0x6000 for i in listed["OptionalObjects"])
    objects = [int(name, 16) for name in eds.sections() if re.fullmatch(r"[0-9A-F]{4}", name)]
    every = [i for indices in listed.values() for i in indices]
    assert sorted(every) == sorted(objects) and len(set(every)) == len(every)


def test_device_info_says_what_the_drive_is(tmp_path):
    _, od = imported(tmp_path)
    info = od.device_information
    assert (info.vendor_number, info.product_number, info.revision_number) == \
        (VENDOR_ID, PRODUCT_CODE, REVISION)
    assert info.allowed_baudrates == {10_000, 20_000, 50_000, 125_000, 250_000, 500_000,
                                      800_000, 1_000_000}
    assert (info.nr_of_RXPDO, info.nr_of_TXPDO) == (4, 4)
    assert info.vendor_name and info.product_name
    # canopen reads Granularity as a flag; CiA 306 has the mapping's granularity in bits
    eds = configparser.ConfigParser()
    eds.read(tmp_path / f"node{NODE}.eds")
    assert eds["DeviceInfo"]["Granularity"] == "8"  # dynamic PDO mapping, byte by byte


def test_the_dcf_carries_the_node_and_its_values(tmp_path):
    dev, od = imported(tmp_path, dcf=True)
    assert (od.node_id, od.bitrate) == (NODE, 500_000)
    for var in variables(od):
        assert var.value == dev.values[(var.index, var.subindex)], (var.index, var.subindex)
    # the machine file's values, not CiA's: 1006h 1 ms, 60C2h the same, 6502h truthful
    assert od[0x1006].value == 1000 and (od[0x60C2][1].value, od[0x60C2][2].value) == (1, -3)
    assert od[0x6502].value == 0x3A5  # PP, PV, homing, CSP, CSV, CST
    assert od[0x608F][1].value == 4194304  # the encoder's increments per revolution


def test_the_running_drive_answers_what_the_eds_declares(tmp_path):
    """The node as ``hil run`` sets it up (the drive's objects and bounds attached), asked
    by canopen's SDO client with the imported EDS: each declared default comes back, and
    a write one step beyond a declared limit is refused."""
    channel = virtual_channel()
    url = f"can://virtual/{channel}?{QUERY}"
    _, od = imported(tmp_path, url=url)
    drive = EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.0))
    network = master_network()
    with open_endpoint(url, "device") as ep:
        ep.setpoint_bounds = (drive.setpoint_bounds(),)
        ep.objects = DriveObjects([drive], ep.rated_current_a)
        try:
            network.connect(interface="virtual", channel=channel)
            node = network.add_node(NODE, od)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            answered = 0
            for var in variables(od):
                key = (var.index, var.subindex)
                if key in DYNAMIC:
                    continue
                assert node.sdo.upload(*key) == var.encode_raw(var.default), key
                answered += 1
            refused = 0
            for var in variables(od):
                lo, hi = INT_RANGE[var.data_type]
                for limit, beyond, code in ((var.max, 1, ABORT_HIGH), (var.min, -1, ABORT_LOW)):
                    if var.access_type != "rw" or limit is None or not lo <= limit + beyond <= hi:
                        continue
                    with pytest.raises(SdoAbortedError) as e:
                        node.sdo.download(var.index, var.subindex,
                                          var.encode_raw(limit + beyond))
                    assert e.value.code == code, (var.index, var.subindex)
                    refused += 1
        finally:
            network.disconnect()
    assert answered > 100 and refused > 10


def test_hil_eds_writes_one_pair_per_node(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([str(XY), "--adapter", f"can://udp_multicast/239.74.163.2?{QUERY}",
                              "--out", str(tmp_path)])
    assert run_from_args(args) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["node5.dcf", "node5.eds", "node6.dcf", "node6.eds", "nodes.dbc",
                     "nodes.viewer"]
    dbc = (tmp_path / "nodes.dbc").read_text()
    assert "BO_ 389 TPDO1_node5: 5" in dbc and "BO_ 646 TPDO2_node6: 8" in dbc  # 185h, 286h
    assert "SG_ Position_actual_value_6064 : 0|32@1- (1,0)" in dbc
    assert "286:<ll" in (tmp_path / "nodes.viewer").read_text().splitlines()
    assert canopen.import_od(str(tmp_path / "node6.dcf")).node_id == 6
    too_high = "can://udp_multicast/g?node=127&rated_current_ma=1"
    bad = parser.parse_args([str(XY), "--adapter", too_high, "--out", str(tmp_path)])
    assert run_from_args(bad) == 2
    assert "node-IDs up to 128" in capsys.readouterr().err
