"""``hil export --to mdf4`` as a measurement engineer opens it: the CiA 402 words and
enums as text, counts as integers with their twin in table units, one unit convention,
compressed data blocks.

References: asammdf reading the file back (raw values and its own conversions), the
recording's own values, hil.cia402's State, ModeOfOperation and STATUSWORD_BITS (the
project's one definition of the names), the run's metadata (the scale factors), an
uncompressed save of the same file by asammdf, and the MDF4 block id of a compressed data
block (``##DZ``, ASAM MDF 4).  The real run's export: test_recording_processes.py.
"""

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from hil.cia402 import STATUSWORD_BITS, ModeOfOperation, State
from hil.drive.faults import ERROR_CODE, Cause
from hil.runtime import mdf_channels
from hil.runtime.export import export_mdf4
from hil.runtime.record_reader import Recording
from hil.runtime.record_writer import RecordingWriter
from hil.runtime.run_events import EventCollector
from hil.runtime.run_folder import EVENTS, RECORDING, RunFolder
from hil.runtime.stream_file import META_KEY, UNCHECKED_FORMAT
from hil.runtime.watchdog import Watchdog
from io_adapters.messages import MODE_CSP, MODE_VOLTAGE
from plant import Plant, load_machine
from plant import layout as L
from tests.test_recording import ARROW, PERIOD_NS, Rig

asammdf = pytest.importorskip("asammdf")

MACHINE = load_machine(ARROW)
#: the machine's m per motor-encoder count (as hil run's metadata gives it) and per scale count
TABLE_PER_COUNT = (Plant(MACHINE).built.ratio
                   / Plant(MACHINE).params[L.P_ENC_COUNTS_PER_RAD])
SCALE_M = MACHINE.sensors.scale_resolution_m
#: controlword per range of ticks: disabled, shutdown (-> READY TO SWITCH ON), switch on
#: (-> SWITCHED ON), enable operation (-> OPERATION ENABLED)
CONTROLWORDS = ((0, 0), (40, 0x06), (80, 0x07), (120, 0x0F))


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Recording]:
    """A real drive's recording (through the enable sequence, 160 ticks in 4 batches) with
    an axis X in its metadata, exported to MDF4."""
    folder = tmp_path_factory.mktemp("mdf")
    rig = Rig(Plant(MACHINE, table_pos=0.25), slots=256)
    watchdog = Watchdog(800, PERIOD_NS * 1e-9, lambda line: None)
    meta = {"period_ns": PERIOD_NS,
            "axes": [{"name": "X", "kind": "screw", "prefix": "", "machine_file": str(ARROW),
                      "table_per_count": TABLE_PER_COUNT, "scale_resolution_m": SCALE_M}]}
    writer = RecordingWriter(RunFolder.open(folder / "run"), rig.recorder,
                             EventCollector(("X",), rig.drives, watchdog, rig.recorder),
                             meta, PERIOD_NS, lambda failure: None)
    for k in range(160):
        rig.sp.controlword = next(cw for first, cw in reversed(CONTROLWORDS) if k >= first)
        rig.tick(k)
        if k % 40 == 39:
            writer.flush()
    writer.stop([])
    writer.folder.close()
    rec = Recording(folder / "run")
    return export_mdf4(rec, folder / "run.mf4"), rec


def test_the_cia402_state_mode_and_fault_read_as_their_names(exported):
    """drive_state's samples are the names of hil.cia402.State for the raw values, and the
    run went through four of them; sp_mode's the ModeOfOperation names; fb_fault's 0 is
    "no error"; the raw values stay integers."""
    out, rec = exported
    rows = rec.read(["drive_state", "sp_mode", "fb_fault"])
    with asammdf.MDF(out) as mdf:
        state = mdf.get("drive_state")
        raw = mdf.get("drive_state", raw=True).samples
        assert raw.dtype == np.uint8 and raw.tolist() == rows["drive_state"].tolist()
        assert [s.decode() for s in state.samples] == [State(v).name for v in raw]
        assert {State.SWITCH_ON_DISABLED.name, State.READY_TO_SWITCH_ON.name,
                State.SWITCHED_ON.name, State.OPERATION_ENABLED.name} <= \
            {s.decode() for s in state.samples}
        modes = mdf.get("sp_mode").samples
        assert [m.decode() for m in modes] == [ModeOfOperation(v).name
                                               for v in rows["sp_mode"]]
        assert {f.decode() for f in mdf.get("fb_fault").samples} == {"no error"}


