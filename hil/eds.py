"""``hil eds``: the electronic data sheet (CiA 306 EDS) of the drive ``hil run`` serves, and
its device configuration file (DCF), for a master to import.

::

    hil eds configs/arrow500_x.toml --out eds/ \
        --adapter 'can://udp_multicast/239.74.163.2?node=5&rated_current_ma=28000'

writes ``eds/node5.eds`` and ``eds/node5.dcf`` (one pair per node of a machine of several
axes), and for CAN tools ``eds/nodes.dbc`` and ``eds/nodes.viewer``: every node's PDOs as
they power up, as a DBC and as python-can's ``can.viewer`` decode file
(:mod:`hil.dbc`).  The EDS describes the device: ``[DeviceInfo]`` (vendor, product code, revision,
every CiA 301 bit rate, dynamic PDO mapping: ``Granularity=8``, four RPDOs and four
TPDOs) and every object of :mod:`io_adapters.cia402_objects` with its data type, access
type, PDO mapping, limits (``LowLimit``/``HighLimit``) and ``DefaultValue``: the value the
drive powers up with for this machine file and URL (the node's COB-IDs as ``$NODEID+...``).
The DCF is the EDS for one node with ``[DeviceComissioning]`` (node-ID, bit rate) and every
object's ``ParameterValue``.  Numbers are written as CiA 306 has them: unsigned in hex,
signed in decimal with their sign (canopen's own writer writes -2**31 as 0x-80000000,
which no tool reads back).

:func:`device_values` gives the values without files (what the tests compare the running
drive's answers with).
"""

import argparse
import datetime
from dataclasses import dataclass
from pathlib import Path

from hil.dbc import pdo_frames, write_dbc, write_viewer
from hil.drive import DriveSet, EmulatedDrive
from hil.drive.objects import DriveObjects
from hil.runtime.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    check_link,
    eprint,
    start_positions,
)
from io_adapters import AdapterConfigError, Role
from io_adapters.can_bus_time import BIT_RATES
from io_adapters.can_catalog import (
    COMPOUNDS,
    FEEDBACK,
    INPUTS,
    PRODUCT_CODE,
    PRODUCT_NAME,
    REVISION,
    VENDOR_ID,
    VENDOR_NAME,
    entries,
    spec,
)
from io_adapters.can_dictionary import NodeDictionary
from io_adapters.can_url import CanLink, parse_can_url
from io_adapters.cia402_objects import drive_object_dictionary
from io_adapters.messages import SetpointBounds
from plant import Plant
from plant.errors import ConfigError
from plant.machines import load_machine_set

SIGNED = {0x2, 0x3, 0x4}   # INTEGER8, 16, 32
VAR, ARRAY, RECORD = 0x7, 0x8, 0x9
#: COB-IDs that are 80h/180h... + node-ID: written as $NODEID+base
NODE_RELATIVE = {(0x1014, 0)} | {(c + n, 1) for c in (0x1400, 0x1800) for n in range(4)}
#: what the drive measures or the master sends: 0 at power-up, whatever it is later
DYNAMIC = frozenset((*INPUTS, *FEEDBACK, (0x6062, 0), (0x60F4, 0), (0x60FD, 0)))


@dataclass
class _Owner:
    """What a node's dictionary reads of the endpoint: the drive's objects and bounds."""
    objects: DriveObjects
    setpoint_bounds: tuple[SetpointBounds, ...]


@dataclass(frozen=True)
class DeviceValues:
    """One node's objects as it powers up.

    Attributes:
        node: the node-ID.
        values: (index, sub-index) -> value on the wire.
        limits: (index, sub-index) -> (low, high) of the writable objects (None: the type's).
        bitrate: bit/s.
    """
    node: int
    values: dict
    limits: dict
    bitrate: int


def device_values(config: Path, url: str) -> list[DeviceValues]:
    """The power-on values of every node ``hil run config --adapter url`` serves."""
    machine = load_machine_set(config)
    link = parse_can_url(check_link(url, len(machine.axes)), Role.DEVICE)
    x0 = start_positions(machine, 0.0)
    drives = DriveSet([EmulatedDrive(Plant(c, table_pos=x)) for c, x in zip(machine.configs,
                                                                             x0)])
    owner = _Owner(DriveObjects(drives.drives, link.rated_current_ma / 1e3),
                   tuple(d.setpoint_bounds() for d in drives.drives))
    return [_node_values(axis, node, link, owner) for axis, node in enumerate(link.nodes)]


def _node_values(axis: int, node: int, link: CanLink, owner: _Owner) -> DeviceValues:
    dictionary = NodeDictionary(node, link, axis, owner)
    od = drive_object_dictionary(node, link.rated_current_ma, link.rated_torque_mnm,
                                 link.heartbeat_consumer)
    values, limits = {}, {}
    for key in entries():
        value = 0 if key in DYNAMIC else dictionary.read(*key)
        if value is None:
            obj = od[key[0]]
            value = (obj[key[1]] if key[0] in COMPOUNDS else obj).default
        values[key] = value
        if spec(*key).writable:
            limits[key] = dictionary.limits(*key)
    return DeviceValues(node, values, limits, link.bitrate)


def _number(data_type: int, value: int) -> str:
    return str(value) if data_type in SIGNED else f"0x{value:X}"


