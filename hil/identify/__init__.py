"""``hil identify``: find the physical effect a machine file is missing from a measured trace.

:mod:`hil.identify.record` reads the measured trace (servo-trace CSV, EMPS ``.mat``),
:mod:`hil.identify.replay` runs the machine file's closed loop on its setpoints.
"""