def test_the_statusword_reads_as_its_set_bits_by_their_cia402_names(exported):
    """Each fb_statusword sample is the CiA 402 names of exactly the bits set in the raw
    word (hil.cia402.STATUSWORD_BITS), joined by |; OPERATION ENABLED shows "Operation
    enabled", SWITCH ON DISABLED "Switch on disabled"."""
    out, rec = exported
    words = rec.read(["fb_statusword"])["fb_statusword"]
    with asammdf.MDF(out) as mdf:
        texts = [t.decode() for t in mdf.get("fb_statusword").samples]
        assert mdf.get("fb_statusword", raw=True).samples.tolist() == words.tolist()
    for word, text in zip(words, texts):
        assert set(text.split("|")) - {""} == {name for mask, name in STATUSWORD_BITS.items()
                                               if word & mask}
    assert "Switch on disabled" in texts[0].split("|")
    assert "Operation enabled" in texts[-1].split("|")


def test_counts_are_integers_with_a_twin_in_metres_from_the_run_metadata(exported):
    """plant_encoder_counts and plant_scale_counts (whole numbers) are int64 in the file
    with their values; plant_encoder_pos and plant_scale_pos are the same raw counts times
    the metadata's table_per_count and scale_resolution_m, in m like plant_table_pos, and
    within 20 µm of it (the motor encoder differs by the screw's wind-up under the current)."""
    out, rec = exported
    rows = rec.read(["plant_encoder_counts", "plant_scale_counts", "plant_table_pos"])
    with asammdf.MDF(out) as mdf:
        for counts, twin, factor in (("plant_encoder_counts", "plant_encoder_pos",
                                      TABLE_PER_COUNT),
                                     ("plant_scale_counts", "plant_scale_pos", SCALE_M)):
            raw = mdf.get(counts, raw=True).samples
            assert raw.dtype == np.int64 and mdf.get(counts).unit == "counts"
            np.testing.assert_array_equal(raw, rows[counts])
            pos = mdf.get(twin)
            assert pos.unit == mdf.get("plant_table_pos").unit == "m"
            np.testing.assert_allclose(pos.samples, rows[counts] * factor, rtol=1e-15)
            np.testing.assert_allclose(pos.samples, rows["plant_table_pos"], atol=2e-5)


def test_every_unitless_channel_has_the_one_empty_unit(exported):
    """No channel carries the recording's "1" or "-": a count (tick, sp_seq), a CiA word
    (fb_statusword), an enum (drive_state) and an event's code all have the unit ""."""
    out, _ = exported
    with asammdf.MDF(out) as mdf:
        units = {ch.name: ch.unit for group in mdf.groups for ch in group.channels}
    assert not {"1", "-"} & set(units.values()), units
    assert {units[n] for n in ("tick", "sp_seq", "fb_statusword", "drive_state",
                               "drive_enable", "plant_limit_neg")} == {mdf_channels.NO_UNIT}
    assert units["plant_table_pos"] == "m" and units["lateness_ns"] == "ns"


def test_the_file_is_compressed(exported, tmp_path):
    """The data are in compressed blocks (##DZ), and the file is under half of asammdf's
    uncompressed save of the same measurement."""
    out, _ = exported
    plain = tmp_path / "plain.mf4"
    with asammdf.MDF(out) as mdf:
        mdf.save(plain, overwrite=True, compression=0)
    data = out.read_bytes()
    assert b"##DZ" in data and b"##DZ" not in plain.read_bytes()
    assert out.stat().st_size < 0.5 * plain.stat().st_size


