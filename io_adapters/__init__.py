"""Transports between a controller and the emulator (UDP, CAN, serial).

``io_adapters`` imports nothing from ``plant`` or ``hil``.  The adapters
arrive with the real-time runtime (issue 4); this package holds the place in
the data flow controller -> adapter -> loop -> plant -> adapter -> controller.
"""
