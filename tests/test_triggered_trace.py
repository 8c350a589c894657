"""``hil sim --trigger``: the servo trace with trigger (level or edge, pre-trigger rows), as
the NC's servo trace offers it."""

from hil.cli import main
from hil.trace_file import read_trace
from tests.conftest import CONFIGS, ROOT

ARROW = CONFIGS / "arrow500_x.toml"
PROGRAM = ROOT / "programs" / "demo_moves.nc"


def test_level_trigger_keeps_the_pre_trigger_rows(tmp_path):
    """Definition of a rising level trigger (hil.measure.trace): the row at index
    ``pre`` is the first at or above the level, the one before it below; ``depth`` rows in
    all, at the position-control cycle like trace.csv, and the rows are trace.csv's own."""
    out = tmp_path / "sim"
    code = main(["sim", str(ARROW), "--program", str(PROGRAM), "--out", str(out),
                 "--trigger", "vel_set_mm_min:10000:rising", "--depth", "300",
                 "--pre-trigger", "50"])
    assert code == 0
    trig = read_trace(out / "triggered.csv")
    full = read_trace(out / "trace.csv")
    v = trig.column("vel_set_mm_min")
    assert trig.n_samples == 300
    assert v[49] < 10000.0 <= v[50]
    assert trig.sample_time_s == full.sample_time_s
    first = int(round((full.column("vel_set_mm_min") >= 10000.0).argmax())) - 50
    assert (trig.column("pos_mm") == full.column("pos_mm")[first:first + 300]).all()


def test_bad_trigger_is_refused(tmp_path, capsys):
    """A trigger on a column trace.csv does not have is refused with exit 2, naming it."""
    code = main(["sim", str(ARROW), "--program", str(PROGRAM), "--out", str(tmp_path / "x"),
                 "--trigger", "speed:3:up"])
    assert code == 2
    assert "speed" in capsys.readouterr().err