def _object(lines: list, key: tuple[int, int], dev: DeviceValues, dcf: bool) -> None:
    s = spec(*key)
    value = dev.values[key]
    default = (f"$NODEID+0x{value - dev.node:X}" if key in NODE_RELATIVE
               else _number(s.data_type, value))
    lines += [f"ParameterName={s.name}", f"ObjectType=0x{VAR:X}",
              f"DataType=0x{s.data_type:04X}", f"AccessType={s.access}",
              f"DefaultValue={default}", f"PDOMapping={int(s.pdo)}"]
    low, high = dev.limits.get(key, (None, None))
    if low is not None:
        lines.append(f"LowLimit={_number(s.data_type, low)}")
    if high is not None:
        lines.append(f"HighLimit={_number(s.data_type, high)}")
    if dcf:
        lines.append(f"ParameterValue={_number(s.data_type, value)}")


#: the objects every CANopen device has (CiA 301): device type, error register, identity
MANDATORY = (0x1000, 0x1001, 0x1018)
#: CiA 301's manufacturer-specific profile area, which CiA 306 lists as ManufacturerObjects
MANUFACTURER_AREA = (0x2000, 0x5FFF)


def _section_list(lines: list, name: str, indexes: list[int]) -> None:
    lines += ["", f"[{name}]", f"SupportedObjects={len(indexes)}"]
    lines += [f"{n}=0x{index:04X}" for n, index in enumerate(indexes, start=1)]


def write_eds(dev: DeviceValues, path: Path, dcf: bool = False) -> Path:
    """Write the EDS (or, with ``dcf``, the DCF) of one node to ``path``."""
    now = datetime.datetime.now()
    lines = ["[FileInfo]", f"FileName={path.name}", "FileVersion=1", "FileRevision=0",
             "EDSVersion=4.0", f"Description={PRODUCT_NAME}, node {dev.node}",
             f"CreationTime={now:%I:%M%p}", f"CreationDate={now:%m-%d-%Y}",
             "CreatedBy=hil eds", "", "[DeviceInfo]", f"VendorName={VENDOR_NAME}",
             f"VendorNumber=0x{VENDOR_ID:08X}", f"ProductName={PRODUCT_NAME}",
             f"ProductNumber=0x{PRODUCT_CODE:08X}", f"RevisionNumber=0x{REVISION:08X}",
             "OrderCode=", *(f"BaudRate_{b // 1000}=1" for b in BIT_RATES),
             "SimpleBootUpMaster=0", "SimpleBootUpSlave=1", "Granularity=8",
             "DynamicChannelsSupported=0", "GroupMessaging=0", "NrOfRXPDO=4", "NrOfTXPDO=4",
             "LSS_Supported=0", "", "[DummyUsage]",
             *(f"Dummy{i:04d}=0" for i in range(1, 8))]
    if dcf:
        lines += ["", "[DeviceComissioning]", f"NodeID={dev.node}",
                  f"NodeName=node{dev.node}", f"Baudrate={dev.bitrate // 1000}", "NetNumber=0",
                  "NetworkName=", "CANopenManager=0", "LSS_SerialNumber=0"]
    indexes = sorted({i for i, _ in dev.values})
    # CiA 306: the manufacturer-specific profile area in its own list, every other object
    # (communication and device profile areas) mandatory or optional
    manufacturer = [i for i in indexes if MANUFACTURER_AREA[0] <= i <= MANUFACTURER_AREA[1]]
    _section_list(lines, "MandatoryObjects", list(MANDATORY))
    _section_list(lines, "OptionalObjects", [i for i in indexes if i not in MANDATORY
                                             and i not in manufacturer])
    _section_list(lines, "ManufacturerObjects", manufacturer)
    for index in indexes:
        lines += ["", f"[{index:04X}]"]
        if index in COMPOUNDS:
            comp = COMPOUNDS[index]
            lines += [f"ParameterName={comp.name}",
                      f"ObjectType=0x{RECORD if comp.record else ARRAY:X}",
                      f"SubNumber={len(comp.members) + 1}"]
            for sub in (0, *comp.members):
                lines += ["", f"[{index:04X}sub{sub:X}]"]
                _object(lines, (index, sub), dev, dcf)
        else:
            _object(lines, (index, 0), dev, dcf)
    path.write_text("\n".join(lines) + "\n")
    return path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil eds``."""
    p.add_argument("config", help="machine file (TOML), or a manifest of several axes")
    p.add_argument("--adapter", required=True, metavar="URL",
                   help="the can:// URL hil run serves (node-ID, rated current, bit rate)")
    p.add_argument("--out", default="eds", metavar="DIR",
                   help="folder for nodeN.eds and nodeN.dcf (default %(default)s)")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil eds``: write the files, print their names; 2 on a bad machine file or URL."""
    try:
        nodes = device_values(Path(args.config), args.adapter)
    except (ConfigError, AdapterConfigError, ValueError) as e:
        eprint(f"hil eds: {e}")
        return EXIT_BAD_INPUT
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for dev in nodes:
        for dcf, suffix in ((False, "eds"), (True, "dcf")):
            print(write_eds(dev, out / f"node{dev.node}.{suffix}", dcf))
    frames = [f for dev in nodes for f in pdo_frames(dev.node, dev.values)]
    print(write_dbc(frames, out / "nodes.dbc"))
    print(write_viewer(frames, out / "nodes.viewer"))
    return EXIT_OK
