"""The emulated CiA 402 drive around the plant: state machine, modes, monitoring, fault
reaction (:mod:`hil.drive.core`); its parameters (:mod:`hil.drive.config`), fault causes
(:mod:`hil.drive.faults`), monitoring (:mod:`hil.drive.monitor`), braking
(:mod:`hil.drive.reaction`) and own loops (:mod:`hil.drive.loops`).  Every adapter and the
lock-step simulation use this one drive."""

from hil.drive.config import DriveParameters, load_drive
from hil.drive.core import DriveSet, EmulatedDrive
from hil.drive.faults import Cause, FaultEvent, FaultLog
from hil.drive.loops import DriveLoops

__all__ = ["Cause", "DriveLoops", "DriveParameters", "DriveSet", "EmulatedDrive", "FaultEvent",
           "FaultLog", "load_drive"]
