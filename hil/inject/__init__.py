"""Fault and wear injection (issue 14 part 6): the faults (:mod:`hil.inject.catalog`) and
when they act on a plant (:mod:`hil.inject.schedule`).  This module itself imports nothing
(the command line builds its help from it without loading the plant)."""

#: the faults, in the order of :data:`hil.inject.catalog.FAULTS` (a test holds them equal)
FAULT_NAMES = ("friction_growth", "backlash_growth", "preload_loss", "torque_constant_loss",
               "encoder_noise", "encoder_lost_counts", "current_offset", "current_gain_error",
               "torque_ripple")
#: the ``--inject`` option's help, the same for every command that has it
INJECT_HELP = ("inject a fault or wear as an [inject.FAULT] table of the machine file says it "
               "(repeatable), e.g. friction_growth:growth_pct=50,at_s=2,ramp_s=10; faults: "
               f"{', '.join(FAULT_NAMES)} (hil config-keys lists their keys)")