def _hand_made(folder: Path, columns: dict[str, tuple[np.ndarray, str]], axes: list) -> Path:
    """A run folder of the format before the checksums holding ``columns`` (name ->
    (values, unit)) with ``axes`` in its metadata, and no events."""
    meta = json.dumps({"format": UNCHECKED_FORMAT, "period_ns": PERIOD_NS,
                       "axes": axes}).encode()
    fields = [pa.field(n, pa.from_numpy_dtype(v.dtype), metadata={"unit": u, "doc": n})
              for n, (v, u) in columns.items()]
    table = pa.table({n: v for n, (v, _) in columns.items()},
                     schema=pa.schema(fields, metadata={META_KEY: meta}))
    events = pa.table({"tick": pa.array([], pa.int64())})
    folder.mkdir()
    for name, t in ((RECORDING, table), (EVENTS, events)):
        with pa.ipc.new_stream(str(folder / name),
                               t.schema.with_metadata({META_KEY: meta})) as w:
            for batch in t.to_batches(max_chunksize=7):
                w.write_batch(batch)
    return folder


def test_axes_by_prefix_a_rotary_twin_in_rad_and_fractional_setpoints_kept(tmp_path):
    """Two axes (X screw, C rotary): each prefixed column gets its axis's conversion and
    factor -- C's encoder twin in rad (its plant_table_pos's unit), X's drive_state as
    text; X's CSP target in fractional counts (as a controller on udp:// sends them) stays
    float64 to the last digit, its whole encoder counts become int64; a mode not in
    ModeOfOperation reads "unknown"; the voltage mode (-1) "VOLTAGE"; fault code 8612h
    names both causes that give it."""
    n = 20
    target = 1000.25 + np.arange(n) * 0.5
    axes = [{"name": "X", "kind": "screw", "prefix": "X_", "table_per_count": 1e-8,
             "scale_resolution_m": 0.0},
            {"name": "C", "kind": "rotary", "prefix": "C_", "table_per_count": 1e-6,
             "scale_resolution_m": 0.0}]
    modes = np.array([MODE_CSP, MODE_VOLTAGE, 2] + [MODE_CSP] * (n - 3), np.int8)
    fault = np.zeros(n, np.uint16)
    fault[5] = ERROR_CODE[Cause.LIMIT_SWITCH]
    folder = _hand_made(tmp_path / "run", {
        "tick": (np.arange(n, dtype=np.int64), "1"),
        "X_sp_mode": (modes, "-"),
        "X_fb_fault": (fault, "-"),
        "X_sp_target_position_counts": (target, "counts"),
        "X_plant_encoder_counts": (np.round(target), "counts"),
        "X_plant_table_pos": (target * 1e-8, "m"),
        "X_drive_state": (np.full(n, State.FAULT, np.uint8), "-"),
        "C_plant_encoder_counts": (np.arange(n, dtype=np.float64) * 1000, "counts"),
        "C_plant_table_pos": (np.arange(n) * 1e-3, "rad")}, axes)
    out = export_mdf4(Recording(folder), tmp_path / "r.mf4")
    with asammdf.MDF(out) as mdf:
        sp = mdf.get("X_sp_target_position_counts", raw=True).samples
        assert sp.dtype == np.float64 and sp.tolist() == target.tolist()
        np.testing.assert_allclose(mdf.get("X_sp_target_position").samples, target * 1e-8)
        assert mdf.get("X_plant_encoder_counts", raw=True).samples.dtype == np.int64
        c = mdf.get("C_plant_encoder_pos")
        assert c.unit == "rad"
        np.testing.assert_allclose(c.samples, np.arange(n) * 1000 * 1e-6)
        assert set(mdf.get("X_drive_state").samples) == {b"FAULT"}
        assert [m.decode() for m in mdf.get("X_sp_mode").samples[:3]] == \
            ["CSP", "VOLTAGE", "unknown"]
        assert mdf.get("X_fb_fault").samples[5].decode() == "SOFTWARE_LIMIT or LIMIT_SWITCH"
        assert "C_drive_state" not in mdf.channels_db and "X_plant_scale_pos" not in \
            mdf.channels_db
