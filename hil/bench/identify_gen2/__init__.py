"""The second, independent trace generator of ``hil bench identify`` (issue 30 item 5).

Written without the replay's code and without the first generator's
(:mod:`hil.bench.identify_gen`): a hand-written fixed-step Runge-Kutta integrator of the axis
equations with the stick-slip switch located inside the step, a cascade controller written
from the servo-trace format's text (shared docs, ``trace-format.md``), its own encoders and
current ADC, and a setpoint of sine-squared velocity pulses.  The machine file is only read
for its values (``plant.config.load_machine``); the trace is written in the trace format
(``hil.trace_file.write_trace``).  ``tests/test_bench_identify_gen2.py`` checks that nothing
here imports ``hil.identify``, ``hil.controller``, the plant's kernel or the first generator.

Modules: :mod:`.program` (setpoint), :mod:`.axis` (equations' constants from a machine
file), :mod:`.loop` (the compiled closed loop), :mod:`.trace` (a run, its floor, the file),
:mod:`.cases` (the bench's traces).
"""
