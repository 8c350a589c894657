"""LinuxCNC drives the emulated machine: ``hil linuxcnc`` (:mod:`hil.linuxcnc.command`).

* :mod:`hil.linuxcnc.install`: where LinuxCNC is (a prefix or installed), how its programs
  are started (a private mount namespace with overlays when it is in a prefix), and the
  feeddrive HAL component (``hal/feeddrive.c``) built with ``halcompile``;
* :mod:`hil.linuxcnc.session`: ``hil run`` and LinuxCNC side by side, and what they recorded;
* :mod:`hil.linuxcnc.verdict`: PASS or FAIL with the reasons;
* ``display.py``: the headless DISPLAY program LinuxCNC runs in its own Python.

The component speaks the fixed binary wire (:mod:`io_adapters.codec_fixed`); a LinuxCNC
machine configuration for it is ``configs/linuxcnc/arrow500_xyz.ini``.
"""
